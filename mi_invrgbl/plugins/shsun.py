"""``shsun``: the InvRGB+L sky (real spherical harmonics) plus a sun, as a Mitsuba emitter."""

from __future__ import annotations

import math
import re

import drjit as dr
import mitsuba as mi
import numpy as np

from ..physics.host_arrays import jit_array
from ..physics.sh import (MAX_ORDER, Y0, as_coeffs, eval_sh_numpy, num_coeffs,  # noqa: F401
                 order_from_count, project_sh, sh_basis_numpy, sphere_quadrature)

_variant = mi.variant()

#: Resolution of the sky's sampling table: cells uniform in azimuth φ and in
#: z = cos θ, so every cell covers the same solid angle 4π / (W·H).
TABLE_W, TABLE_H = 64, 32
#: Sub-samples per cell side when tabulating the sky.
TABLE_SUB = 4
#: Floor added to every cell, relative to the mean cell weight: keeps the pdf
#: positive wherever the sky might be bright between the tabulated points.
TABLE_FLOOR = 0.02
#: Bounds of the probability of sampling the sun cone when sky and sun both shine.
P_SUN_MIN, P_SUN_MAX = 0.1, 0.9
#: Distance of the emitting point of a sampled direction when no bounding sphere
#: is known (Mitsuba does not forward ``set_scene`` to Python emitters): far
#: outside any street scene, yet small enough for float32 shadow rays.
FAR_DISTANCE = 1e6


