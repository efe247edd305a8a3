r"""LiDAR sensor response: which intensity a sensor reports for a return.

The ``lidar_return`` integrator renders

.. math::  I = g_{beam}\,(\rho + \pi f_s)\,P_e \cos^a\theta / (\pi d^b)

The paper's physics is ``a = 1, b = 2, g = 1``. Real sensors differ: KITTI's
HDL-64E reports range-compensated reflectivity (on the shared excerpt the
ground's median stays ~0.16 from 3 to 30 m while cos/d^2 falls a hundredfold,
i.e. ``b ~ 0``), Waymo's report raw return strength, and every beam of a
spinning LiDAR has its own gain. :func:`estimate_response` fits ``a``, ``b``
and the per-beam gains from observed returns on the current geometry.

The model is linear in logs. With one unknown reflectance per surface
element (``surface_id``: e.g. the Gaussian with the largest blend weight
along the beam),

.. math::  \log I_i = u_{s(i)} + v_{beam(i)} + a \log\cos\theta_i - b \log d_i

a two-way fixed-effects regression. It is solved exactly by eliminating the
surface effects (per-surface weighted demeaning, i.e. the Schur complement of
the diagonal surface block of the normal equations), which leaves a dense
``(n_beams + 2)`` system, and made robust by iteratively reweighted least
squares with Huber weights (scale: the residuals' MAD) plus trimming of
residuals beyond ``trim`` scales. Only within-surface variation of range,
angle and beam identifies ``a``, ``b`` and the gains; surfaces seen once
carry no information about them (they only get their own ``rho``).

Identifiability and priors: on a street seen from a car, the same surface is
often seen over a narrow span of ranges, and on the road ``cos ~ h / d`` makes
the angle and range terms nearly collinear; a free fit then trades one for
the other (and the per-surface reflectance absorbs the rest), which
reproduces the training poses but not a new pose. So the exponents and the
log gains carry Gaussian priors from the sensor's kind (:data:`PRIORS`: a
raw sensor ``a = 1, b = 2``; a range-compensated one ``a = 1, b = 0``),
i.e. the normal equations get ``s^2 / tau^2`` added on those columns, with
``s`` the robust residual scale and ``tau`` the prior's width. Where the data
identify a term (its within-surface information ``>> 1 / tau^2``) the prior
is negligible; where they do not, the estimate stays at the sensor's kind.
The posterior standard deviations are reported (``extra``), and a term
counts as identified where its posterior deviation is below half the
prior's.

Gauge: surface effects and gains share a common factor; it is fixed by
``median(beam_gains) = 1`` and the constant goes into ``rho``, reported in
the integrator's convention ``rho = pi exp(u) / P_e`` (the specular term is
neglected: fit on matte surfaces, or rely on the robust weights).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..outdir import atomic_write
from ..physics.lidar_response import colocated_intensity_np, format_gains  # noqa: F401

#: Returns at more grazing incidence than this are ignored (cos theta).
MIN_COS = 0.05
#: Huber threshold in units of the residual scale (95 % efficiency for Gaussian noise).
HUBER_K = 1.345


@dataclass(frozen=True)
class ResponsePrior:
    """Gaussian prior on the response: exponent means and widths, and the
    width of the log beam gains around 0 (gain 1)."""
    range_exponent: float
    angle_exponent: float = 1.0
    range_std: float = 0.25
    angle_std: float = 0.25
    log_gain_std: float = 0.5


#: Priors by intensity kind (``frames.json``'s ``lidar.intensity``).
PRIORS = {"raw": ResponsePrior(2.0), "reflectivity": ResponsePrior(0.0)}


def prior_for(kind: str | None) -> ResponsePrior:
    """The prior for a sensor reporting ``raw`` strength or ``reflectivity``."""
    return PRIORS.get(str(kind), PRIORS["raw"])


@dataclass
class SensorResponse:
    """Fitted response; ``rho`` is per surface id (NaN where unobserved)."""
    range_exponent: float
    angle_exponent: float
    beam_gains: np.ndarray
    rho: np.ndarray
    residual_rms: float
    n_used: int
    n_surfaces_used: int = 0
    iterations: int = 0
    extra: dict = field(default_factory=dict)

    def integrator_dict(self, model: str = "pbr") -> dict:
        """A ``mi.load_dict`` dictionary for the ``lidar_return`` integrator."""
        return {"type": "lidar_return", "model": model,
                "range_exponent": float(self.range_exponent),
                "angle_exponent": float(self.angle_exponent),
                "beam_gains": format_gains(self.beam_gains)}

    def integrator_xml(self, model: str = "pbr", indent: str = "    ") -> str:
        """The ``<integrator type="lidar_return">`` element for ``scene_lidar.xml``."""
        d = self.integrator_dict(model)
        return (f'{indent}<integrator type="lidar_return">\n'
                f'{indent}    <string name="model" value="{model}"/>\n'
                f'{indent}    <float name="range_exponent" value="{d["range_exponent"]:.6g}"/>\n'
                f'{indent}    <float name="angle_exponent" value="{d["angle_exponent"]:.6g}"/>\n'
                f'{indent}    <string name="beam_gains" value="{d["beam_gains"]}"/>\n'
                f'{indent}</integrator>\n')

    def to_json(self) -> dict:
        return {"range_exponent": float(self.range_exponent),
                "angle_exponent": float(self.angle_exponent),
                "beam_gains": [float(g) for g in self.beam_gains],
                "residual_rms": float(self.residual_rms), "n_used": int(self.n_used),
                "n_surfaces_used": int(self.n_surfaces_used),
                "iterations": int(self.iterations), **self.extra}

    def predict(self, rho, distance, cos_theta, beam, power: float = 1.0) -> np.ndarray:
        """Intensity of Lambertian returns under this response (numpy), with
        the integrator's formula and clamps."""
        g = np.asarray(self.beam_gains, np.float64)
        g = g[np.minimum(np.asarray(beam, np.int64), g.size - 1)]
        return colocated_intensity_np(rho, cos_theta, distance, g, power,
                                      self.angle_exponent, self.range_exponent)


