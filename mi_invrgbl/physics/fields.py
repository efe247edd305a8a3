"""The per-Gaussian fields: one record each, read by every layer.

The PLY reader and writer (:mod:`.gaussian_ply`), the ``gaussians`` shape
(its per-primitive attributes), the Gaussian traversal's gathers
(:mod:`.hits`), and the fit's variables, learning rates, clamps and
checkpoints all loop over :data:`FIELDS`. Adding a per-Gaussian material
field is one :class:`GaussianField` line in :data:`MATERIAL`.

Units: ``default`` and ``valid`` are in the field's natural units (metres,
opacity in [0, 1], ...). ``storage`` says how the fit optimises it and how
the PLY file stores it:

==========  ==============================================  ===================
storage     fit variable / PLY value                         fit variable name
==========  ==============================================  ===================
linear      the value itself                                 ``name``
unit        a direction, normalised where it is used         ``name``
log         natural log (scales)                             ``log_<name>``
logit       logit (opacity)                                  ``<name>_logit``
quaternion  x y z w in the fit (Dr.Jit's order), w x y z     ``name``
            in the PLY and :class:`GaussianCloud`
==========  ==============================================  ===================
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class GaussianField:
    """One per-Gaussian field.

    ``name`` is the shape attribute (``mi.traverse`` key ``<id>.<name>``) and
    the fit's key; ``cloud`` the :class:`~.gaussian_ply.GaussianCloud`
    attribute. ``default`` is None where the default is derived from other
    fields (see ``GaussianCloud.with_defaults``). ``lr`` is the fit's Adam
    learning rate (per step, in storage units). ``stage`` is the fit stage that
    optimises it (1: geometry and the view-independent colour, 2: materials).
    ``ply`` holds the PLY property names, empty for fit-only fields.
    """
    name: str
    cloud: str
    width: int
    default: float | None
    valid: tuple | None
    lr: float
    stage: int
    ply: tuple = ()
    storage: str = "linear"

    @property
    def variable(self) -> str:
        """The fit's name for the stored form (``log_scale``, ``opacity_logit``, ...)."""
        if self.storage == "log":
            return "log_" + self.name
        if self.storage == "logit":
            return self.name + "_logit"
        return self.name

    # --------------------------------------------------- storage transforms
    def to_storage(self, value: np.ndarray) -> np.ndarray:
        """Natural units (cloud layout) -> the fit's stored form."""
        value = np.asarray(value, np.float64)
        if self.storage == "log":
            return np.log(np.maximum(value, 1e-6))
        if self.storage == "logit":
            p = np.clip(value, 1e-4, 1 - 1e-4)
            return np.log(p / (1 - p))
        if self.storage == "quaternion":
            q = value / np.linalg.norm(value, axis=1, keepdims=True)
            return np.concatenate([q[:, 1:4], q[:, :1]], axis=1)
        return value

    def from_storage(self, stored: np.ndarray) -> np.ndarray:
        """The fit's stored form -> natural units (cloud layout), clamped to ``valid``."""
        stored = np.asarray(stored, np.float64)
        if self.storage == "log":
            return np.exp(stored)
        if self.storage == "logit":
            lo, hi = self.storage_range()
            return 1 / (1 + np.exp(-np.clip(stored, lo, hi)))
        if self.storage == "quaternion":
            q = stored / np.maximum(np.linalg.norm(stored, axis=1, keepdims=True), 1e-12)
            return np.concatenate([q[:, 3:4], q[:, :3]], axis=1)
        if self.storage == "unit":
            return stored / np.maximum(np.linalg.norm(stored, axis=1, keepdims=True), 1e-12)
        if self.valid is not None:
            return np.clip(stored, *self.valid)
        return stored

    def storage_range(self) -> tuple | None:
        """``valid`` in storage units (what the fit clamps its variable to)."""
        if self.valid is None:
            return None
        lo, hi = self.valid
        if self.storage == "log":
            return (math.log(lo), math.log(hi))
        if self.storage == "logit":
            return (math.log(lo / (1 - lo)), math.log(hi / (1 - hi)))
        return (float(lo), float(hi))

    def ply_to_cloud(self, columns: np.ndarray) -> np.ndarray:
        """PLY columns (N, len(ply)) -> cloud layout."""
        if self.storage == "log":
            return np.exp(columns)
        if self.storage == "logit":
            return 1.0 / (1.0 + np.exp(-columns))
        return columns

    def cloud_to_ply(self, value: np.ndarray) -> np.ndarray:
        """Cloud layout -> PLY columns (N, len(ply))."""
        value = np.asarray(value, np.float64).reshape(len(value), -1)
        if self.storage == "log":
            return np.log(np.maximum(value, 1e-30))
        if self.storage == "logit":
            p = np.clip(value, 1e-7, 1 - 1e-7)
            return np.log(p / (1 - p))
        return value


