"""The ``cooktorrance`` BSDF: the paper's diffuse + Cook-Torrance material.

The maths lives in :mod:`mi_invrgbl.physics.brdf` so that this BSDF, the
``invrgbl`` camera integrator and the ``lidar_return`` integrator all evaluate
exactly the same reflectance.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..physics import brdf

_variant = mi.variant()


def _as_param(value, channels):
    """A scene parameter as either a ``mi.Texture`` or a plain JIT value.

    Constants stay plain values (traversed as ``albedo``, ``roughness``, ...)
    so an optimiser can update them directly; textures are kept as child
    objects (traversed as ``albedo.data`` and so on).
    """
    if isinstance(value, mi.Texture):
        return value
    if channels == 3:
        return mi.Color3f(value)
    return mi.Float(value)


def _lookup(param, si, channels):
    """Evaluate a parameter from :func:`_as_param` at ``si``."""
    if isinstance(param, mi.Texture):
        return param.eval(si) if channels == 3 else param.eval_1(si)
    return param


class CookTorranceBSDF(mi.BSDF):
    r"""
    .. _bsdf-cooktorrance:

    Cook-Torrance material of InvRGB+L (:monosp:`cooktorrance`)
    -----------------------------------------------------------

    .. pluginparameters::

     * - albedo
       - |spectrum| or |texture|
       - Diffuse albedo :math:`\rho` of the camera (RGB) lobe ``rho / pi``. (Default: 0.5)
       - |exposed|, |differentiable|

     * - roughness
       - |float| or |texture|
       - Roughness :math:`\tau` of the specular lobe; the GGX parameter is
         :math:`\alpha = \tau` (not :math:`\tau^2`), clamped to
         :math:`[10^{-3}, 1]`. (Default: 0.5)
       - |exposed|, |differentiable|

     * - lidar_albedo
       - |float| or |texture|
       - Diffuse albedo :math:`\rho_\mathrm{lidar}` at the LiDAR's infrared
         wavelength. Camera rendering ignores it; LiDAR integrators read it
         through :py:meth:`material` or ``eval_attribute_1('lidar_albedo')``.
         (Default: 0.5)
       - |exposed|, |differentiable|

     * - f0
       - |float|
       - Fresnel reflectance at normal incidence. (Default: 0.04)
       - |exposed|, |differentiable|

    The BRDF is :math:`f_r = \rho/\pi + F\,D\,G / (4\cos\theta_i\cos\theta_o)`
    with the GGX distribution :math:`D`, the Cook-Torrance V-cavity shadowing
    term :math:`G = \min(1, 2\cos\theta_h\cos\theta_o/(\omega_o\cdot h),
    2\cos\theta_h\cos\theta_i/(\omega_o\cdot h))` and Schlick's Fresnel term
    :math:`F` around :math:`F_0`. Evaluated with light and viewer co-located
    (:math:`\omega_i = \omega_o`, a LiDAR) it is exactly the paper's model
    :math:`\pi f_r = \rho + F_0\tau^2\min(1, 2\cos^2\theta) /
    (4\cos^2\theta(\cos^2\theta(\tau^2-1)+1)^2)`.

    Where it departs from the paper, it is for physical or numerical reasons:

    * The paper uses the constant :math:`F_0`, which is only right when light
      and viewer coincide. For the camera (sun, sky) the material uses
      Schlick's Fresnel, which rises towards grazing angles and equals
      :math:`F_0` at :math:`\omega_i\cdot h = 1`, i.e. in the co-located case.
    * :math:`G/(4\cos\theta_i\cos\theta_o)` is evaluated as the minimum of
      three bounded ratios, so grazing directions give finite values and
      finite gradients instead of 0/0.
    * :math:`\tau\to 0` makes GGX a Dirac delta that no renderer can
      represent; :math:`\alpha` is clamped to :math:`10^{-3}`.

    The surface is one-sided (front side only). Sampling mixes a cosine
    hemisphere for the diffuse lobe with GGX visible-normal sampling for the
    specular lobe, weighting them by the albedo's luminance and the Fresnel
    reflectance at the incident angle.

    Integrators read the material at a hit through Mitsuba's attribute
    interface, which dispatches to this Python class even for arrays of mixed
    BSDFs: ``si.bsdf().has_attribute('lidar_albedo')``,
    ``si.bsdf().eval_attribute_1('lidar_albedo' | 'roughness', si)`` and
    ``si.bsdf().eval_attribute_3('albedo', si)`` (other BSDFs answer
    ``False``/0). :py:meth:`material` returns all three at once when the
    Python object is at hand (``si.bsdf()[i]`` is that object).

    .. tabs::

        .. code-tab:: xml

            <bsdf type="cooktorrance">
                <rgb name="albedo" value="0.6, 0.5, 0.4"/>
                <float name="roughness" value="0.3"/>
                <float name="lidar_albedo" value="0.35"/>
            </bsdf>

        .. code-tab:: python

            'type': 'cooktorrance',
            'albedo': {'type': 'rgb', 'value': [0.6, 0.5, 0.4]},
            'roughness': 0.3,
            'lidar_albedo': 0.35
    """

    #: Names answered by ``has_attribute``/``eval_attribute*`` and their channel count.
    ATTRIBUTES = {"albedo": 3, "roughness": 1, "lidar_albedo": 1}

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.albedo = _as_param(props.get("albedo", 0.5), 3)
        self.roughness = _as_param(props.get("roughness", 0.5), 1)
        self.lidar_albedo = _as_param(props.get("lidar_albedo", 0.5), 1)
        self.f0 = mi.Float(props.get("f0", brdf.F0_DEFAULT))
        self._update_flags()

    # ------------------------------------------------------------------ setup

    def _update_flags(self):
        varying = any(isinstance(p, mi.Texture) for p in
                      (self.albedo, self.roughness, self.lidar_albedo))
        extra = mi.BSDFFlags.FrontSide | (mi.BSDFFlags.SpatiallyVarying if varying else 0)
        diffuse = mi.BSDFFlags.DiffuseReflection | extra
        glossy = mi.BSDFFlags.GlossyReflection | extra
        self.m_components = [diffuse, glossy]
        self.m_flags = diffuse | glossy

    def traverse(self, callback):
        flags = mi.ParamFlags.Differentiable
        callback.put("albedo", self.albedo, flags)
        callback.put("roughness", self.roughness, flags)
        callback.put("lidar_albedo", self.lidar_albedo, flags)
        callback.put("f0", self.f0, flags)

    def parameters_changed(self, keys):
        # Opaque values keep optimisation steps from baking new literals into
        # the kernels (which would recompile them at every iteration).
        for name in ("albedo", "roughness", "lidar_albedo", "f0"):
            value = getattr(self, name)
            if not isinstance(value, mi.Texture):
                dr.make_opaque(value)

    # ---------------------------------------------------------------- material

    def material(self, si, active=True):
        """``(albedo Color3f, roughness Float, lidar_albedo Float)`` at ``si``."""
        return (_lookup(self.albedo, si, 3), _lookup(self.roughness, si, 1),
                _lookup(self.lidar_albedo, si, 1))

    def has_attribute(self, name, active=True):
        return mi.Bool(name in self.ATTRIBUTES)

    def eval_attribute(self, name, si, active=True):
        if self.ATTRIBUTES.get(name) == 3:
            return mi.UnpolarizedSpectrum(_lookup(getattr(self, name), si, 3))
        if name in self.ATTRIBUTES:
            return mi.UnpolarizedSpectrum(_lookup(getattr(self, name), si, 1))
        return dr.zeros(mi.UnpolarizedSpectrum)

    def eval_attribute_1(self, name, si, active=True):
        if self.ATTRIBUTES.get(name) == 1:
            return _lookup(getattr(self, name), si, 1)
        if name == "albedo":  # luminance, as Mitsuba's textures do
            return mi.luminance(_lookup(self.albedo, si, 3))
        return dr.zeros(mi.Float)

    def eval_attribute_3(self, name, si, active=True):
        if name in self.ATTRIBUTES:
            return mi.Color3f(_lookup(getattr(self, name), si, self.ATTRIBUTES[name]))
        return dr.zeros(mi.Color3f)

    def eval_diffuse_reflectance(self, si, active=True):
        return _lookup(self.albedo, si, 3)

    # ------------------------------------------------------------- BSDF model

    @staticmethod
    def _lobes(ctx):
        """Which of the two components (0 diffuse, 1 glossy) ``ctx`` asks for."""
        return (ctx.is_enabled(mi.BSDFFlags.DiffuseReflection, 0),
                ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 1))

    def _value(self, ctx, si, wo, albedo, roughness):
        """``f_r(wi, wo) cos(theta_o)`` restricted to the lobes in ``ctx``."""
        has_diffuse, has_glossy = self._lobes(ctx)
        if has_diffuse and has_glossy:
            f = brdf.eval_brdf(albedo, roughness, si.wi, wo, self.f0)
        elif has_glossy:
            f = mi.Color3f(brdf.specular(si.wi, wo, roughness, self.f0))
        elif has_diffuse:
            front = ((mi.Frame3f.cos_theta(si.wi) > brdf.COS_EPS)
                     & (mi.Frame3f.cos_theta(wo) > brdf.COS_EPS))
            f = dr.select(front, albedo * dr.inv_pi, 0.0)
        else:
            f = dr.zeros(mi.Color3f)
        return f * dr.maximum(mi.Frame3f.cos_theta(wo), 0.0)

    def _glossy_probability(self, ctx, si, albedo):
        """Probability of sampling the specular lobe.

        Proportional to Fresnel at the incident angle (the specular lobe's
        albedo for a smooth surface) versus the diffuse albedo's luminance.
        """
        has_diffuse, has_glossy = self._lobes(ctx)
        if not has_glossy:
            return mi.Float(0.0)
        if not has_diffuse:
            return mi.Float(1.0)
        spec = brdf.schlick_f(self.f0, dr.clip(mi.Frame3f.cos_theta(si.wi), 0.0, 1.0))
        diff = dr.maximum(mi.luminance(albedo), 0.0)
        total = spec + diff
        return dr.select(total > 0, spec / dr.maximum(total, 1e-12), 0.5)

    @staticmethod
    def _distribution(roughness):
        return mi.MicrofacetDistribution(mi.MicrofacetType.GGX,
                                         brdf.clamp_alpha(roughness), True)

    def _pdf(self, ctx, si, wo, albedo, roughness):
        cos_i = mi.Frame3f.cos_theta(si.wi)
        cos_o = mi.Frame3f.cos_theta(wo)
        p_glossy = self._glossy_probability(ctx, si, albedo)
        pdf_diffuse = mi.warp.square_to_cosine_hemisphere_pdf(wo)
        m = dr.normalize(si.wi + wo)
        # Reflection about m maps the half-vector density to solid angle.
        pdf_glossy = (self._distribution(roughness).pdf(si.wi, m)
                      / (4.0 * dr.maximum(dr.dot(wo, m), 1e-12)))
        pdf_glossy = dr.select(dr.dot(wo, m) > 0, pdf_glossy, 0.0)
        pdf = p_glossy * pdf_glossy + (1.0 - p_glossy) * pdf_diffuse
        return dr.select((cos_i > brdf.COS_EPS) & (cos_o > brdf.COS_EPS), pdf, 0.0)

    def eval(self, ctx, si, wo, active=True):
        albedo, roughness, _ = self.material(si, active)
        return dr.select(active, self._value(ctx, si, wo, albedo, roughness), 0.0)

    def pdf(self, ctx, si, wo, active=True):
        albedo, roughness, _ = self.material(si, active)
        return dr.select(active, self._pdf(ctx, si, wo, albedo, roughness), 0.0)

    def eval_pdf(self, ctx, si, wo, active=True):
        albedo, roughness, _ = self.material(si, active)
        value = self._value(ctx, si, wo, albedo, roughness)
        pdf = self._pdf(ctx, si, wo, albedo, roughness)
        return dr.select(active, value, 0.0), dr.select(active, pdf, 0.0)

    def sample(self, ctx, si, sample1, sample2, active=True):
        albedo, roughness, _ = self.material(si, active)
        cos_i = mi.Frame3f.cos_theta(si.wi)
        active = mi.Bool(active) & (cos_i > brdf.COS_EPS)

        p_glossy = self._glossy_probability(ctx, si, albedo)
        glossy = sample1 < p_glossy

        m, _ = self._distribution(roughness).sample(si.wi, sample2)
        wo_glossy = mi.reflect(si.wi, m)
        wo_diffuse = mi.warp.square_to_cosine_hemisphere(sample2)

        bs = dr.zeros(mi.BSDFSample3f)
        bs.wo = dr.select(glossy, wo_glossy, wo_diffuse)
        bs.eta = 1.0
        bs.sampled_component = dr.select(glossy, mi.UInt32(1), mi.UInt32(0))
        bs.sampled_type = dr.select(glossy, mi.UInt32(+mi.BSDFFlags.GlossyReflection),
                                    mi.UInt32(+mi.BSDFFlags.DiffuseReflection))
        # The pdf of the whole mixture, so that sample() agrees with pdf()
        # and MIS in the integrators sees one consistent density.
        bs.pdf = self._pdf(ctx, si, bs.wo, albedo, roughness)
        value = self._value(ctx, si, bs.wo, albedo, roughness)

        active &= bs.pdf > 0
        bs.pdf = dr.select(active, bs.pdf, 0.0)
        weight = dr.select(active, value / dr.maximum(bs.pdf, 1e-20), 0.0)
        return bs, weight

    def to_string(self):
        return ("CookTorranceBSDF[\n  albedo = %s,\n  roughness = %s,\n"
                "  lidar_albedo = %s,\n  f0 = %s\n]"
                % (self.albedo, self.roughness, self.lidar_albedo, self.f0))


def register():
    mi.register_bsdf("cooktorrance", lambda props: CookTorranceBSDF(props))
