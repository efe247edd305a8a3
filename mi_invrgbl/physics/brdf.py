"""Cook-Torrance reflectance shared by the ``cooktorrance`` BSDF and both integrators.

The model is the paper's: a Lambertian lobe ``rho / pi`` plus a Cook-Torrance
specular lobe ``F D G / (4 cos_i cos_o)`` with

* ``D``: GGX with ``alpha = roughness`` (not roughness squared, as in the paper),
* ``G``: the Cook-Torrance V-cavity term
  ``min(1, 2 cos_h cos_o / (o.h), 2 cos_h cos_i / (o.h))`` (the paper's), or
  (``shadowing="smith"``, the fit's default) Smith's separable GGX term
  ``G1(i) G1(o)``, ``G1(w) = 2 / (1 + sqrt(1 + alpha^2 tan^2 w))`` (Mitsuba's
  microfacet models). They agree at normal incidence; towards grazing the
  V-cavity term shadows far less: under a uniform sky the specular lobe of
  roughness 0.5 seen 80 degrees from the normal reflects 0.138 of the light
  with V-cavity and 0.066 with Smith (Schlick's F in both; computed in
  ``tests/test_shadowing.py``),
* ``F``: Schlick's Fresnel around ``f0`` (0.04 by default). When light and
  viewer coincide (``o.h = 1``) Schlick's term is exactly ``f0``, which is the
  constant the paper uses for LiDAR.

All functions work on Dr.Jit arrays in the local shading frame (normal = +z)
and are written so that grazing angles and roughness -> 0 stay finite:
``G / (4 cos_i cos_o)`` is evaluated as the minimum of three bounded ratios
(V-cavity) or as one product bounded by ``1 / alpha^2`` (Smith) instead of
dividing a product of small numbers by another one.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

#: Fresnel reflectance at normal incidence of a dielectric with IOR ~1.5.
F0_DEFAULT = 0.04
#: GGX alpha is clamped here: alpha -> 0 turns D into a Dirac delta, which no
#: floating-point renderer can represent; 1e-3 keeps D finite (< 1/(pi 1e-6)).
MIN_ALPHA = 1e-3
#: Cosines below this are treated as grazing (no contribution).
COS_EPS = 1e-6
#: Shadowing-masking terms ``specular`` offers: the paper's first.
SHADOWING = ("vcavity", "smith")


def clamp_alpha(roughness):
    """GGX alpha from the paper's roughness tau (alpha = tau), clamped to [MIN_ALPHA, 1]."""
    return dr.clip(roughness, MIN_ALPHA, 1.0)


def ggx_d(cos_h, alpha, sin2_h=None):
    """GGX normal distribution D(h) for ``cos_h = n.h``; 0 for back-facing h.

    ``sin2_h`` (``h.x^2 + h.y^2``), when given, replaces ``1 - cos_h^2``:
    near the peak of a smooth lobe that difference cancels to float32
    rounding noise, which is comparable to ``alpha^2`` for alpha ~ 1e-3.
    """
    a2 = dr.square(alpha)
    c2 = dr.square(cos_h)
    s2 = 1.0 - c2 if sin2_h is None else sin2_h
    denom = c2 * a2 + s2
    return dr.select(cos_h > 0, a2 / (dr.pi * dr.square(denom)), 0.0)


def vcavity_g_over_4cos(cos_i, cos_o, cos_h, o_dot_h):
    """``G / (4 cos_i cos_o)`` with the Cook-Torrance V-cavity ``G``.

    ``min(1, 2 c_h c_o / oh, 2 c_h c_i / oh) / (4 c_i c_o)`` equals
    ``min(1 / (4 c_i c_o), c_h / (2 c_i oh), c_h / (2 c_o oh))``; the right-hand
    form stays finite at grazing angles (cos -> 0).
    """
    ci = dr.maximum(cos_i, COS_EPS)
    co = dr.maximum(cos_o, COS_EPS)
    oh = dr.maximum(o_dot_h, COS_EPS)
    ch = dr.maximum(cos_h, 0.0)
    return dr.minimum(dr.rcp(4.0 * ci * co),
                      dr.minimum(ch / (2.0 * ci * oh), ch / (2.0 * co * oh)))


def _smith_denominator(cos_w, alpha):
    """``c + sqrt(alpha^2 + (1 - alpha^2) c^2)`` with ``c = max(cos_w, 0)``:
    ``G1(w) = 2 c / this``, and it stays >= alpha at grazing angles."""
    c = dr.maximum(cos_w, 0.0)
    a2 = dr.square(alpha)
    return c + dr.sqrt(a2 + (1.0 - a2) * dr.square(c))


def smith_g1(cos_w, alpha):
    """Smith's GGX masking ``G1(w) = 2 / (1 + sqrt(1 + alpha^2 tan^2 w))``
    (``2 cos / (cos + sqrt(alpha^2 + (1 - alpha^2) cos^2))``, finite at cos -> 0)."""
    return 2.0 * dr.maximum(cos_w, 0.0) / dr.maximum(_smith_denominator(cos_w, alpha), COS_EPS)