def _weighted_group_mean(values, groups, weights, n_groups, wsum):
    s = np.bincount(groups, weights=values * weights, minlength=n_groups)
    return s / np.maximum(wsum, 1e-300)


class _SchurBeamBlock:
    """``M^T diag(1/ws) M`` with ``M[s, k] = sum of weights of surface s, beam k``.

    The sparsity pattern (which surface saw which beam) is found once; each
    call sums the current weights into it and multiplies densified chunks of
    surfaces (memory O(chunk * n_beams)). ``einsum`` rather than ``@``: on
    the 2-core development machine it was 10x faster than the BLAS call.
    """

    def __init__(self, surf, col, nb, chunk=20000):
        self.nb = nb
        key = surf * nb + col
        uniq, inv = np.unique(key, return_inverse=True)
        self.inv = inv.ravel()
        self.n_entries = uniq.size
        self.s_e, self.k_e = uniq // nb, uniq % nb
        if uniq.size:
            bounds = np.arange(0, int(self.s_e[-1]) + chunk + 1, chunk)
            starts = np.searchsorted(self.s_e, bounds)
            self.chunks = [(lo, hi) for lo, hi in zip(starts[:-1], starts[1:]) if hi > lo]
        else:
            self.chunks = []

    def __call__(self, weight, ws):
        m = np.bincount(self.inv, weights=weight, minlength=self.n_entries)
        out = np.zeros((self.nb, self.nb))
        for lo, hi in self.chunks:
            s0 = int(self.s_e[lo])
            rows = self.s_e[lo:hi] - s0
            dense = np.zeros((int(rows[-1]) + 1, self.nb))
            dense[rows, self.k_e[lo:hi]] = m[lo:hi]
            scaled = dense / np.maximum(ws[s0:s0 + dense.shape[0]], 1e-300)[:, None]
            out += np.einsum("ij,ik->jk", scaled, dense)
        return out


