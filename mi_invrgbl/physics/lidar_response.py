r"""The LiDAR sensor response: which intensity a sensor reports for a return.

One home for the co-located intensity formula and the sensor's response,
shared by the ``lidar_return`` integrator, the fit and the response
estimator:

.. math::  I = g_{beam}\,\pi f_r(\omega, \omega)\,P_e \cos^a\theta / (\pi d^b)

where ``pi f_r(w, w)`` is the co-located reflectance factor
(:func:`mi_invrgbl.physics.brdf.lidar_return_factor`: ``rho`` for the
Lambertian model, ``rho + pi f_s`` for the paper's), ``P_e`` the laser
power, ``g_beam`` the gain of the beam that fired, and ``a`` / ``b`` the
angle and range exponents. The paper's physics is ``a = 1, b = 2, g = 1``.
Sensors that report range-compensated reflectivity (KITTI's HDL-64E) have
``b ~ 0``; raw return strength (Waymo's) keeps ``b ~ 2``.

Clamps (the same everywhere, so a fitted scene renders what the fit saw):

* ``d`` is clamped to at least :data:`MIN_DISTANCE` (the sensor drops returns
  closer than its ``near_clip`` anyway; this only keeps ``d^-b`` finite);
* ``cos`` is clipped to ``[0, 1]``; a beam at or beyond grazing (``cos <= 0``)
  returns 0, and ``cos^a`` is evaluated as ``exp(a log max(cos, MIN_COS))`` so
  that the gradient with respect to ``a`` stays finite at grazing incidence.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import drjit as dr
import mitsuba as mi

from .host_arrays import jit_array

#: Smallest distance used in ``d^-b`` (metres).
MIN_DISTANCE = 1e-3
#: Smallest cosine used in ``log cos`` (``cos <= 0`` itself returns nothing).
MIN_COS = 1e-6
#: The paper's exponents.
PAPER_RANGE_EXPONENT = 2.0
PAPER_ANGLE_EXPONENT = 1.0


def parse_gains(value) -> list:
    """Per-beam gains from an XML string (comma or space separated) or a number."""
    if isinstance(value, str):
        return [float(v) for v in value.replace(",", " ").split()]
    return [float(value)]


def format_gains(gains) -> str:
    """The XML form of a gain list (inverse of :func:`parse_gains`)."""
    return ", ".join("%.6g" % g for g in np.asarray(gains, np.float64).ravel())


def colocated_intensity(factor, cos_theta, distance, gain=1.0, power=1.0,
                        angle_exponent=PAPER_ANGLE_EXPONENT,
                        range_exponent=PAPER_RANGE_EXPONENT):
    """``gain * factor * power * cos^a / (pi d^b)`` with the module's clamps (Dr.Jit)."""
    c = dr.clip(cos_theta, 0.0, 1.0)
    d = dr.maximum(distance, MIN_DISTANCE)
    shape = dr.exp(angle_exponent * dr.log(dr.maximum(c, MIN_COS))
                   - range_exponent * dr.log(d))
    return dr.select(c > 0, gain * factor * power * shape * dr.inv_pi, 0.0)


def colocated_intensity_np(factor, cos_theta, distance, gain=1.0, power=1.0,
                           angle_exponent=PAPER_ANGLE_EXPONENT,
                           range_exponent=PAPER_RANGE_EXPONENT) -> np.ndarray:
    """:func:`colocated_intensity` in numpy (float64), same clamps."""
    c = np.clip(np.asarray(cos_theta, np.float64), 0.0, 1.0)
    d = np.maximum(np.asarray(distance, np.float64), MIN_DISTANCE)
    shape = np.exp(angle_exponent * np.log(np.maximum(c, MIN_COS)) - range_exponent * np.log(d))
    out = np.asarray(gain, np.float64) * np.asarray(factor, np.float64) * power * shape / np.pi
    return np.where(c > 0, out, 0.0)