def smith_g_over_4cos(cos_i, cos_o, alpha):
    """``G1(i) G1(o) / (4 cos_i cos_o)``, evaluated as the product of the two
    denominators' reciprocals: bounded by ``1 / alpha^2`` at grazing angles."""
    return dr.rcp(dr.maximum(_smith_denominator(cos_i, alpha) * _smith_denominator(cos_o, alpha),
                             COS_EPS))


def schlick_f(f0, i_dot_h):
    """Schlick's Fresnel approximation around ``f0``."""
    m = dr.clip(1.0 - i_dot_h, 0.0, 1.0)
    m2 = dr.square(m)
    return f0 + (1.0 - f0) * (m2 * m2 * m)


def specular(wi, wo, roughness, f0=F0_DEFAULT, shadowing="vcavity"):
    """Cook-Torrance specular BRDF value f_s(wi, wo) (no cosine factor).

    ``wi`` and ``wo`` are unit vectors in the local frame pointing away from
    the surface. Returns 0 where either lies below the surface.
    ``shadowing``: ``"vcavity"`` (the paper's) or ``"smith"`` (see the module).
    """
    cos_i = mi.Frame3f.cos_theta(wi)
    cos_o = mi.Frame3f.cos_theta(wo)
    h = dr.normalize(wi + wo)
    cos_h = mi.Frame3f.cos_theta(h)
    o_dot_h = dr.dot(wo, h)
    alpha = clamp_alpha(roughness)
    if shadowing == "vcavity":
        g = vcavity_g_over_4cos(cos_i, cos_o, cos_h, o_dot_h)
    elif shadowing == "smith":
        g = smith_g_over_4cos(cos_i, cos_o, alpha)
    else:
        raise ValueError("shadowing must be one of %s (got %r)" % (", ".join(SHADOWING), shadowing))
    value = (schlick_f(f0, dr.dot(wi, h)) * ggx_d(cos_h, alpha, dr.square(h.x) + dr.square(h.y))
             * g)
    return dr.select((cos_i > COS_EPS) & (cos_o > COS_EPS), value, 0.0)


def ior_from_f0(f0):
    """The relative IOR of a dielectric whose reflectance at normal incidence is ``f0``."""
    r = dr.sqrt(dr.clip(f0, 0.0, 0.99))
    return (1.0 + r) / (1.0 - r)


def eval_brdf(albedo, roughness, wi, wo, f0=F0_DEFAULT):
    """Full BRDF ``albedo / pi + f_s`` (no cosine factor); ``albedo`` may be a colour."""
    cos_i = mi.Frame3f.cos_theta(wi)
    cos_o = mi.Frame3f.cos_theta(wo)
    front = (cos_i > COS_EPS) & (cos_o > COS_EPS)
    diffuse = albedo * dr.inv_pi
    return dr.select(front, diffuse + specular(wi, wo, roughness, f0), 0.0)


def colocated_specular_pi(roughness, cos_theta, f0=F0_DEFAULT):
    """``pi * f_s(w, w)``: the specular term of the paper's LiDAR equation.

    Equals ``F0 tau^2 min(1, 2 cos^2) / (4 cos^2 (cos^2 (tau^2 - 1) + 1)^2)``;
    finite for cos -> 0 (the limit is ``F0 tau^2 / 2``) and for tau -> 0
    (alpha is clamped to ``MIN_ALPHA``).
    """
    c = dr.clip(cos_theta, 0.0, 1.0)
    c2 = dr.square(c)
    alpha = clamp_alpha(roughness)
    a2 = dr.square(alpha)
    # min(1, 2c^2) / (4c^2) = 1/2 when 2c^2 <= 1, else 1 / (4c^2)
    g_term = dr.select(2.0 * c2 <= 1.0, 0.5, dr.rcp(4.0 * dr.maximum(c2, 0.5)))
    return f0 * a2 * g_term / dr.square(c2 * (a2 - 1.0) + 1.0)


def lidar_return_factor(lidar_albedo, roughness, cos_theta, model="pbr", f0=F0_DEFAULT):
    """``pi f_r(w, w)`` for LiDAR: ``rho`` (lambertian) or ``rho + pi f_s`` (pbr)."""
    if model == "lambertian":
        return lidar_albedo
    return lidar_albedo + colocated_specular_pi(roughness, cos_theta, f0)


def lidar_intensity(lidar_albedo, roughness, cos_theta, distance, power=1.0,
                    model="pbr", f0=F0_DEFAULT):
    """The paper's LiDAR equation ``(rho + pi f_s) P_e cos / (pi d^2)``.

    ``distance`` must be positive: callers drop returns closer than the
    sensor's minimum range before calling this.
    """
    c = dr.clip(cos_theta, 0.0, 1.0)
    return (lidar_return_factor(lidar_albedo, roughness, c, model, f0)
            * power * c / (dr.pi * dr.square(distance)))