def estimate_response(intensity, distance, cos_theta, beam, surface_id, n_beams: int,
                      n_surfaces: int | None = None, *, fit_range: bool = True,
                      fit_angle: bool = True, fit_gains: bool = True,
                      range_exponent: float = 2.0, angle_exponent: float = 1.0,
                      power: float = 1.0, robust: str = "huber", trim: float = 4.0,
                      iterations: int = 20, min_cos: float = MIN_COS,
                      min_returns_per_beam: int = 20, tol: float = 1e-7,
                      prior: ResponsePrior | None = None) -> SensorResponse:
    """Fit range/angle exponents, per-beam gains and per-surface reflectance.

    Args (one entry per observed return; numpy arrays of equal length):
        intensity: reported intensity ``I`` (returns with ``I <= 0`` or non-finite
            values are ignored).
        distance: range ``d`` (> 0).
        cos_theta: incidence cosine from the current geometry (returns with
            ``cos < min_cos`` are ignored).
        beam: beam (film row) index, ``0 <= beam < n_beams``.
        surface_id: id of the surface element hit (non-negative int).
        n_beams: number of beams (length of ``beam_gains``).
        n_surfaces: length of the returned ``rho`` (default ``max(surface_id) + 1``).
        fit_range / fit_angle / fit_gains: ``False`` holds that part fixed at
            ``range_exponent`` / ``angle_exponent`` / gains 1.
        power: the laser power ``P_e`` the integrator will use (scales ``rho``).
        robust: ``huber`` (IRLS, default), ``l2`` (plain least squares).
        trim: residuals beyond ``trim`` robust scales get weight 0 (0 = no trimming).
        min_returns_per_beam: beams with fewer used returns keep gain 1 (before
            the median gauge) instead of a noisy estimate.
        prior: :class:`ResponsePrior` for the free exponents and gains (see
            the module docstring); ``None``: unregularised least squares.

    Returns:
        :class:`SensorResponse`. ``residual_rms`` is the RMS of the log-residuals
        over the returns kept by the final weights (inliers).
    """
    I = np.asarray(intensity, np.float64).ravel()
    d = np.asarray(distance, np.float64).ravel()
    c = np.asarray(cos_theta, np.float64).ravel()
    b = np.asarray(beam).ravel().astype(np.int64)
    s = np.asarray(surface_id).ravel().astype(np.int64)
    n = I.size
    if not all(a.size == n for a in (d, c, b, s)):
        raise ValueError("estimate_response: intensity, distance, cos_theta, beam and "
                         "surface_id must have the same length")
    n_beams = int(n_beams)
    if n_surfaces is None:
        n_surfaces = int(s.max()) + 1 if n else 0
    if robust not in ("huber", "l2"):
        raise ValueError("estimate_response: robust must be 'huber' or 'l2'")
    with np.errstate(invalid="ignore", divide="ignore"):
        use = (np.isfinite(I) & np.isfinite(d) & np.isfinite(c) & (I > 0) & (d > 0)
               & (c >= min_cos) & (b >= 0) & (b < n_beams) & (s >= 0) & (s < n_surfaces))
    idx = np.nonzero(use)[0]
    gains = np.ones(n_beams)
    rho = np.full(n_surfaces, np.nan)
    if idx.size == 0:
        return SensorResponse(float(range_exponent), float(angle_exponent), gains, rho,
                              float("nan"), 0)
    y = np.log(I[idx])
    x_cos = np.log(c[idx])
    x_d = -np.log(d[idx])
    bb = b[idx]
    # Compact surface ids of the used returns.
    s_uniq, ss = np.unique(s[idx], return_inverse=True)
    n_s = s_uniq.size

    # Beams with enough returns get a free gain; the first of them is the
    # reference (gauge), re-centred to median 1 at the end.
    counts = np.bincount(bb, minlength=n_beams)
    free_beams = np.nonzero(counts >= max(1, min_returns_per_beam))[0] if fit_gains else np.array([], int)
    free_beams = free_beams[1:] if free_beams.size else free_beams
    col_of_beam = np.full(n_beams, -1, np.int64)
    col_of_beam[free_beams] = np.arange(free_beams.size)
    n_cols = free_beams.size + int(fit_angle) + int(fit_range)

    fixed = np.zeros_like(y)
    if not fit_angle:
        fixed += angle_exponent * x_cos
    if not fit_range:
        fixed += range_exponent * x_d
    target = y - fixed

    w = np.ones_like(y)
    theta = np.zeros(n_cols)
    u = np.zeros(n_s)
    it = 0
    scale = float("nan")
    schur = None
    for it in range(1, int(iterations) + 1):
        ws = np.bincount(ss, weights=w, minlength=n_s)
        # Within-surface demeaning of the target and of the dense columns.
        t_dm = target - _weighted_group_mean(target, ss, w, n_s, ws)[ss]
        dense = []
        if fit_angle:
            dense.append(x_cos - _weighted_group_mean(x_cos, ss, w, n_s, ws)[ss])
        if fit_range:
            dense.append(x_d - _weighted_group_mean(x_d, ss, w, n_s, ws)[ss])
        A = np.zeros((n_cols, n_cols))
        rhs = np.zeros(n_cols)
        nb = free_beams.size
        if nb:
            col = col_of_beam[bb]
            on = col >= 0
            # Beam indicator block: E^T W E - M^T W_s^-1 M with M[s, k] = sum_{i in s, beam k} w_i
            A[:nb, :nb] += np.diag(np.bincount(col[on], weights=w[on], minlength=nb))
            if schur is None:
                schur = _SchurBeamBlock(ss[on], col[on], nb)
            A[:nb, :nb] -= schur(w[on], ws)
            rhs[:nb] = np.bincount(col[on], weights=(w * t_dm)[on], minlength=nb)
            for j, x in enumerate(dense):
                # cross terms: sum_{i in beam k} w_i x_dm_i (x demeaned -> Schur exact)
                A[:nb, nb + j] = A[nb + j, :nb] = np.bincount(col[on], weights=(w * x)[on],
                                                               minlength=nb)
        for j, xj in enumerate(dense):
            for k, xk in enumerate(dense):
                A[nb + j, nb + k] = np.sum(w * xj * xk)
            rhs[nb + j] = np.sum(w * xj * t_dm)
        # Tiny ridge: keeps the system solvable when a column has no
        # within-surface variation (the parameter then stays at 0 / its prior).
        ridge = 1e-9 * max(float(np.trace(A)) / max(n_cols, 1), 1e-300)
        A_data = A.copy()
        if prior is not None and n_cols:
            s2 = (scale if np.isfinite(scale) else PRIOR_SCALE0) ** 2
            prec, mean = _prior_terms(prior, nb, fit_angle, fit_range)
            A = A + np.diag(s2 * prec)
            rhs = rhs + s2 * prec * mean
        theta_new = np.linalg.solve(A + ridge * np.eye(n_cols), rhs) if n_cols else theta
        # Surface effects from the current theta.
        pred_wo_u = np.zeros_like(y)
        if nb:
            pred_wo_u += np.where(col_of_beam[bb] >= 0, theta_new[np.maximum(col_of_beam[bb], 0)], 0.0)
        k = nb
        if fit_angle:
            pred_wo_u += theta_new[k] * x_cos
            k += 1
        if fit_range:
            pred_wo_u += theta_new[k] * x_d
        u = _weighted_group_mean(target - pred_wo_u, ss, w, n_s, ws)
        resid = target - pred_wo_u - u[ss]
        step = float(np.max(np.abs(theta_new - theta))) if n_cols else 0.0
        theta = theta_new
        if robust == "l2" and trim <= 0:
            break
        # Robust weights from the residuals of surfaces with > 1 return (a
        # surface seen once fits exactly and says nothing about the scale).
        multi = np.bincount(ss, minlength=n_s)[ss] > 1
        r_ref = resid[multi] if multi.any() else resid
        scale = 1.4826 * float(np.median(np.abs(r_ref - np.median(r_ref))))
        scale = max(scale, 1e-12)
        a = np.abs(resid) / scale
        w = np.ones_like(y) if robust == "l2" else np.minimum(1.0, HUBER_K / np.maximum(a, 1e-12))
        if trim > 0:
            w = np.where(a > trim, 0.0, w)
        if it > 1 and step < tol:
            break

    # Unpack, fix the gauge (median gain 1) and move the constant into rho.
    log_g = np.zeros(n_beams)
    nb = free_beams.size
    if nb:
        log_g[free_beams] = theta[:nb]
    k = nb
    a_exp = float(theta[k]) if fit_angle else float(angle_exponent)
    k += int(fit_angle)
    b_exp = float(theta[k]) if fit_range else float(range_exponent)
    observed = counts > 0
    shift = float(np.log(np.median(np.exp(log_g[observed])))) if fit_gains and observed.any() else 0.0
    log_g -= shift
    u = u + shift
    gains = np.exp(log_g)
    rho[s_uniq] = np.pi * np.exp(u) / float(power)
    inl = w > 0
    rms = float(np.sqrt(np.mean(resid[inl] ** 2))) if inl.any() else float("nan")
    extra = {"residual_scale": scale, "n_inliers": int(inl.sum())}
    if n_cols and np.isfinite(scale):
        # Posterior deviations s * sqrt(diag((A_data + s^2 P)^-1)), and the
        # data's own (no prior): a term is identified where the data alone
        # pin it to within half the prior's width.
        s2 = scale ** 2
        reg = A_data + ridge * np.eye(n_cols)
        post = reg if prior is None else reg + np.diag(
            s2 * _prior_terms(prior, nb, fit_angle, fit_range)[0])
        try:
            cov_post = s2 * np.linalg.inv(post)
            cov_data = s2 * np.linalg.pinv(reg, hermitian=True)
            k = nb
            for name, on, tau in (("angle_exponent", fit_angle, prior.angle_std if prior else None),
                                  ("range_exponent", fit_range, prior.range_std if prior else None)):
                if on:
                    extra[name + "_std"] = float(np.sqrt(max(cov_post[k, k], 0.0)))
                    sd = float(np.sqrt(max(cov_data[k, k], 0.0)))
                    extra[name + "_data_std"] = sd
                    if tau is not None:
                        extra[name + "_identified"] = bool(sd < 0.5 * tau)
                    k += 1
        except np.linalg.LinAlgError:
            pass
    if prior is not None:
        extra["prior"] = {"range_exponent": prior.range_exponent,
                          "angle_exponent": prior.angle_exponent,
                          "range_std": prior.range_std, "angle_std": prior.angle_std,
                          "log_gain_std": prior.log_gain_std}
    return SensorResponse(b_exp, a_exp, gains, rho, rms, int(idx.size), int(n_s), it,
                          extra=extra)


