"""Image, material and LiDAR metrics (numpy) for ``mi-invrgbl eval``.

Conventions:

* Images are ``(H, W)`` or ``(H, W, C)`` arrays; a ``mask`` is ``(H, W)`` bool
  (or broadcastable to it) and selects the pixels that are scored.
* An empty selection gives NaN (the metric is undefined there), so that
  means over frames can use ``np.nanmean``. NaN in a prediction propagates
  (a broken render is not hidden); pixels where the *target* is not finite
  are never scored.
* PSNR/SSIM compare values as given. The camera observations are 8-bit sRGB,
  so ``eval`` converts a linear render with :func:`linear_to_srgb`, clips to
  [0, 1] and compares in sRGB with ``peak = 1`` (as PSNR is usually reported
  for images); :func:`psnr` does no conversion of its own unless
  ``srgb=True``.
"""

from __future__ import annotations

import math

import numpy as np

# The sRGB curve (physics/colour.py); the metrics' callers take it from here too.
from ..physics.colour import linear_to_srgb, srgb_to_linear  # noqa: F401

#: SSIM constants of Wang et al. 2004.
SSIM_K1, SSIM_K2 = 0.01, 0.03
SSIM_WINDOW, SSIM_SIGMA = 11, 1.5


def _prepare(pred, target, mask):
    p = np.asarray(pred, np.float64)
    t = np.asarray(target, np.float64)
    if p.shape != t.shape:
        raise ValueError("prediction has shape %s, target %s" % (p.shape, t.shape))
    valid = np.isfinite(t)
    if valid.ndim == 3:
        valid = valid.all(axis=2)
    if mask is not None:
        m = np.asarray(mask, bool)
        if m.ndim == 3:
            m = m[..., 0]
        valid = valid & np.broadcast_to(m, valid.shape)
    return p, t, valid


def _select(a, valid):
    return a[valid] if a.ndim == valid.ndim else a[valid].reshape(-1, a.shape[-1])


def mse(pred, target, mask=None) -> float:
    p, t, v = _prepare(pred, target, mask)
    if not v.any():
        return float("nan")
    return float(np.mean((_select(p, v) - _select(t, v)) ** 2))


def rmse(pred, target, mask=None) -> float:
    """Root mean squared error over the selected pixels (all channels)."""
    m = mse(pred, target, mask)
    return float(math.sqrt(m)) if np.isfinite(m) else float("nan")


def mae(pred, target, mask=None) -> float:
    """Mean absolute error over the selected pixels (all channels)."""
    p, t, v = _prepare(pred, target, mask)
    if not v.any():
        return float("nan")
    return float(np.mean(np.abs(_select(p, v) - _select(t, v))))


def psnr(pred, target, peak: float = 1.0, mask=None, srgb: bool = False) -> float:
    """Peak signal-to-noise ratio ``10 log10(peak^2 / MSE)`` in dB.

    With ``srgb=True`` both images are taken as linear, converted with
    :func:`linear_to_srgb` and clipped to [0, 1] first. Identical images
    give ``inf``.
    """
    if srgb:
        pred = np.clip(linear_to_srgb(pred), 0.0, 1.0)
        target = np.clip(linear_to_srgb(target), 0.0, 1.0)
    m = mse(pred, target, mask)
    if not np.isfinite(m):
        return float("nan")
    if m == 0:
        return float("inf")
    return float(10.0 * math.log10(peak * peak / m))


def _gaussian_blur(x, window, sigma):
    import cv2
    return cv2.GaussianBlur(x, (window, window), sigma, sigmaY=sigma,
                            borderType=cv2.BORDER_REFLECT)


def ssim_map(pred, target, peak: float = 1.0, window: int = SSIM_WINDOW,
             sigma: float = SSIM_SIGMA):
    """Per-pixel SSIM of one channel (Wang et al. 2004, Gaussian window).

    Local statistics use an ``window x window`` Gaussian of std ``sigma``
    (``cv2.GaussianBlur``; population variances, as in the original code).
    Returns the map of the 'valid' region (``window // 2`` pixels cropped at
    every side, where the window lies inside the image), or the whole map
    (reflected borders) for images smaller than the window.
    """
    x = np.asarray(pred, np.float64)
    y = np.asarray(target, np.float64)
    c1 = (SSIM_K1 * peak) ** 2
    c2 = (SSIM_K2 * peak) ** 2
    mu_x = _gaussian_blur(x, window, sigma)
    mu_y = _gaussian_blur(y, window, sigma)
    sxx = _gaussian_blur(x * x, window, sigma) - mu_x ** 2
    syy = _gaussian_blur(y * y, window, sigma) - mu_y ** 2
    sxy = _gaussian_blur(x * y, window, sigma) - mu_x * mu_y
    num = (2 * mu_x * mu_y + c1) * (2 * sxy + c2)
    den = (mu_x ** 2 + mu_y ** 2 + c1) * (sxx + syy + c2)
    s = num / den
    r = window // 2
    if x.shape[0] > 2 * r and x.shape[1] > 2 * r:
        return s[r:-r, r:-r], r
    return s, 0