def _sigmoid(x):
    return 1.0 / (1.0 + math.exp(-x))


#: Geometry: centre, extent, orientation, opacity (optimised in stage 1).
#: Opacity stays within logit +-9 so that log(1 - a) stays finite.
#: The shape's rates (log-scale, rotation, opacity logit) are high because a
#: budgeted fit gets a few hundred steps: on the KITTI excerpt 300 stage-1
#: steps (``tests/bench/stage1_steps.py``, validation frames) reach 17.96 dB
#: with them against 16.72 with a third of them; 6x reached 17.90 (faster early,
#: 17.00 against 16.60 at 150), and tripling the centre's rate as well 17.53.
#: (They once made the small test scene's LiDAR response trade its range
#: exponent for its angle exponent; :func:`..fit.init.init_materials` now
#: keeps a free angle exponent only where it predicts the validation scans.)
GEOMETRY = (
    GaussianField("center", "centers", 3, None, None, 2e-3, 1, ("x", "y", "z")),
    GaussianField("scale", "scales", 3, 0.01, (1e-4, 5.0), 1.5e-2, 1,
                  ("scale_0", "scale_1", "scale_2"), "log"),
    GaussianField("rotation", "quaternions", 4, None, None, 6e-3, 1,
                  ("rot_0", "rot_1", "rot_2", "rot_3"), "quaternion"),
    GaussianField("opacity", "opacities", 1, 1.0, (_sigmoid(-9.0), _sigmoid(9.0)), 6e-2, 1,
                  ("opacity",), "logit"),
)

#: Materials: per-primitive attributes of the ``gaussians`` shape (stage 2).
MATERIAL = (
    GaussianField("normal", "normals", 3, None, None, 5e-3, 2, ("nx", "ny", "nz"), "unit"),
    GaussianField("albedo", "albedo", 3, 0.5, (0.0, 1.0), 1e-2, 2,
                  ("albedo_0", "albedo_1", "albedo_2")),
    GaussianField("roughness", "roughness", 1, 0.5, (0.02, 1.0), 1e-2, 2, ("roughness",)),
    GaussianField("lidar_albedo", "lidar_albedo", 1, 0.5, (0.0, 1.0), 1e-2, 2, ("lidar_albedo",)),
    # The paper's v_sun: how much sun reaches the Gaussian.
    GaussianField("sun_visibility", "sun_visibility", 1, 1.0, (0.0, 1.0), 2e-2, 2,
                  ("sun_visibility",)),
)

#: Fit-only: stage 1's view-independent colour (written out as the albedo
#: when a fit stops in stage 1).
FIT_ONLY = (
    GaussianField("colour", "albedo", 3, 0.5, (0.0, 1.0), 1e-2, 1),
)

FIELDS = GEOMETRY + MATERIAL + FIT_ONLY
BY_NAME = {f.name: f for f in FIELDS}
BY_VARIABLE = {f.variable: f for f in FIELDS}
#: Shape attribute name -> width (what the ``gaussians`` shape carries).
ATTRIBUTE_WIDTHS = {f.name: f.width for f in MATERIAL}
#: Shape attribute name -> value a plain ``ellipsoids`` shape without it reads.
ATTRIBUTE_DEFAULTS = {f.name: f.default for f in MATERIAL if f.default is not None}