#: Residual scale (log units) used for the prior's weight before the first
#: robust estimate.
PRIOR_SCALE0 = 0.1


def _prior_terms(prior: ResponsePrior, n_gain_cols: int, fit_angle: bool, fit_range: bool):
    """Prior precision (1 / tau^2) and mean of each unknown column."""
    prec = [1.0 / prior.log_gain_std ** 2] * n_gain_cols
    mean = [0.0] * n_gain_cols
    if fit_angle:
        prec.append(1.0 / prior.angle_std ** 2)
        mean.append(prior.angle_exponent)
    if fit_range:
        prec.append(1.0 / prior.range_std ** 2)
        mean.append(prior.range_exponent)
    return np.asarray(prec), np.asarray(mean)


# ----------------------------------------------------------------------------
def ground_mask(points, sensor_height: float = 1.73, tolerance: float = 0.3) -> np.ndarray:
    """Points of a sweep (sensor frame, z up) within ``tolerance`` of the ground
    plane ``z = -sensor_height`` (KITTI's HDL-64E sits 1.73 m up)."""
    p = np.asarray(points, np.float64)
    return np.abs(p[:, 2] + sensor_height) < tolerance


DEFAULT_RANGE_BINS = ((3.0, 5.0), (5.0, 8.0), (8.0, 12.0), (12.0, 20.0), (20.0, 30.0),
                      (30.0, 50.0))


