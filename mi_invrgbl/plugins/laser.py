r"""The ``laser`` emitter: a LiDAR's own pulse for Mitsuba's stock integrators.

.. _emitter-laser:

LiDAR laser pulse (:monosp:`laser`)
-----------------------------------

.. pluginparameters::

 * - power
   - |float|
   - Radiant intensity :math:`P_e` of the pulse (W/sr), the same in every
     direction and every colour channel. (Default: 1.0)
   - |exposed|, |differentiable|

 * - to_world
   - |transform|
   - Pose of the LiDAR; the laser sits at its origin. Give the ``lidar``
     sensor the same transform. (Default: identity)

 * - position
   - |point|
   - Alternative to ``to_world``: the laser's position. (Default: none)
   - |exposed|

The pulse is modelled as an isotropic point source of radiant intensity
:math:`P_e`. Co-located with a ``lidar`` sensor, any stock integrator that
samples emitters (``path``, ``direct``, ``prb``) then renders the LiDAR
return of the paper's model: a surface point at distance :math:`d` whose
normal makes an angle :math:`\theta` with the beam sends back the radiance

.. math::

    L = f_r(\omega, \omega)\, P_e \cos\theta / d^2,

which is :math:`\rho/\pi \cdot P_e \cos\theta / d^2` for a ``diffuse`` BSDF of
reflectance :math:`\rho`. Being a delta light it cannot be hit by rays;
shadow rays towards it account for occluders between the surface and the
sensor.

Python attribute for integrators: ``power`` (``mi.Float``) and ``position``
(``mi.Point3f``, world space).

.. tabs::

    .. code-tab:: python

        'type': 'laser',
        'power': 1.0,
        'to_world': mi.ScalarTransform4f().translate([0, 0, 1.7]),
"""

from __future__ import annotations

import numpy as np
import drjit as dr
import mitsuba as mi

_variant = mi.variant()


class LaserError(ValueError):
    """An invalid ``laser`` parameter; the message names it."""


class LaserEmitter(mi.Emitter):
    __doc__ = __doc__

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.m_flags = mi.EmitterFlags.DeltaPosition
        if "position" in props:
            if "to_world" in props:
                raise LaserError("laser: give either 'position' or 'to_world', not both")
            p = props.get("position")
            self.position = mi.Point3f(*(float(v) for v in p))
        else:
            # The laser sits at the origin of `to_world`: its translation column.
            m = np.asarray(props.get("to_world", mi.ScalarTransform4f()).matrix,
                           dtype=np.float64).reshape(4, 4)
            if not np.all(np.isfinite(m)):
                raise LaserError("laser: parameter 'to_world' contains NaN or Inf")
            self.position = mi.Point3f(*(float(v) for v in m[:3, 3]))
        self.power = mi.Float(float(props.get("power", 1.0)))
        self._validate()

    def _validate(self):
        for name, value in (("position", self.position), ("power", self.power)):
            if not np.all(np.isfinite(np.asarray(value.numpy(), dtype=np.float64))):
                raise LaserError("laser: parameter '%s' contains NaN or Inf" % name)
        if dr.width(self.power) != 1 or dr.width(self.position) != 1:
            raise LaserError("laser: parameters 'power' and 'position' must be single values")
        if float(self.power.numpy()[0]) < 0.0:
            raise LaserError("laser: parameter 'power' must be >= 0, got %g"
                             % float(self.power.numpy()[0]))

    def traverse(self, callback):
        callback.put("power", self.power, mi.ParamFlags.Differentiable)
        callback.put("position", self.position, mi.ParamFlags.NonDifferentiable)

    def parameters_changed(self, keys):
        self._validate()

    # ------------------------------------------------------------ Mitsuba API

    def sample_direction(self, it, sample, active=True):
        ds = dr.zeros(mi.DirectionSample3f)
        ds.p = mi.Point3f(self.position)
        ds.time = it.time
        ds.pdf = mi.Float(1.0)
        ds.delta = mi.Bool(True)
        ds.emitter = mi.EmitterPtr(self)
        d = ds.p - it.p
        dist2 = dr.squared_norm(d)
        ds.dist = dr.sqrt(dist2)
        ds.d = d / ds.dist
        # Delta position: the "estimate" is the incident irradiance factor
        # P_e / d^2 (the cosine at the receiver is the integrator's job).
        weight = mi.Spectrum(self.power / dist2)
        return ds, dr.select(active, weight, 0.0)

    def pdf_direction(self, it, ds, active=True):
        return mi.Float(0.0)

    def eval_direction(self, it, ds, active=True):
        dist2 = dr.squared_norm(mi.Point3f(self.position) - it.p)
        return dr.select(active, mi.Spectrum(self.power / dist2), 0.0)

    def eval(self, si, active=True):
        # A point source is never hit by a ray.
        return mi.Spectrum(0.0)

    def sample_position(self, time, sample, active=True):
        ps = dr.zeros(mi.PositionSample3f)
        ps.p = mi.Point3f(self.position)
        ps.time = time
        ps.pdf = mi.Float(1.0)
        ps.delta = mi.Bool(True)
        return ps, mi.Spectrum(1.0)

    def pdf_position(self, ps, active=True):
        return mi.Float(0.0)

    def sample_ray(self, time, wavelength_sample, spatial_sample, direction_sample,
                   active=True):
        d = mi.warp.square_to_uniform_sphere(direction_sample)
        ray = mi.Ray3f(mi.Point3f(self.position), d, time, mi.Color0f())
        # Uniform sphere pdf 1/(4 pi): the weight is the total power 4 pi P_e.
        return ray, dr.select(active, mi.Spectrum(4.0 * dr.pi * self.power), 0.0)

    def sample_wavelengths(self, si, sample, active=True):
        return mi.Color0f(), mi.Spectrum(self.power)

    def bbox(self):
        p = mi.ScalarPoint3f(*(float(v[0]) for v in self.position.numpy()))
        return mi.ScalarBoundingBox3f(p, p)

    def is_environment(self):
        return False

    def to_string(self):
        p = self.position.numpy().ravel()
        return "LaserEmitter[power=%g, position=[%g, %g, %g]]" % (
            float(self.power.numpy()[0]), p[0], p[1], p[2])


def register():
    mi.register_emitter("laser", lambda props: LaserEmitter(props))