@dataclass
class LidarResponse:
    """A sensor's response: exponents, per-beam gains and laser power.

    ``beam_gains`` is indexed by the beam that fired (the ``lidar`` sensor's
    :py:meth:`beam_index`: the film row of a spinning sensor, the ray's own
    beam in ``rays`` mode); a beam past the end of the list gets the last
    gain, so a single value applies to every beam. The fields are Dr.Jit
    values so the fit can differentiate them.
    """
    range_exponent: mi.Float
    angle_exponent: mi.Float
    beam_gains: mi.Float
    power: mi.Float = None

    def __post_init__(self):
        if self.power is None:
            self.power = mi.Float(1.0)

    @classmethod
    def paper(cls, n_beams: int = 1, power: float = 1.0) -> "LidarResponse":
        """The paper's ``cos / d^2`` with unit gains."""
        return cls(mi.Float(PAPER_RANGE_EXPONENT), mi.Float(PAPER_ANGLE_EXPONENT),
                   dr.ones(mi.Float, max(int(n_beams), 1)), mi.Float(power))

    def gain(self, beam):
        """Gain of each ``beam`` (``mi.UInt32``)."""
        n = dr.width(self.beam_gains)
        return dr.gather(mi.Float, self.beam_gains, dr.minimum(mi.UInt32(beam), n - 1))

    def __call__(self, factor, cos_theta, distance, beam, power=None):
        """Intensity of returns with reflectance ``factor`` (``pi f_r(w, w)``)."""
        p = self.power if power is None else power
        return colocated_intensity(factor, cos_theta, distance, self.gain(beam), p,
                                   self.angle_exponent, self.range_exponent)

    def numpy(self, factor, cos_theta, distance, beam, power=None) -> np.ndarray:
        """:py:meth:`__call__` in numpy (``beam`` an int array)."""
        g = np.asarray(self.beam_gains, np.float64).ravel()
        b = np.minimum(np.asarray(beam, np.int64), g.size - 1)
        p = float(np.asarray(self.power if power is None else power).ravel()[0])
        return colocated_intensity_np(factor, cos_theta, distance, g[b], p,
                                      float(np.asarray(self.angle_exponent).ravel()[0]),
                                      float(np.asarray(self.range_exponent).ravel()[0]))


#: Features of the ray-drop model, in the order of its weights.
RETURN_FEATURES = ("log_range", "log_cos", "log_albedo")
#: Floors of the features' logarithms (a return at grazing incidence or from
#: a black surface stays finite).
RETURN_FLOOR = 1e-3


@dataclass
class ReturnModel:
    r"""Ray drop as a model: the probability that a beam reaching a surface
    reports a return,

    .. math::  p = \sigma(c_{beam} + w_1 \log d + w_2 \log\cos\theta + w_3 \log\rho)

    (``sigma`` the logistic function, ``rho`` the LiDAR albedo). Weak returns
    are lost: ``log(rho cos / d^2)`` is the log of the return strength, so
    the model holds a sensor whose detection threshold acts on it, with
    per-beam offsets ``c_beam`` for beams that see more or less. A beam with
    no surface (accumulated opacity below the hit threshold) never returns.
    """
    weights: np.ndarray        # (3,) for RETURN_FEATURES
    beam_bias: np.ndarray      # (B,) indexed by beam; past the end: the last

    def logit(self, distance, cos_theta, albedo, beam):
        """Dr.Jit log-odds of a return."""
        n = len(self.beam_bias)
        bias = dr.gather(mi.Float, jit_array(mi.Float, self.beam_bias),
                         dr.minimum(mi.UInt32(beam), n - 1))
        w = [float(v) for v in self.weights]
        return (bias + w[0] * dr.log(dr.maximum(distance, RETURN_FLOOR))
                + w[1] * dr.log(dr.maximum(cos_theta, RETURN_FLOOR))
                + w[2] * dr.log(dr.maximum(albedo, RETURN_FLOOR)))

    @staticmethod
    def features(distance, cos_theta, albedo) -> np.ndarray:
        """(N, 3) numpy features (see :data:`RETURN_FEATURES`)."""
        return np.stack([np.log(np.maximum(np.asarray(v, np.float64), RETURN_FLOOR))
                         for v in (distance, cos_theta, albedo)], axis=1)

    def logit_np(self, distance, cos_theta, albedo, beam) -> np.ndarray:
        b = np.asarray(self.beam_bias, np.float64)
        return (b[np.minimum(np.asarray(beam, np.int64), b.size - 1)]
                + self.features(distance, cos_theta, albedo) @ np.asarray(self.weights, np.float64))

    def probability_np(self, distance, cos_theta, albedo, beam) -> np.ndarray:
        return 1.0 / (1.0 + np.exp(-self.logit_np(distance, cos_theta, albedo, beam)))


def return_scores(returned, predicted) -> dict:
    """Accuracy and F1 of the drop class (no return) of a ray-drop prediction."""
    y = ~np.asarray(returned, bool).ravel()
    p = ~np.asarray(predicted, bool).ravel()
    tp = int(np.sum(y & p))
    fp = int(np.sum(~y & p))
    fn = int(np.sum(y & ~p))
    f1 = 2 * tp / max(2 * tp + fp + fn, 1)
    return {"accuracy": float(np.mean(y == p)) if y.size else float("nan"), "f1": float(f1),
            "drop_rate_observed": float(np.mean(y)) if y.size else float("nan"),
            "drop_rate_predicted": float(np.mean(p)) if p.size else float("nan"), "n": int(y.size)}