def intensity_statistics(points, ranges=DEFAULT_RANGE_BINS, intensity=None, origin=None,
                         mask=None) -> list:
    """Median intensity by range bin: tells a reflectivity sensor from a raw one.

    Args:
        points: ``(N, 4)`` x, y, z, intensity (or ``(N, 3)`` with ``intensity``).
        ranges: bins as ``(lo, hi)`` pairs in metres, or a sorted list of edges.
        origin: the sensor position (default: the origin, i.e. sensor-frame points).
        mask: optional boolean selection (e.g. :func:`ground_mask`).

    Returns one dict per bin: ``lo``, ``hi``, ``n``, ``median``, ``p25``, ``p75``
    (NaN for empty bins) and ``inv_d2``, the bin's median ``1/d^2`` relative to
    the first non-empty bin's. A raw sensor's median falls like ``inv_d2``; a
    range-compensated one (KITTI: ~0.16 for the ground from 3 to 30 m) stays flat.
    """
    p = np.asarray(points, np.float64)
    if intensity is None:
        if p.ndim != 2 or p.shape[1] < 4:
            raise ValueError("intensity_statistics: points must be (N, 4) x, y, z, intensity")
        inten = p[:, 3]
    else:
        inten = np.asarray(intensity, np.float64).ravel()
    xyz = p[:, :3] - (0.0 if origin is None else np.asarray(origin, np.float64))
    d = np.linalg.norm(xyz, axis=1)
    sel = np.isfinite(inten) & np.isfinite(d)
    if mask is not None:
        sel &= np.asarray(mask, bool)
    ranges = list(ranges)
    if ranges and np.ndim(ranges[0]) == 0:
        ranges = list(zip(ranges[:-1], ranges[1:]))
    out, ref = [], None
    for lo, hi in ranges:
        m = sel & (d >= lo) & (d < hi)
        v = inten[m]
        row = {"lo": float(lo), "hi": float(hi), "n": int(m.sum())}
        if v.size:
            row.update(median=float(np.median(v)), p25=float(np.percentile(v, 25)),
                       p75=float(np.percentile(v, 75)))
            inv = float(np.median(1.0 / d[m] ** 2))
            ref = inv if ref is None else ref
            row["inv_d2"] = inv / ref
        else:
            row.update(median=float("nan"), p25=float("nan"), p75=float("nan"),
                       inv_d2=float("nan"))
        out.append(row)
    return out