class SHSunEmitter(mi.Emitter):
    r"""
    .. _emitter-shsun:

    Spherical-harmonics sky with a sun (:monosp:`shsun`)
    -----------------------------------------------------

    .. pluginparameters::

     * - sh
       - |string| or tensor
       - Real SH coefficients of the sky radiance, coefficient-major RGB
         (``c0.r c0.g c0.b c1.r ...``), comma and/or space separated, or a (K,3)
         tensor; ``3*(order+1)^2`` values. (Default: order 0 with a uniform grey
         sky of radiance 1, i.e. ``c0 = 1/Y_0``.)
       - |exposed|, |differentiable| (flat Float of 3K values)

     * - order
       - |int|
       - SH order 0..3 (the paper uses 3: 16x3 coefficients). (Default: inferred
         from the number of coefficients.)

     * - sun_direction
       - |vector|
       - Direction *towards* the sun in world space; normalised on use.
         (Default: (0, 0, 1), straight up.)
       - |exposed|, |differentiable|

     * - sun_irradiance
       - |spectrum|
       - Irradiance (RGB) the sun delivers to a surface facing it; 0 disables it.
         (Default: 0)
       - |exposed|, |differentiable|

     * - sun_radius
       - |float|
       - Angular radius of the sun disk in degrees, in (0, 90). (Default: 0.265,
         the real sun.)

     * - to_world
       - |transform|
       - Rotation of the SH sky's frame. The sky is evaluated at
         ``to_world⁻¹ · d``; with the default identity world +z is the SH polar
         axis ("up"). ``sun_direction`` is world space and not rotated.

    The sky radiance is :math:`L_{sky}(d) = \max(0, \sum_k c_k Y_k(d))` with the
    real, orthonormal SH basis of ``dr.sh_eval`` (polar axis +z, Condon-Shortley
    phase; :math:`Y_0 = 0.282095`, :math:`Y_{1,-1..1} = -0.4886\,y,\ 0.4886\,z,\
    -0.4886\,x`, ...; see ``mi_invrgbl/physics/sh.py``). The sun is a disk of uniform
    radiance :math:`E / (\pi \sin^2 r)` of angular radius :math:`r` around the sun
    direction, so a surface facing it receives exactly the irradiance :math:`E`.

    Unlike the paper's shading sum, where the sun adds :math:`I_{sun}\,(\omega_{sun}
    \cdot n)` without the BRDF, here the sun is an ordinary (small) light source:
    the BSDF multiplies it, so glossy surfaces show a highlight and Mitsuba's
    stock ``path``/``direct`` integrators render it with shadows. Directions are
    importance-sampled from a mixture of uniform sampling of the sun cone and a
    piecewise-constant equal-area table of the sky; ``pdf_direction`` is the exact
    mixture density, so MIS and the estimates stay unbiased.

    Python accessors (used by the ``invrgbl`` integrator): ``sky_radiance(d)``,
    ``sun_direction_world()``, ``sun_irradiance_value()``, ``has_sun()``,
    ``sh_coefficients()``.

    Mitsuba does not call ``set_scene`` on Python emitters; sampled directions are
    emitted from :data:`FAR_DISTANCE`. Call ``set_scene(scene)`` yourself before
    using ``sample_ray`` (light tracing) so rays start on the scene's bounding sphere.

    .. tabs::

        .. code-tab:: xml

            <emitter type="shsun">
                <string name="sh" value="3.5 3.8 4.4,  0 0 0,  1.2 1.3 1.6,  0 0 0"/>
                <vector name="sun_direction" x="0.3" y="0.2" z="0.9"/>
                <rgb name="sun_irradiance" value="30, 28, 25"/>
            </emitter>
    """

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.m_flags = mi.EmitterFlags.Infinite | mi.EmitterFlags.SpatiallyVarying

        coeffs = _parse_sh(props["sh"]) if "sh" in props else None
        order = props.get("order", None)
        if order is not None:
            order = int(order)
            if not 0 <= order <= MAX_ORDER:
                raise ValueError("shsun: 'order' must be in 0..%d, got %d" % (MAX_ORDER, order))
        if coeffs is None:
            coeffs = np.zeros((num_coeffs(order or 0), 3))
            coeffs[0] = 1.0 / Y0  # a uniform grey sky of radiance 1
        self._order = _check_sh(coeffs, order)
        self.sh = jit_array(mi.Float, coeffs)

        self.sun_direction = mi.Vector3f(*map(float, _parse_direction(props.get("sun_direction", [0, 0, 1]))))
        self.sun_irradiance = mi.Color3f(*map(float, _parse_irradiance(props.get("sun_irradiance", 0.0))))

        radius = float(props.get("sun_radius", 0.265))
        if not (math.isfinite(radius) and 0.0 < radius < 90.0):
            raise ValueError("shsun: 'sun_radius' must be an angle in degrees in (0, 90), "
                             "got %r" % radius)
        r = math.radians(radius)
        self._sun_radius_deg = radius
        self._sin2_r = math.sin(r) ** 2
        # 1 - cos r, written so that it stays accurate for a 0.27 degree sun in float32
        self._one_minus_cos_r = 2.0 * math.sin(0.5 * r) ** 2
        self._sun_scale = 1.0 / (math.pi * self._sin2_r)  # radiance per unit irradiance

        to_world = props.get("to_world", None)
        self._local_from_world = _rotation_part(to_world)

        self._bsphere_center = np.zeros(3)
        self._bsphere_radius = None
        self.parameters_changed([])

    # ----------------------------------------------------------- parameters

    def traverse(self, callback):
        flags = mi.ParamFlags.Differentiable
        callback.put("sh", self.sh, flags)
        callback.put("sun_direction", self.sun_direction, flags)
        callback.put("sun_irradiance", self.sun_irradiance, flags)

    def parameters_changed(self, keys=[]):
        """Check the (possibly optimised) values and rebuild the sampling tables."""
        coeffs = np.asarray(dr.detach(self.sh), np.float64)
        if coeffs.size != 3 * num_coeffs(self._order):
            raise ValueError("shsun: 'sh' must keep its %d values (order %d), got %d"
                             % (3 * num_coeffs(self._order), self._order, coeffs.size))
        if not np.all(np.isfinite(coeffs)):
            raise ValueError("shsun: 'sh' contains NaN or infinite values")
        _parse_direction(np.asarray(dr.detach(self.sun_direction), np.float64).ravel())
        irradiance = _parse_irradiance(
            np.asarray(dr.detach(self.sun_irradiance), np.float64).ravel())
        self._has_sun = bool(np.any(irradiance > 0))

        # Sky table: mean (over sub-samples) of the channel-averaged clamped sky,
        # per equal-area cell, in world space.
        W, H, S = TABLE_W, TABLE_H, TABLE_SUB
        u = (np.arange(W * S) + 0.5) / (W * S)
        v = (np.arange(H * S) + 0.5) / (H * S)
        vv, uu = np.meshgrid(v, u, indexing="ij")
        z = 1.0 - 2.0 * vv
        s = np.sqrt(np.maximum(0.0, 1.0 - z * z))
        phi = 2.0 * np.pi * uu
        dirs = np.stack([s * np.cos(phi), s * np.sin(phi), z], -1).reshape(-1, 3)
        sky = np.maximum(0.0, eval_sh_numpy(coeffs, dirs @ self._local_from_world.T))
        cells = sky.mean(axis=1).reshape(H, S, W, S).mean(axis=(1, 3))
        mean_sky = float(cells.mean())
        weights = cells + TABLE_FLOOR * mean_sky if mean_sky > 0 else np.ones_like(cells)
        self._sky_dist = mi.DiscreteDistribution2D(np.asarray(weights, np.float32))

        # Share of samples sent to the sun: ratio of the irradiance each delivers
        # to a surface facing it (a uniform sky of radiance L gives π L).
        sun_e, sky_e = float(irradiance.mean()), math.pi * mean_sky
        if not self._has_sun:
            p_sun = 0.0
        elif sky_e <= 0.0:
            p_sun = 1.0
        else:
            p_sun = min(P_SUN_MAX, max(P_SUN_MIN, sun_e / (sun_e + sky_e)))
        self._p_sun_value = p_sun
        # Opaque: changing values must not bake new literals into the kernels.
        self._p_sun = dr.opaque(mi.Float, p_sun)
        for value in (self.sh, self.sun_direction, self.sun_irradiance):
            dr.make_opaque(value)

    def set_scene(self, scene):
        """Record the scene's bounding sphere (used by ``sample_ray``).

        Mitsuba does not forward this call to Python emitters: call it yourself.
        """
        bbox = scene.bbox()
        if bbox.valid():
            sphere = bbox.bounding_sphere()
            self._bsphere_center = np.array(sphere.center, np.float64).ravel()
            self._bsphere_radius = max(float(sphere.radius), 1e-3)

    # ------------------------------------------------------ Python accessors

    @property
    def order(self) -> int:
        return self._order

    def sh_coefficients(self) -> np.ndarray:
        """Current SH coefficients as a numpy (K,3) array (detached)."""
        return np.asarray(dr.detach(self.sh), np.float64).reshape(-1, 3)

    def sky_radiance(self, d_world: mi.Vector3f) -> mi.Color3f:
        """Sky radiance (SH only, no sun, clamped at 0) arriving from world direction ``d_world``."""
        d = self._to_local(d_world)
        basis = dr.sh_eval(d, self._order)
        value = mi.Color3f(0.0)
        for k, y in enumerate(basis):
            c = mi.Color3f(*[dr.gather(mi.Float, self.sh, mi.UInt32(3 * k + i)) for i in range(3)])
            value += c * y
        return dr.maximum(value, 0.0)

    def sun_direction_world(self) -> mi.Vector3f:
        """Unit vector towards the sun, world space (differentiable)."""
        return dr.normalize(self.sun_direction)

    def sun_irradiance_value(self) -> mi.Color3f:
        """Sun irradiance (RGB) on a surface facing the sun."""
        return mi.Color3f(self.sun_irradiance)

    def has_sun(self) -> bool:
        """Whether the sun shines (irradiance > 0 in some channel)."""
        return self._has_sun

    def sun_radius(self) -> float:
        """Angular radius of the sun disk in degrees."""
        return self._sun_radius_deg

    # ---------------------------------------------------------- radiance

    def _to_local(self, d):
        m = self._local_from_world.tolist()  # Python floats: numpy scalars would pull
        if m == np.eye(3).tolist():             # the (symbolic) Dr.Jit arrays into numpy
            return mi.Vector3f(d)
        return mi.Vector3f(*[m[i][0] * d.x + m[i][1] * d.y + m[i][2] * d.z for i in range(3)])

    def _in_sun(self, d, s):
        # Angle test via |d × s|² = sin² of the angle: exact enough for a tiny disk,
        # where a cosine test would drown in float32 rounding.
        return (dr.dot(d, s) > 0.0) & (dr.squared_norm(dr.cross(d, s)) <= self._sin2_r)

    def _radiance(self, d, active=True):
        value = self.sky_radiance(d)
        if self._has_sun:
            sun = self.sun_irradiance * self._sun_scale
            value += dr.select(self._in_sun(d, self.sun_direction_world()), sun, 0.0)
        return dr.select(active, value, 0.0)

    def _pdf(self, d, active=True):
        d = dr.detach(d)
        phi = dr.atan2(d.y, d.x)
        phi = dr.select(phi < 0.0, phi + 2.0 * dr.pi, phi)
        ix = dr.minimum(mi.UInt32(phi * (TABLE_W / (2.0 * dr.pi))), TABLE_W - 1)
        iy = dr.minimum(mi.UInt32(dr.maximum(1.0 - d.z, 0.0) * (0.5 * TABLE_H)), TABLE_H - 1)
        sky = self._sky_dist.pdf(mi.Point2u(ix, iy)) * (TABLE_W * TABLE_H / (4.0 * dr.pi))
        pdf = (1.0 - self._p_sun) * sky
        if self._has_sun:
            s = dr.detach(self.sun_direction_world())
            cone = 1.0 / (2.0 * math.pi * self._one_minus_cos_r)
            pdf += self._p_sun * dr.select(self._in_sun(d, s), cone, 0.0)
        return dr.select(active, pdf, 0.0)

    def _sample(self, sample):
        """A world direction towards the sky/sun from a uniform 2D sample."""
        p_sun = self._p_sun
        x_sky = (sample.x - p_sun) / dr.maximum(1.0 - p_sun, 1e-8)
        idx, _, rest = self._sky_dist.sample(mi.Point2f(dr.clip(x_sky, 0.0, 1.0), sample.y))
        phi = (2.0 * dr.pi / TABLE_W) * (mi.Float(idx.x) + rest.x)
        z = 1.0 - (2.0 / TABLE_H) * (mi.Float(idx.y) + rest.y)
        sin_t = dr.safe_sqrt(1.0 - z * z)
        d = mi.Vector3f(sin_t * dr.cos(phi), sin_t * dr.sin(phi), z)
        if self._has_sun:
            pick_sun = sample.x < p_sun
            # Uniform cone: 1 - cos θ uniform in [0, 1 - cos r]; sin θ from it directly.
            t = dr.clip(sample.x / dr.maximum(p_sun, 1e-8), 0.0, 1.0) * self._one_minus_cos_r
            sin_c = dr.safe_sqrt(t * (2.0 - t))
            phi_c = 2.0 * dr.pi * sample.y
            local = mi.Vector3f(sin_c * dr.cos(phi_c), sin_c * dr.sin(phi_c), 1.0 - t)
            # Attached sun direction: sun samples move with it, so gradients with
            # respect to sun_direction flow through the shading of the sample.
            d_sun = mi.Frame3f(self.sun_direction_world()).to_world(local)
            d = dr.select(pick_sun, d_sun, d)
        return d

    # ---------------------------------------------------------- Emitter API

    def eval(self, si, active=True):
        return self._radiance(-si.wi, active)

    def eval_direction(self, it, ds, active=True):
        return self._radiance(ds.d, active)

    def pdf_direction(self, it, ds, active=True):
        return self._pdf(ds.d, active)

    def sample_direction(self, it, sample, active=True):
        d = self._sample(sample)
        pdf = self._pdf(d, active)
        weight = dr.select(pdf > 0.0, self._radiance(d, active) / pdf, 0.0)

        ds = dr.zeros(mi.DirectionSample3f)
        dist = self._far_distance(it.p)
        ds.p = it.p + d * dist
        ds.n = -d
        ds.d = d
        ds.dist = dist
        ds.pdf = pdf
        ds.time = it.time
        ds.delta = mi.Bool(False)
        ds.emitter = mi.EmitterPtr(self)
        return ds, weight

    def sample_ray(self, time, sample1, sample2, sample3, active=True):
        d = self._sample(sample2)  # towards the sky
        pdf_dir = self._pdf(d, active)
        center = mi.Point3f(*map(float, self._bsphere_center))
        radius = self._bsphere_radius if self._bsphere_radius else FAR_DISTANCE
        # Start on a disk of the bounding sphere's radius facing the scene.
        offset = mi.warp.square_to_uniform_disk_concentric(sample3) * radius
        origin = center + d * radius + mi.Frame3f(d).to_world(mi.Vector3f(offset.x, offset.y, 0.0))
        pdf = pdf_dir / (dr.pi * radius * radius)
        weight = dr.select(pdf > 0.0, self._radiance(d, active) / pdf, 0.0)
        return mi.Ray3f(origin, -d, time), weight

    def sample_wavelengths(self, si, sample, active=True):
        # RGB variant: no wavelengths to sample; the radiance is the spectral weight.
        return dr.zeros(type(si.wavelengths), dr.width(sample)), self._radiance(-si.wi, active)

    def pdf_wavelengths(self, wavelengths, active=True):
        raise NotImplementedError("shsun: pdf_wavelengths is not defined for an RGB emitter")

    def sample_position(self, time, sample, active=True):
        raise NotImplementedError("shsun: an infinite emitter has no position to sample")

    def pdf_position(self, ps, active=True):
        raise NotImplementedError("shsun: an infinite emitter has no position density")

    def bbox(self):
        return mi.ScalarBoundingBox3f()  # infinite: contributes nothing to the scene bounds

    def to_string(self):
        return ("SHSunEmitter[order=%d, sun_direction=%s, sun_irradiance=%s, "
                "sun_radius=%g deg]" % (self._order, self.sun_direction,
                                         self.sun_irradiance, self._sun_radius_deg))

    def _far_distance(self, p):
        if self._bsphere_radius is None:
            return mi.Float(FAR_DISTANCE)
        center = mi.Point3f(*map(float, self._bsphere_center))
        # Like Mitsuba's constant emitter: outside the scene even for a reference
        # point (a sensor) that lies outside the bounding sphere.
        return 2.0 * dr.maximum(self._bsphere_radius, dr.norm(p - center))


