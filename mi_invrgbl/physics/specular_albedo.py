"""The specular lobe's directional albedo and the sky's reflection through it.

A Gaussian sees the sky through ``M`` fixed directions around its normal
(:mod:`.lighting`). Summed as a Monte Carlo estimate, ``pi/M sum f_s L``,
they resolve a lobe only as wide as their spacing (about ``sqrt(2 pi / M)``
radians): a glossy lobe (GGX alpha 0.1, a window) falls between them, so the
estimate is nearly zero for most normals and a spike for a few (unbiased
over many Gaussians, but off by 0.4-3.8 times its value on one at M = 16,
``tests/bench/bench_specular_sky.py``). :func:`sky_specular` splits the integral
instead (the "split sum" of real-time renderers): the lobe's energy, its
directional albedo ``E_s(cos_o, roughness) = int f_s cos_i`` tabulated here
once per Fresnel ``f0`` and shadowing term, times the mean radiance of the
samples weighted by the lobe. The weights use the lobe widened to the
samples' spacing (:func:`lobe_floor`), so a sharp lobe reads the radiance
of the samples nearest its mirror direction instead of missing them all.
Under a uniform sky the split sum is exact for any lobe; for a wide lobe it
agrees with dense sampling (``tests/test_specular_albedo.py``). The price
is bias where light comes from a patch narrower than the samples' spacing:
the widened weights blur it (20-37 % low at its mirror direction, up to
80 % high at grazing views for roughness 0.05-0.1, in that bench).
"""

from __future__ import annotations

import math

import numpy as np
import drjit as dr
import mitsuba as mi

from . import brdf
from .host_arrays import jit_array

#: Nodes of the table along cos_o and along roughness (both 0..1).
TABLE_NODES = 64
#: Stratified half-vector samples per node along each axis (their square in all).
TABLE_STRATA = 48
#: The weights' lobe is at least this many sample spacings wide (GGX alpha
#: per radian of spacing): half a spacing keeps two or three samples in a
#: sharp lobe's weight, so its reflection moves smoothly with the normal.
FLOOR_PER_SPACING = 0.5

_tables: dict = {}


def lobe_floor(samples: int) -> float:
    """The least GGX alpha of the weighting lobe for ``samples`` sky directions."""
    return FLOOR_PER_SPACING * math.sqrt(2.0 * math.pi / max(int(samples), 1))


def _build(f0: float, shadowing: str) -> mi.Float:
    """``E_s`` at the table's nodes (row-major: cos_o, then roughness), by
    stratified GGX importance sampling of the half vector through
    :func:`brdf.specular` itself, so the table integrates the very lobe the
    integrator evaluates."""
    n, s = TABLE_NODES, TABLE_STRATA
    with dr.suspend_grad():
        k = dr.arange(mi.UInt32, n * n * s * s)
        node, stratum = k // (s * s), k % (s * s)
        mu = dr.maximum(mi.Float(node // n) / (n - 1), 1e-3)
        tau = mi.Float(node % n) / (n - 1)
        u = (mi.Float(stratum // s) + 0.5) / s
        v = (mi.Float(stratum % s) + 0.5) / s
        alpha = brdf.clamp_alpha(tau)
        wo = mi.Vector3f(dr.safe_sqrt(1.0 - dr.square(mu)), 0.0, mu)
        # GGX half vector: tan^2 theta_h = alpha^2 u / (1 - u).
        tan2 = dr.square(alpha) * u / (1.0 - u)
        cos_h = dr.rsqrt(1.0 + tan2)
        sin_h = dr.safe_sqrt(1.0 - dr.square(cos_h))
        phi = 2.0 * dr.pi * v
        h = mi.Vector3f(sin_h * dr.cos(phi), sin_h * dr.sin(phi), cos_h)
        o_dot_h = dr.dot(wo, h)
        wi = 2.0 * o_dot_h * h - wo
        # pdf(wi) = D(h) cos_h / (4 o.h); f_s cos_i / pdf.
        d = brdf.ggx_d(cos_h, alpha, dr.square(h.x) + dr.square(h.y))
        pdf = d * cos_h / dr.maximum(4.0 * o_dot_h, 1e-12)
        f = brdf.specular(wi, wo, tau, f0, shadowing)
        ok = (o_dot_h > 0) & (wi.z > 0) & (pdf > 0)
        term = dr.select(ok, f * wi.z / dr.maximum(pdf, 1e-30), 0.0)
        table = dr.block_sum(term, s * s) / (s * s)
        dr.eval(table)
    return table


def table(f0: float = brdf.F0_DEFAULT, shadowing: str = "smith") -> mi.Float:
    """The (TABLE_NODES x TABLE_NODES) table of ``E_s`` for ``f0`` and
    ``shadowing``, built on first use and kept."""
    key = (round(float(f0), 6), str(shadowing))
    if key not in _tables:
        values = np.clip(np.array(_build(*key), np.float32), 0.0, 1.0)
        _tables[key] = jit_array(mi.Float, values)
    return _tables[key]


def directional_albedo(cos_o, roughness, f0=brdf.F0_DEFAULT, shadowing="smith"):
    """``E_s(cos_o, roughness)``, bilinear in the table: differentiable in both
    (the roughness' gradient is the table's slope between nodes)."""
    n = TABLE_NODES
    values = table(f0, shadowing)
    x = dr.clip(cos_o, 0.0, 1.0) * (n - 1)
    y = dr.clip(roughness, 0.0, 1.0) * (n - 1)
    x0 = dr.minimum(mi.UInt32(dr.floor(dr.detach(x))), n - 2)
    y0 = dr.minimum(mi.UInt32(dr.floor(dr.detach(y))), n - 2)
    fx, fy = x - mi.Float(x0), y - mi.Float(y0)
    at = lambda i, j: dr.gather(mi.Float, values, i * n + j)  # noqa: E731
    low = at(x0, y0) * (1 - fy) + at(x0, y0 + 1) * fy
    high = at(x0 + 1, y0) * (1 - fy) + at(x0 + 1, y0 + 1) * fy
    return dr.select(cos_o > brdf.COS_EPS, low * (1 - fx) + high * fx, 0.0)


def sky_specular(directions, radiance, wo, roughness, samples, f0=brdf.F0_DEFAULT,
                 shadowing="smith"):
    """Light the specular lobe reflects towards ``wo`` from ``samples`` sky
    directions: ``E_s(cos_o, roughness)`` times the radiance of the
    directions averaged with the lobe's weights (the lobe widened to at
    least :func:`lobe_floor`).

    ``directions`` and ``radiance`` are callables of the sample index
    returning the local direction (Vector3f) and the radiance arriving
    along it (Color3f); ``wo`` is local too. Zero where no sample lies in
    the lobe's weight or ``wo`` is below the surface."""
    alpha = brdf.clamp_alpha(roughness)
    widened = dr.sqrt(dr.square(alpha) + lobe_floor(samples) ** 2)
    total, weight = mi.Color3f(0.0), mi.Float(0.0)
    for i in range(int(samples)):
        w = brdf.specular(directions(i), wo, widened, f0, shadowing)
        total += radiance(i) * w
        weight += w
    mean = dr.select(weight > 1e-12, total / dr.maximum(weight, 1e-12), 0.0)
    return mean * directional_albedo(mi.Frame3f.cos_theta(wo), roughness, f0, shadowing)