def ssim(pred, target, peak: float = 1.0, mask=None, window: int = SSIM_WINDOW,
         sigma: float = SSIM_SIGMA) -> float:
    """Mean SSIM, computed per channel and averaged over channels.

    Standard constants ``K1 = 0.01, K2 = 0.03`` and an 11 x 11 Gaussian window
    with sigma 1.5. ``mask`` (optional) selects the pixels whose SSIM values
    are averaged (over the valid region, see :func:`ssim_map`). SSIM(x, x) = 1.
    """
    p, t, valid = _prepare(pred, target, mask)
    if p.ndim == 2:
        p, t = p[..., None], t[..., None]
    vals = []
    for c in range(p.shape[2]):
        pc = np.where(valid, p[..., c], 0.0)
        tc = np.where(valid, t[..., c], 0.0)
        s, r = ssim_map(pc, tc, peak, window, sigma)
        v = valid[r:valid.shape[0] - r, r:valid.shape[1] - r] if r else valid
        if not v.any():
            return float("nan")
        vals.append(np.mean(s[v]))
    return float(np.mean(vals))


def angular_error_deg(pred_normals, gt_normals, mask=None, reduce: str = "mean") -> float:
    """Angle between normal maps in degrees (``mean`` or ``median`` over pixels).

    Both maps are normalised per pixel; pixels where either is (near) zero
    are not scored.
    """
    p, t, valid = _prepare(pred_normals, gt_normals, mask)
    np_ = np.linalg.norm(p, axis=-1)
    nt = np.linalg.norm(t, axis=-1)
    valid = valid & (nt > 1e-6) & ~(np_ <= 1e-6)
    if not valid.any():
        return float("nan")
    cos = np.sum(p[valid] * t[valid], axis=-1) / (np_[valid] * nt[valid])
    ang = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return float(np.median(ang) if reduce == "median" else np.mean(ang))


def scale_fit(pred, target, mask=None):
    """Per-channel least-squares scales ``s_c = sum(p t) / sum(p^2)``."""
    p, t, valid = _prepare(pred, target, mask)
    if p.ndim == 2:
        p, t = p[..., None], t[..., None]
    pv, tv = p[valid], t[valid]
    den = np.sum(pv * pv, axis=0)
    return np.where(den > 0, np.sum(pv * tv, axis=0) / np.where(den > 0, den, 1.0), 1.0)


def albedo_rmse_scaled(pred, target, mask=None, per_channel: bool = True) -> float:
    """RMSE after fitting the prediction's scale to the target by least squares.

    Albedo is recovered only up to the scale the lighting leaves free, so
    each channel (or, with ``per_channel=False``, all channels together) is
    scaled by its least-squares factor first. Works for RGB and for 1-channel
    maps (LiDAR albedo). Invariant to scaling ``pred``.
    """
    p, t, valid = _prepare(pred, target, mask)
    if not valid.any():
        return float("nan")
    if per_channel:
        s = scale_fit(p, t, valid)
        scaled = p * (s if p.ndim == 3 else s[0])
    else:
        pv, tv = p[valid].ravel(), t[valid].ravel()
        den = float(np.sum(pv * pv))
        scaled = p * (float(np.sum(pv * tv)) / den if den > 0 else 1.0)
    return rmse(scaled, t, valid)


def ray_drop_accuracy(pred_hit, obs_hit, mask=None) -> float:
    """Fraction of beams whose return / drop the prediction gets right."""
    p = np.asarray(pred_hit) > 0.5
    o = np.asarray(obs_hit) > 0.5
    if p.shape != o.shape:
        raise ValueError("pred_hit has shape %s, obs_hit %s" % (p.shape, o.shape))
    sel = np.ones(p.shape, bool) if mask is None else np.broadcast_to(np.asarray(mask, bool), p.shape)
    if not sel.any():
        return float("nan")
    return float(np.mean(p[sel] == o[sel]))


def range_error(pred_range, obs_range, pred_hit=None, obs_hit=None) -> float:
    """Mean absolute range error over the beams that return in both.

    Without hit maps, a positive finite range counts as a return.
    """
    pr = np.asarray(pred_range, np.float64)
    orr = np.asarray(obs_range, np.float64)
    ph = (np.isfinite(pr) & (pr > 0)) if pred_hit is None else np.asarray(pred_hit) > 0.5
    oh = (np.isfinite(orr) & (orr > 0)) if obs_hit is None else np.asarray(obs_hit) > 0.5
    both = ph & oh & np.isfinite(orr)
    if not both.any():
        return float("nan")
    return float(np.mean(np.abs(pr[both] - orr[both])))
