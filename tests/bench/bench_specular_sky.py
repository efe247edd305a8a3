"""The specular sky term: the split sum against the plain sum of the M samples.

    python tests/bench/bench_specular_sky.py [--points 100000] [--samples 16 32]

A Gaussian sees the sky through M fixed directions about its normal
(:mod:`mi_invrgbl.physics.lighting`), turned per Gaussian. Its specular sky
light can be summed as ``pi/M sum f_s(w_i, w_o) L(w_i)`` (a Monte Carlo
estimate with a uniform-in-disk pdf, what the integrator did before) or split
as ``E_s(cos_o, roughness)`` times the lobe-weighted mean of the samples
(:func:`mi_invrgbl.physics.specular_albedo.sky_specular`, what it does now).

The sky here is a street's: a smooth gradient plus a bright patch 50 degrees
off the normal (a sunlit facade across the street, 4x brighter than the
sky). For each roughness and view angle the reference is a dense float64
midpoint quadrature of ``int f_s L cos_i`` (1200 x 2400 nodes). Each method
is evaluated on ``--points`` Gaussians with their own turn of the spiral
(as the integrator's), and the table gives:

- ``rel RMSE``: RMS over the Gaussians of (estimate / reference - 1), the
  error one Gaussian's shading carries (the fit cannot average it away: each
  Gaussian has one turn);
- ``bias``: the mean of (estimate / reference - 1);
- ``fwd+bwd ms``: one forward pass and one backward pass to the roughness
  over all points (``dr.sync_thread`` around it, best of 3 after a warm-up).
"""

import sys as _sys, pathlib as _pathlib
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parents[1]))
import variant_choice  # noqa: E402  (--variant NAME, default $MI_INVRGBL_VARIANT or llvm_ad_rgb)
variant_choice.from_argv()

import argparse  # noqa: E402
import math  # noqa: E402
import time  # noqa: E402

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402

from mi_invrgbl.physics import brdf, specular_albedo  # noqa: E402
from mi_invrgbl.physics.lighting import fibonacci_direction, hash_rotation_of  # noqa: E402

PATCH = np.array([math.sin(math.radians(50)), 0.0, math.cos(math.radians(50))])
F0 = 0.04
SHADOWING = "smith"


def sky_np(w):
    """Radiance along local directions ``w`` (..., 3)."""
    facade = 4.0 * np.exp(-(1.0 - w @ PATCH) / 0.03)
    return 1.0 + 0.4 * w[..., 1] + 0.3 * w[..., 2] + facade


def sky_dr(w):
    p = mi.Vector3f(*[float(x) for x in PATCH])
    facade = 4.0 * dr.exp(-(1.0 - dr.dot(w, p)) / 0.03)
    return mi.Color3f(1.0 + 0.4 * w.y + 0.3 * w.z + facade)


def reference(mu, tau, n=1200):
    """int f_s(w_i, w_o) L(w_i) cos_i dw_i by a float64 midpoint rule in
    (cos_i, phi); ``w_o`` in the plane of the patch, on its mirror side."""
    c = (np.arange(n) + 0.5) / n
    phi = (np.arange(2 * n) + 0.5) / (2 * n) * 2 * math.pi
    C, P = np.meshgrid(c, phi, indexing="ij")
    s = np.sqrt(1 - C ** 2)
    wi = np.stack([s * np.cos(P), s * np.sin(P), C], -1)
    wo = np.array([-math.sqrt(1 - mu * mu), 0.0, mu])
    wi_dr = mi.Vector3f(*[mi.Float(wi[..., k].ravel().astype(np.float32)) for k in range(3)])
    wo_dr = mi.Vector3f(*[float(x) for x in wo])
    f = np.array(brdf.specular(wi_dr, wo_dr, mi.Float(tau), F0, SHADOWING), np.float64)
    return float(np.sum(f.reshape(C.shape) * C * sky_np(wi)) / n * (2 * math.pi / (2 * n)))


def plain_sum(dirs, wo, tau, M):
    out = mi.Color3f(0.0)
    for i in range(M):
        w = dirs(i)
        out += sky_dr(w) * brdf.specular(w, wo, tau, F0, SHADOWING) * (dr.pi / M)
    return out


def split_sum(dirs, wo, tau, M):
    return specular_albedo.sky_specular(dirs, lambda i: sky_dr(dirs(i)), wo, tau, M, F0,
                                        SHADOWING)


def run(method, mu, tau, M, points):
    rot = hash_rotation_of(dr.arange(mi.UInt32, points))
    dirs = lambda i: fibonacci_direction(mi.Float(i), M, rot)  # noqa: E731
    wo = mi.Vector3f(-math.sqrt(1 - mu * mu), 0.0, mu)
    t = dr.full(mi.Float, tau, points)
    dr.enable_grad(t)
    out = method(dirs, wo, t, M)
    dr.backward(dr.sum(out[0]))
    g = dr.grad(t)
    dr.eval(out, g)
    dr.sync_thread()
    return np.array(out[0], np.float64)


def timed(method, mu, tau, M, points):
    run(method, mu, tau, M, points)          # warm-up: kernels compiled
    best = math.inf
    for _ in range(3):
        dr.sync_thread()
        t0 = time.perf_counter()
        run(method, mu, tau, M, points)
        best = min(best, time.perf_counter() - t0)
    return best * 1e3


def main(argv=None):
    """Print the table; returns its rows as dicts."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--points", type=int, default=100000)
    ap.add_argument("--samples", type=int, nargs="+", default=[16, 32])
    ap.add_argument("--roughness", type=float, nargs="+", default=[0.05, 0.1, 0.3, 0.7, 1.0])
    ap.add_argument("--cos", type=float, nargs="+", default=[0.9, 0.5, 0.2])
    args = ap.parse_args(argv)
    rows = []
    print("%s, %d Gaussians, f0 %.2f, %s shadowing" % (mi.variant(), args.points, F0, SHADOWING))
    print("%3s %5s %5s %10s | %9s %8s %10s | %9s %8s %10s" % (
        "M", "rough", "cos_o", "reference", "plain RMS", "bias", "ms", "split RMS", "bias", "ms"))
    for M in args.samples:
        for tau in args.roughness:
            for mu in args.cos:
                ref = reference(mu, tau)
                cells = []
                for method in (plain_sum, split_sum):
                    est = run(method, mu, tau, M, args.points)
                    rel = est / ref - 1.0
                    cells.append((float(np.sqrt(np.mean(rel ** 2))), float(np.mean(rel)),
                                  timed(method, mu, tau, M, args.points)))
                print("%3d %5.2f %5.2f %10.5f | %9.3f %+8.3f %10.1f | %9.3f %+8.3f %10.1f" % (
                    M, tau, mu, ref, *cells[0], *cells[1]))
                rows.append({"samples": M, "roughness": tau, "cos_o": mu, "reference": ref,
                             "plain": cells[0], "split": cells[1]})
    return rows


if __name__ == "__main__":
    main()
