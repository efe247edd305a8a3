"""Model selection: decide from the data what the scene needs.

* **Sun.** Directional light shows up as shadows and n.l shading: for a
  candidate sun direction ``l``, the stage-1 colour of the Gaussians should
  follow ``s(l) = v(l) max(0, n.l)`` (``v`` = traced visibility). Albedo
  varies far more between surfaces than within one, so the score compares
  *neighbouring* Gaussians on the same surface (close, similar normals):
  the difference of their log luminance should correlate with the
  difference of ``s``. Candidates cover the upper hemisphere and the best
  one is refined locally; a sun is used only if the correlation and the
  fitted sun/sky ratio are clearly above what a sunless scene gives.
* **SH order.** The sky seen directly (pixels with no Gaussian in front) is
  fitted by least squares at orders 0..3 on 80 % of those pixels; the lowest
  order within 2 % of the best error on the other 20 % wins.
"""

from __future__ import annotations

import math

import numpy as np
import drjit as dr
import mitsuba as mi

from ..plugins import hits as hitlib
from ..plugins.lighting import transmittance
from ..plugins.sh import num_coeffs, sh_basis_numpy


def hemisphere_candidates(count=48, min_elevation_deg=5.0):
    """Fibonacci directions on the upper hemisphere (z up) above an elevation."""
    out = []
    golden = (math.sqrt(5) - 1) / 2
    zmin = math.sin(math.radians(min_elevation_deg))
    for i in range(count):
        z = zmin + (1 - zmin) * (i + 0.5) / count
        phi = 2 * math.pi * ((i * golden) % 1.0)
        r = math.sqrt(max(0.0, 1 - z * z))
        out.append((r * math.cos(phi), r * math.sin(phi), z))
    return np.array(out)


def sun_features(scene, centers, normals, directions):
    """``s = v max(0, n.l)`` per Gaussian for each candidate direction (G x D)."""
    nodes = hitlib.gaussian_nodes(scene)
    G = centers.shape[0]
    out = np.zeros((G, len(directions)), np.float32)
    with dr.suspend_grad():
        for k, l in enumerate(directions):
            cos = np.maximum(normals @ l, 0.0)
            o = mi.Point3f(*(centers + 1e-3 * normals).T.astype(np.float32))
            d = mi.Vector3f(*np.tile(np.float32(l), (G, 1)).T)
            vis = np.array(transmittance(scene, o, d, mi.Float(dr.inf), nodes))
            out[:, k] = vis * cos
    return out


def neighbour_pairs(centers, normals, radius=0.5, min_cos=0.9, seed=0):
    """Pairs (i, j) of Gaussians in the same ``radius`` voxel with similar normals."""
    rng = np.random.default_rng(seed)
    keys = np.floor(centers / radius).astype(np.int64)
    keys = keys[:, 0] * 73856093 ^ keys[:, 1] * 19349663 ^ keys[:, 2] * 83492791
    order = np.lexsort((rng.random(len(keys)), keys))
    k = keys[order]
    same = k[1:] == k[:-1]
    i, j = order[:-1][same], order[1:][same]
    ok = np.abs(np.sum(normals[i] * normals[j], axis=1)) >= min_cos
    return i[ok], j[ok]


def choose_sun_pairs(luminance, features, directions, pairs, min_corr=0.2, min_ratio=0.15):
    """Score candidates by the correlation of luminance *differences* between
    neighbouring Gaussians with differences of ``s`` (albedo cancels)."""
    i, j = pairs
    y = np.log(np.maximum(luminance, 1e-4))
    dy = y[i] - y[j]
    corrs = []
    for k in range(features.shape[1]):
        ds = features[i, k] - features[j, k]
        den = np.sqrt(np.sum(ds * ds) * np.sum(dy * dy))
        corrs.append(float(np.sum(ds * dy) / den) if den > 1e-12 else 0.0)
    k = int(np.argmax(corrs))
    s = features[:, k]
    A = np.stack([np.ones_like(s), s], axis=1)
    b0, b1 = np.linalg.lstsq(A, luminance, rcond=None)[0]
    ratio = float(b1 / b0) if b0 > 1e-6 else float("inf")
    return {"direction": directions[k].tolist(), "correlation": corrs[k], "sun_to_sky": ratio,
            "sky_level": float(max(b0, 1e-3)), "sun_level": float(max(b1, 0.0)),
            "use_sun": bool(corrs[k] >= min_corr and ratio >= min_ratio),
            "median_correlation": float(np.median(corrs)), "pairs": int(len(i)), "index": k}