def format_statistics(rows) -> str:
    """The :func:`intensity_statistics` rows as a small text table."""
    lines = ["range [m]      n    median   p25     p75   rel. 1/d^2"]
    for r in rows:
        lines.append("%5.1f-%-5.1f %7d  %6.3f  %6.3f  %6.3f  %8.4f"
                     % (r["lo"], r["hi"], r["n"], r["median"], r["p25"], r["p75"], r["inv_d2"]))
    return "\n".join(lines)


# ----------------------------------------------------------------------------
# Ray drop
# ----------------------------------------------------------------------------

def fit_return_model(distance, cos_theta, albedo, beam, returned, n_beams: int,
                     beam_l2: float = 1.0, iterations: int = 30):
    """Fit a :class:`~mi_invrgbl.physics.lidar_response.ReturnModel`.

    One sample per beam that reaches a surface in the fitted scene: its range,
    incidence cosine and LiDAR albedo there, its beam, and whether the sensor
    reported a return (``returned``). Logistic regression by Newton's method
    (IRLS) on ``[1, log d, log cos, log rho]`` plus per-beam offsets, the
    offsets with an L2 penalty ``beam_l2`` (beams with few samples stay at the
    common intercept) and a tiny one elsewhere (a separable set stays finite).
    """
    from ..physics.lidar_response import ReturnModel
    y = np.asarray(returned, np.float64).ravel()
    F = ReturnModel.features(distance, cos_theta, albedo)
    b = np.minimum(np.asarray(beam, np.int64).ravel(), max(int(n_beams), 1) - 1)
    n, B = y.size, max(int(n_beams), 1)
    if n == 0:
        return ReturnModel(np.zeros(3), np.full(B, 10.0))
    X = np.hstack([np.ones((n, 1)), F])
    k = X.shape[1]
    theta = np.zeros(k)
    dev = np.zeros(B)
    pen = np.full(k, 1e-6 * n)
    for _ in range(int(iterations)):
        z = X @ theta + dev[b]
        p = 1.0 / (1.0 + np.exp(-np.clip(z, -30, 30)))
        W = np.maximum(p * (1 - p), 1e-9)
        g_x = X.T @ (y - p) - pen * theta
        g_b = np.bincount(b, weights=y - p, minlength=B) - beam_l2 * dev
        # Newton step on the joint system [X | E] with E the beam indicators.
        H_xx = (X * W[:, None]).T @ X + np.diag(pen)
        H_xb = np.stack([np.bincount(b, weights=W * X[:, j], minlength=B) for j in range(k)])
        H_bb = np.diag(np.bincount(b, weights=W, minlength=B) + beam_l2)
        H = np.block([[H_xx, H_xb], [H_xb.T, H_bb]])
        step = np.linalg.solve(H + 1e-12 * np.eye(k + B), np.concatenate([g_x, g_b]))
        theta += step[:k]
        dev += step[k:]
        if np.max(np.abs(step)) < 1e-8:
            break
    return ReturnModel(theta[1:], theta[0] + dev)


