"""Diffuse light through a rough dielectric coat (``diffuse_fresnel``).

A plastic-like surface is a Lambertian base under a rough dielectric
interface. The paper's model adds the base's ``rho / pi`` to the specular
lobe as if the interface let every photon through; a coated surface instead
passes its diffuse light through the interface twice, and what the interface
reflects or masks on the way never reaches the base. Mitsuba's
``roughplastic`` (the BSDF the synthetic street is rendered with) models it
so, and the factor is far from 1 for rough coats: under GGX with Smith
masking, the coated lobe of alpha 0.8 is 0.44 of the Lambertian lobe lit and
seen head-on and 0.25 seen 80 degrees from the normal (where the camera of
a car sees the road), against 0.97 and 0.65 for a smooth coat. Most of the
difference is the light the base sends up again: a rough coat's masking
loses much of what a smooth coat reflects back down to the base.

The diffuse term of a coated surface is

    rho / pi * T(cos_i, alpha) * T(cos_o, alpha) / (eta^2 (1 - R_in(alpha)))

* ``T(mu, alpha)``: the coat's transmittance from outside at ``mu`` to its
  normal: the mean over the microfacet normals the light sees (GGX visible
  normals) of the Fresnel transmission ``1 - F`` times Smith's masking of
  the refracted direction. A smooth coat (alpha -> 0) gives ``1 - F(mu)``.
* ``R_in(alpha)``: the coat's reflectance seen from inside, averaged over a
  cosine-weighted hemisphere (total internal reflection included): the share
  of the base's light the coat sends back down. ``1 / (1 - R_in)`` sums the
  light that bounces between base and coat (``roughplastic``'s linear form,
  which keeps ``rho`` the base colour), and ``1 / eta^2`` spreads the light
  that leaves the denser medium over the wider outside solid angle.

Both are integrals with no closed form, so they are tabulated once per coat
IOR by quadrature over the visible normals (``COS_STEPS`` cosines x
``ALPHA_STEPS`` roughnesses, ``QUADRATURE`` x ``QUADRATURE`` nodes each) and
read back with bilinear interpolation, differentiable in the cosine and the
roughness. ``tests/test_coat.py`` checks the tables against Mitsuba's own
``roughplastic`` and the smooth limit against the Fresnel equations.

The bounce light one Gaussian passes to another leaves the blocker through
its coat (:func:`way_out` at the angle towards the receiver) and enters the
receiver through its own (:func:`transmission` at the angle it arrives), as
direct light does (:meth:`.lighting.GaussianLighting.pass_on`).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from .brdf import MIN_ALPHA, clamp_alpha, ior_from_f0
from .host_arrays import jit_array

#: Table resolution in the cosine to the normal (0..1) and in GGX alpha (0..1).
COS_STEPS = 65
ALPHA_STEPS = 33
#: Quadrature nodes per axis over the visible-normal sample square.
QUADRATURE = 48
#: The table's smallest cosine: a ray exactly along the surface has no
#: visible microfacets to sample.
MIN_COS = 1e-3

_TABLES: dict = {}


def _visible_normal_means(alpha, mu, eta, reflect):
    """Per (alpha, mu) lane pair: the mean over GGX visible normals seen from
    ``mu`` of ``F G1(reflected)`` (``reflect``) or ``(1 - F) G1(refracted)``,
    with ``eta`` the IOR of the far side over the near side."""
    n = QUADRATURE
    u = (np.arange(n) + 0.5) / n
    u1, u2 = np.meshgrid(u, u, indexing="ij")
    cells = alpha.size
    a = jit_array(mi.Float, np.repeat(alpha, n * n))
    c = np.repeat(np.clip(mu, MIN_COS, 1.0), n * n)
    wi = mi.Vector3f(jit_array(mi.Float, np.sqrt(1.0 - c * c)), 0.0, jit_array(mi.Float, c))
    sample = mi.Point2f(jit_array(mi.Float, np.tile(u1.ravel(), cells)),
                        jit_array(mi.Float, np.tile(u2.ravel(), cells)))
    distr = mi.MicrofacetDistribution(mi.MicrofacetType.GGX, a, True)
    m, _ = distr.sample(wi, sample)
    f, cos_t, _, eta_ti = mi.fresnel(dr.dot(wi, m), mi.Float(eta))
    if reflect:
        wo = mi.reflect(wi, m)
        value = dr.select(wo.z > 0, f * distr.smith_g1(wo, m), 0.0)
    else:
        wo = mi.refract(wi, m, cos_t, eta_ti)
        value = dr.select(wo.z < 0, (1.0 - f) * distr.smith_g1(wo, m), 0.0)
    value = np.array(value, np.float64).reshape(cells, n * n)
    return value.mean(axis=1)


class CoatTables:
    """``T(mu, alpha)`` on a (alpha, mu) grid and ``1 / (eta^2 (1 - R_in))``
    per alpha, for one coat IOR, as Dr.Jit arrays ready for gathers."""

    def __init__(self, eta):
        self.eta = float(eta)
        self.mu = np.linspace(0.0, 1.0, COS_STEPS)
        self.alpha = np.linspace(0.0, 1.0, ALPHA_STEPS)
        alphas = np.maximum(self.alpha, MIN_ALPHA)
        aa, mm = np.meshgrid(alphas, self.mu, indexing="ij")
        t = _visible_normal_means(aa.ravel(), mm.ravel(), self.eta, reflect=False)
        t[mm.ravel() <= 0.0] = 0.0      # light along the surface never enters
        self.transmittance_np = t.reshape(ALPHA_STEPS, COS_STEPS)
        r = _visible_normal_means(aa.ravel(), mm.ravel(), 1.0 / self.eta, reflect=True)
        r = r.reshape(ALPHA_STEPS, COS_STEPS)
        # Cosine-weighted hemispherical mean 2 int R(mu) mu dmu (trapezoids).
        r_in = 2.0 * np.trapezoid(r * self.mu[None, :], self.mu, axis=1)
        self.scale_np = 1.0 / (self.eta ** 2 * (1.0 - r_in))
        self.transmittance = jit_array(mi.Float, self.transmittance_np)
        self.scale = jit_array(mi.Float, self.scale_np)


def tables(f0) -> CoatTables:
    """The coat tables for the IOR whose normal reflectance is ``f0``
    (built on first use, per Mitsuba variant)."""
    eta = float(np.asarray(ior_from_f0(float(f0))))
    key = (mi.variant(), round(eta, 6))
    if key not in _TABLES:
        _TABLES[key] = CoatTables(eta)
    return _TABLES[key]


def _cell(x, steps):
    """Lower grid index and weight of ``x`` in [0, 1] on ``steps`` nodes."""
    pos = dr.clip(x, 0.0, 1.0) * (steps - 1)
    i = dr.minimum(mi.UInt32(dr.floor(dr.detach(pos))), steps - 2)
    return i, pos - mi.Float(i)


def transmission(cos_theta, roughness, f0):
    """``T(|cos_theta|, alpha)``: the share of light the coat lets through
    at ``cos_theta`` to its normal (two-sided, as the Lambertian term it
    weights is lit and seen from either side of a Gaussian)."""
    t = tables(f0)
    ia, wa = _cell(clamp_alpha(roughness), ALPHA_STEPS)
    im, wm = _cell(dr.abs(cos_theta), COS_STEPS)
    base = ia * COS_STEPS + im
    t00 = dr.gather(mi.Float, t.transmittance, base)
    t01 = dr.gather(mi.Float, t.transmittance, base + 1)
    t10 = dr.gather(mi.Float, t.transmittance, base + COS_STEPS)
    t11 = dr.gather(mi.Float, t.transmittance, base + COS_STEPS + 1)
    return dr.lerp(dr.lerp(t00, t01, wm), dr.lerp(t10, t11, wm), wa)


def inner_scale(roughness, f0):
    """``1 / (eta^2 (1 - R_in(alpha)))``: the light that leaves the base
    after bouncing under the coat, per unit of first-pass light."""
    t = tables(f0)
    ia, wa = _cell(clamp_alpha(roughness), ALPHA_STEPS)
    return dr.lerp(dr.gather(mi.Float, t.scale, ia), dr.gather(mi.Float, t.scale, ia + 1), wa)


def way_out(cos_o, roughness, f0):
    """What the viewer's side of the coated diffuse term contributes:
    ``T(cos_o, alpha) / (eta^2 (1 - R_in(alpha)))``. The light's side is
    :func:`transmission` at its own angle."""
    return transmission(cos_o, roughness, f0) * inner_scale(roughness, f0)