# ------------------------------------------------------------- parsing


def _parse_sh(value):
    if isinstance(value, str):
        items = [t for t in re.split(r"[,\s]+", value.strip()) if t]
        try:
            values = np.array([float(t) for t in items], np.float64)
        except ValueError:
            raise ValueError("shsun: 'sh' must be numbers separated by commas or spaces, "
                             "got %r" % value) from None
    else:
        values = np.asarray(value, np.float64).ravel()
    if values.size % 3:
        raise ValueError("shsun: 'sh' needs 3 values (RGB) per coefficient, got %d values"
                         % values.size)
    return values.reshape(-1, 3)


def _check_sh(coeffs, order):
    """Validate (K,3) coefficients against ``order`` (None: infer); return the order."""
    if not np.all(np.isfinite(coeffs)):
        raise ValueError("shsun: 'sh' contains NaN or infinite values")
    count = coeffs.shape[0]
    if order is None:
        try:
            return order_from_count(count)
        except ValueError as e:
            raise ValueError("shsun: 'sh': %s" % e) from None
    if count != num_coeffs(order):
        raise ValueError("shsun: 'sh' has %d coefficients (%d values) but 'order' %d needs %d "
                         "(%d values)" % (count, 3 * count, order, num_coeffs(order),
                                          3 * num_coeffs(order)))
    return order


