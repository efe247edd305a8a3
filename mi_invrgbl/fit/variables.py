"""The optimiser's variables as typed handles.

Each handle knows where its value lives (a Gaussian node's field, the sky's
SH coefficients, the sun, the LiDAR response), its learning rate, its valid
range and how to read and write itself. :class:`Optimizer` holds Adam over a
list of handles: pull (Adam -> model), clamp and commit loop over the
handles, never dispatch on names. The Gaussian fields' ranges and rates
come from :mod:`mi_invrgbl.physics.fields`.

Densification changes the number of Gaussians: :meth:`Optimizer.rebuild`
carries Adam's moments of every surviving Gaussian (and of the parent of a
clone) into the new arrays; new Gaussians start with zero moments.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import drjit as dr
import mitsuba as mi

from ..physics.fields import GaussianField
from .steps import make_optimizer


class Variable:
    """One optimised array. ``key`` names it in Adam and in checkpoints."""
    key: str
    lr: float
    #: Written into the scene on every render (the sky, the sun); Gaussian
    #: fields reach the scene through :meth:`GaussianModel.push` instead.
    in_scene: bool = False

    def read(self):
        raise NotImplementedError

    def write(self, value):
        raise NotImplementedError

    def clamp(self, value):
        return value


@dataclass(eq=False)
class GaussianVariable(Variable):
    """A field of one Gaussian node (flat, ``field.width`` per Gaussian, storage units)."""
    model: object
    node: str
    field: GaussianField
    lr: float

    @property
    def key(self):
        return "%s.%s" % (self.node, self.field.variable)

    def read(self):
        return self.model.nodes[self.node].values[self.field.variable]

    def write(self, value):
        self.model.nodes[self.node].values[self.field.variable] = value

    def clamp(self, value):
        bounds = self.field.storage_range()
        return value if bounds is None else dr.clip(value, *bounds)


@dataclass(eq=False)
class SkySH(Variable):
    """The sky's SH coefficients; those above the selected order stay zero."""
    state: object
    lr: float
    key: str = "sky.sh"
    in_scene: bool = True

    def read(self):
        return self.state.params[self.state.sky_key]

    def write(self, value):
        mask = self.state.sh_mask
        self.state.params[self.state.sky_key] = value * mask if mask is not None else value


def _positive(value):
    # Never exactly 0: shsun would then drop the sun (has_sun), the lighting
    # cache key would change and the sun could not come back.
    return dr.maximum(value, 1e-4)


def _above_horizon(value):
    # A unit vector above the horizon (2 degrees at least).
    d = dr.normalize(value)
    d.z = dr.maximum(d.z, 0.035)
    return dr.normalize(d)


@dataclass(eq=False)
class SunVariable(Variable):
    """The sun's ``sun_irradiance`` or ``sun_direction`` (a ``shsun`` parameter)."""
    state: object
    part: str
    lr: float
    in_scene: bool = True

    CLAMPS = {"sun_irradiance": _positive, "sun_direction": _above_horizon}

    @property
    def key(self):
        return "sky." + self.part

    def read(self):
        return self.state.params[getattr(self.state.sky, self.part)]

    def write(self, value):
        self.state.params[getattr(self.state.sky, self.part)] = value

    def clamp(self, value):
        return self.CLAMPS[self.part](value)


@dataclass(eq=False)
class PoseVariable(Variable):
    """One part (translation ``t`` or rotation vector ``w``) of a moving
    object's per-frame pose corrections (:class:`.object_poses.ObjectPoseFit`)."""
    poses: object
    name: str
    part: str
    lr: float
    bound: float

    @property
    def key(self):
        return self.poses.key(self.name, self.part)

    def read(self):
        return self.poses.values[self.name, self.part]

    def write(self, value):
        self.poses.values[self.name, self.part] = value

    def clamp(self, value):
        return dr.clip(value, -self.bound, self.bound)


#: LiDAR response parameters: valid ranges.
RESPONSE_RANGES = {"range_exponent": (-1.0, 4.0), "angle_exponent": (-1.0, 4.0),
                   "beam_gains": (1e-4, None)}


@dataclass(eq=False)
class ResponseVariable(Variable):
    """One array of the LiDAR sensor response (:class:`.render.Response`)."""
    state: object
    name: str
    lr: float

    @property
    def key(self):
        return "response." + self.name

    def read(self):
        return getattr(self.state.response, self.name)

    def write(self, value):
        setattr(self.state.response, self.name, mi.Float(value))

    def clamp(self, value):
        lo, hi = RESPONSE_RANGES[self.name]
        return dr.maximum(value, lo) if hi is None else dr.clip(value, lo, hi)