def scene_return_samples(scene, integrator, frames, positions, lidar_size=None, log=print,
                         max_beams=None):
    """Samples for :func:`fit_return_model` from frames of a fitted scene.

    For each frame position: the scene posed at that frame, its LiDAR sensor's
    beams rendered by ``integrator`` (without a ray-drop model), and the
    observed range image's ``hit`` channel. Returns numpy arrays
    ``(distance, cos, albedo, beam, returned)`` over beams that reach a
    surface and that the frame's LiDAR mask does not exclude.

    ``max_beams``: render about this many beams over all the frames: every
    ``stride``-th beam of each frame, ``stride`` set from the first frame's
    beams (row-major, starting at the frame's position modulo ``stride``, so
    that consecutive frames take different beams). None: every beam.
    """
    import drjit as dr
    import mitsuba as mi
    from .observations import lidar_exclusion
    from ..physics.host_arrays import jit_array
    from ..io.images import read_exr
    from ..plugins.lidar_return import LidarReturnIntegrator
    from ..scene.posing import set_frame
    saved = integrator.return_model
    integrator.return_model = None
    out = [[] for _ in range(5)]
    stride = None
    try:
        for k in positions:
            rec = frames[k]
            if rec.lidar_scan is None:
                continue
            # set_frame moves the objects through the scene's parameters, so
            # the acceleration structure follows them.
            _, sensor = set_frame(scene, frames, k)
            if sensor is None:
                continue
            img, names = read_exr(str(rec.lidar_scan))
            hit_obs = img[..., [n.lower() for n in names].index("hit")].ravel() > 0.5
            # Returns from moving things no node models are left out.
            excluded = lidar_exclusion(rec, img.shape[:2], log)
            counts = np.ones(hit_obs.size, bool) if excluded is None else ~excluded.ravel()
            rays, beam, _, near = LidarReturnIntegrator.beam_rays(sensor)
            if stride is None:
                stride = 1 if not max_beams else max(
                    1, int(np.ceil(len(positions) * hit_obs.size / max_beams)))
            keep = np.arange(k % stride, hit_obs.size, stride) if stride > 1 else None
            if keep is not None:
                idx = jit_array(mi.UInt32, keep.astype(np.uint32))
                rays = dr.gather(mi.Ray3f, rays, idx)
                beam = dr.gather(type(beam), beam, idx)
                near = dr.gather(mi.Float, near, idx) if dr.width(near) > 1 else near
                hit_obs, counts = hit_obs[keep], counts[keep]
            extra = {}
            with dr.suspend_grad():
                ch = integrator.render_beams(scene, rays, beam, near=near, extra=extra)
            surf = np.array(extra["surface"], bool)
            if surf.size != hit_obs.size:
                continue
            vals = (np.array(ch[1]), np.array(extra["cos"]), np.array(ch[3]), np.array(beam),
                    hit_obs)
            for lst, v in zip(out, vals):
                lst.append(np.asarray(v)[surf & counts])
    finally:
        integrator.return_model = saved
    if not out[0]:
        return tuple(np.zeros(0) for _ in range(5))
    return tuple(np.concatenate(v) for v in out)