def refine_candidates(direction, spread_deg=10.0, count=12):
    """Directions on a cone around ``direction`` (and itself), above the horizon."""
    d = np.asarray(direction, np.float64)
    d /= np.linalg.norm(d)
    a = np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(d, a); u /= np.linalg.norm(u)
    v = np.cross(d, u)
    out = [d]
    for r in (0.5 * spread_deg, spread_deg):
        t = np.radians(r)
        for k in range(count // 2):
            phi = 2 * np.pi * k / (count // 2)
            c = np.cos(t) * d + np.sin(t) * (np.cos(phi) * u + np.sin(phi) * v)
            if c[2] > 0.02:
                out.append(c / np.linalg.norm(c))
    return np.array(out)


def choose_sun(luminance, features, directions, weights=None, min_corr=0.25, min_ratio=0.15):
    """Pick the candidate whose shading best explains the colours.

    Returns a dict with the chosen direction, its correlation, the sun/sky
    ratio ``b1/b0`` of ``Y = b0 + b1 s`` and whether a sun is needed.
    """
    y = np.log(np.maximum(luminance, 1e-4))
    w = np.ones_like(y) if weights is None else weights
    best = None
    corrs = []
    for k in range(features.shape[1]):
        s = features[:, k]
        sm, ym = np.average(s, weights=w), np.average(y, weights=w)
        cov = np.average((s - sm) * (y - ym), weights=w)
        var = np.average((s - sm) ** 2, weights=w) * np.average((y - ym) ** 2, weights=w)
        r = cov / math.sqrt(var) if var > 1e-12 else 0.0
        corrs.append(r)
        if best is None or r > best[0]:
            best = (r, k)
    r, k = best
    s = features[:, k]
    A = np.stack([np.ones_like(s), s], axis=1) * np.sqrt(w)[:, None]
    b0, b1 = np.linalg.lstsq(A, luminance * np.sqrt(w), rcond=None)[0]
    ratio = float(b1 / b0) if b0 > 1e-6 else float("inf")
    need = bool(r >= min_corr and ratio >= min_ratio)
    return {"direction": directions[k].tolist(), "correlation": float(r), "sun_to_sky": ratio,
            "sky_level": float(b0), "sun_level": float(b1), "use_sun": need,
            "median_correlation": float(np.median(corrs))}


def fit_sh_orders(directions, radiance, max_order=3, seed=0, tolerance=0.02):
    """Least-squares SH fits of directly seen sky radiance at each order.

    Returns ``(chosen_order, {order: held-out RMSE}, {order: coefficients (n, 3)})``.
    """
    n = directions.shape[0]
    rng = np.random.default_rng(seed)
    perm = rng.permutation(n)
    split = max(1, int(0.8 * n))
    tr, te = perm[:split], perm[split:]
    errors, coeffs = {}, {}
    for order in range(max_order + 1):
        B = sh_basis_numpy(directions, order)
        c, *_ = np.linalg.lstsq(B[tr], radiance[tr], rcond=None)
        pred = B[te] @ c if te.size else B[tr] @ c
        ref = radiance[te] if te.size else radiance[tr]
        errors[order] = float(np.sqrt(np.mean((pred - ref) ** 2)))
        coeffs[order] = c
    # A camera sees a narrow band of sky directions; higher orders fitted to
    # it can explode towards the zenith, which would flood every Gaussian
    # with light. Orders whose sky anywhere on the upper hemisphere exceeds
    # 3x the brightest observed sky (or goes negative) are rejected.
    upper = hemisphere_candidates(256, 0.0)
    top = float(np.max(radiance)) if radiance.size else 1.0
    sane = {}
    for order, c in coeffs.items():
        sky = sh_basis_numpy(upper, order) @ c
        sane[order] = bool(np.max(sky) <= 3 * top and np.min(sky) >= -0.05 * top)
    ok = {o: e for o, e in errors.items() if sane[o]} or {0: errors[0]}
    best = min(ok.values())
    chosen = min(o for o, e in ok.items() if e <= best * (1 + tolerance) + 1e-9)
    return chosen, errors, coeffs


def pad_sh(coeffs, order_max=3):
    """Coefficients of a lower order padded with zeros to ``order_max``."""
    out = np.zeros((num_coeffs(order_max), 3), np.float32)
    out[: coeffs.shape[0]] = coeffs
    return out