class Optimizer:
    """Adam over typed handles (variables with a zero learning rate are left out)."""

    def __init__(self, variables):
        self.variables = {v.key: v for v in variables if v.lr != 0.0}
        self.adam = make_optimizer({k: v.read() for k, v in self.variables.items()},
                                   {k: v.lr for k, v in self.variables.items()})
        #: Factor on every learning rate, below 1 once a budgeted stage's
        #: validation score has levelled off (:meth:`set_damping`); the
        #: schedules of :meth:`scale_learning_rates` apply on top of it.
        self.damping = 1.0

    def __contains__(self, variable):
        return variable.key in self.variables

    def value(self, variable):
        return self.adam[variable.key]

    def items(self):
        """(handle, current Adam value) pairs."""
        return [(v, self.adam[k]) for k, v in self.variables.items()]

    def pull(self):
        """Write Adam's (grad-enabled) values into their homes."""
        for v, value in self.items():
            v.write(value)

    def clamp(self):
        for k, v in self.variables.items():
            self.adam[k] = v.clamp(self.adam[k])

    def commit(self):
        """Write the detached values into their homes."""
        for v, value in self.items():
            v.write(dr.detach(value))

    def scale_learning_rates(self, factor, which):
        """Set the learning rate of every handle ``which(handle)`` accepts to
        ``factor`` times its own (a schedule), times :attr:`damping`."""
        for k, v in self.variables.items():
            if which(v):
                self.adam.set_learning_rate({k: float(v.lr * factor * self.damping)})

    def set_damping(self, damping):
        """Every learning rate to ``damping`` times its own (a stage's
        schedule, applied at its next step, multiplies it again)."""
        self.damping = float(damping)
        self.scale_learning_rates(1.0, lambda v: True)

    def moments(self, key):
        """(t, m, v) of one variable as numpy (m, v flat)."""
        _, _, _, (t, m, v, _) = self.adam.state[key]
        return t, np.array(m, np.float32), np.array(v, np.float32)

    def rebuild(self, variables, parents: dict, fresh: dict | None = None):
        """A new optimiser over ``variables`` (same keys, new Gaussian counts).

        ``parents[node]`` gives, per Gaussian of the node's new arrays, the
        row of the old arrays it comes from (-1: none); its Adam moments
        move with it. Where ``fresh[node]`` is True (a clone, a split half)
        the row takes only its parent's second moment and starts its first
        moment at zero: it then steps on its own gradients at the usual
        step size. (Zero second moments under Adam's late step count would
        make its steps several times the learning rate for hundreds of
        iterations; the parent's first moment would make a clone repeat its
        parent's steps.) Rows without a parent start at zero; other
        variables (the sky) keep their state. Learning rates start afresh
        (times the :attr:`damping`, which carries over).
        """
        new = Optimizer(variables)
        new.set_damping(self.damping)
        fresh = fresh or {}
        for key, var in new.variables.items():
            if key not in self.variables:
                continue
            parent = parents.get(var.node) if isinstance(var, GaussianVariable) else None
            if parent is None:          # same rows: the state carries over as it is
                value, promoted, lr, _ = new.adam.state[key]
                new.adam.state[key] = (value, promoted, lr, self.adam.state[key][3])
                continue
            t, m, v = self.moments(key)
            w = var.field.width
            m, v = m.reshape(-1, w), v.reshape(-1, w)
            alive = parent >= 0
            src = np.where(alive, parent, 0)
            first = alive & ~fresh.get(var.node, np.zeros(len(parent), bool))
            set_moments(new.adam, key, t, np.where(first[:, None], m[src], 0.0).ravel(),
                        np.where(alive[:, None], v[src], 0.0).ravel())
        return new


def set_moments(adam, key, t, m, v):
    """Put Adam's step count and moments (numpy, flat) for ``key``."""
    value, promoted, lr, extra = adam.state[key]
    if m.shape[-1] != dr.width(value):
        return
    kind_m, kind_v = type(extra[1]), type(extra[2])
    as_kind = lambda kind, a: kind(np.ascontiguousarray(a, np.float32)) if a.ndim == 1 \
        else kind(*np.ascontiguousarray(a, np.float32))  # noqa: E731
    adam.state[key] = (value, promoted, lr, (t, as_kind(kind_m, m), as_kind(kind_v, v), extra[3]))