def _parse_direction(value):
    d = np.asarray(value, np.float64).ravel()
    n = float(np.linalg.norm(d)) if d.size == 3 and np.all(np.isfinite(d)) else 0.0
    if d.size != 3 or not n > 0.0:
        raise ValueError("shsun: 'sun_direction' must be a finite non-zero 3D vector, got %s"
                         % (d.tolist(),))
    return d / n


def _parse_irradiance(value):
    e = np.asarray(value, np.float64).ravel()
    if e.size == 1:
        e = np.repeat(e, 3)
    if e.size != 3 or not np.all(np.isfinite(e)) or np.any(e < 0):
        raise ValueError("shsun: 'sun_irradiance' must be a finite non-negative RGB value, "
                         "got %s" % (e.tolist(),))
    return e


def _rotation_part(to_world):
    """numpy 3x3 mapping world directions into the sky frame (inverse of to_world)."""
    if to_world is None:
        return np.eye(3)
    m = np.array(to_world.matrix, np.float64).reshape(4, 4)[:3, :3]
    if not np.allclose(m.T @ m, np.eye(3), atol=1e-4) or np.linalg.det(m) < 0:
        raise ValueError("shsun: 'to_world' must be a rotation (it only orients the sky)")
    return m.T


def register():
    mi.register_emitter("shsun", lambda props: SHSunEmitter(props))