def write_return_model(scene_lidar_xml, model) -> None:
    """Set the ``return_weights`` / ``return_bias`` of the ``lidar_return``
    integrator in ``scene_lidar_xml`` (a file this package wrote)."""
    import xml.etree.ElementTree as ET
    tree = ET.parse(scene_lidar_xml)
    root = tree.getroot()
    integ = next((e for e in root if e.tag == "integrator" and e.get("type") == "lidar_return"),
                 None)
    if integ is None:
        raise ValueError("%s: no lidar_return integrator" % scene_lidar_xml)
    for e in [e for e in integ if e.get("name") in ("return_weights", "return_bias")]:
        integ.remove(e)
    ET.SubElement(integ, "string", {"name": "return_weights", "value": format_gains(model.weights)})
    ET.SubElement(integ, "string", {"name": "return_bias", "value": format_gains(model.beam_bias)})
    ET.indent(tree, space="  ")
    atomic_write(scene_lidar_xml, lambda tmp: tree.write(tmp, encoding="unicode"))


#: Beams :func:`fit_scene_ray_drop` renders, spread over the training frames.
#: The model has three weights and one offset per beam; rendering every beam
#: of the KITTI excerpt's 32 frames (2.1 million, 1.9 million reaching a
#: surface) took 31 s of a fit's outputs on 2 cores. Every 16th beam of each
#: frame (131 000) took 7.7 s, moved the weights by 0.001 at most and scored
#: the same drop accuracy on every beam (0.8829 against 0.8828; F1 0.0807
#: against 0.0813). The cost per frame does not fall below about 0.2 s.
RAY_DROP_BEAMS = 150_000


def fit_scene_ray_drop(scene_xml, scene_lidar_xml, frames=None, log=print) -> dict:
    """Fit the ray-drop model of a fitted scene on its training frames and
    write it into ``scene_lidar_xml``; returns the fit's summary. ``frames``
    (default: the ``frames.json`` beside the scene) are the scene's records:
    a fit being written has none beside it yet."""
    import mitsuba as mi
    import xml.etree.ElementTree as ET
    from ..physics.lidar_response import return_scores
    from ..scene.frames import Frames
    frames = frames if frames is not None else Frames.load(scene_xml)
    scene = mi.load_file(str(scene_xml))
    root = ET.parse(scene_lidar_xml).getroot()
    integ_el = next(e for e in root if e.tag == "integrator")
    integrator = mi.load_string('<scene version="3.0.0">%s</scene>'
                                % ET.tostring(integ_el, encoding="unicode")).integrator()
    train = [k for k in range(len(frames)) if not frames[k].held_out]
    d, c, rho, beam, ret = scene_return_samples(scene, integrator, frames, train, log=log,
                                                max_beams=RAY_DROP_BEAMS)
    n_beams = max(int(frames.lidar.beams) if frames.lidar is not None else 1,
                  int(beam.max()) + 1 if beam.size else 1)
    model = fit_return_model(d, c, rho, beam, ret, n_beams)
    write_return_model(scene_lidar_xml, model)
    pred = model.logit_np(d, c, rho, beam) >= 0
    summary = {"weights": {k: float(v) for k, v in zip(("log_range", "log_cos", "log_albedo"),
                                                        model.weights)},
               "samples": int(d.size), "train": return_scores(ret, pred)}
    log("[fit] ray-drop model on %d beams reaching a surface: weights log d %.2f, log cos %.2f, "
        "log rho %.2f; training drop accuracy %.3f, F1 %.3f"
        % (d.size, *model.weights, summary["train"]["accuracy"], summary["train"]["f1"]))
    return summary
