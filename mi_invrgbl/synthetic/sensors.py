"""LiDAR sensors the street generator can simulate (``make-scene --lidar``).

=========== ==================================================================
``hdl64``   64 beams (``--beams``) evenly from +2 to -24.9 degrees, unit beam
            gains, random ray drop only, points stored beam by beam: the
            generator's original sensor (streets made before stay identical).
``vlp32``   Velodyne VLP-32C: its documented non-uniform 32-beam table
            (+15 to -25 degrees, 1/3 degree steps around the horizon).
``os128``   Ouster OS1-128: 128 beams evenly over +-22.5 degrees.
``rays:F``  an explicit ray pattern: ``F`` is a ``.npy`` array (N, 6) of ray
            origins and directions in the sensor frame, or (N, 7) whose last
            column is each ray's beam; without it the beam comes from the
            ray's elevation (:func:`mi_invrgbl.physics.beam_layout.ray_beams`).
=========== ==================================================================

All but ``hdl64`` behave like real units: each beam has its own gain
(``BEAM_GAIN_SPREAD``), weak returns are lost more often than strong ones
(:func:`drop_probability`), and the points are stored in firing order,
azimuth step by azimuth step, with the lasers of a step in their hardware
order (for ``vlp32`` not sorted by elevation) -- not beam by beam as KITTI
stores its sweeps.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

from ..errors import UserError

#: Beam tables (degrees, top first).
VLP32C_DEG = (15.0, 10.333, 7.0, 4.667, 3.333, 2.333, 1.667, 1.333, 1.0, 0.667,
              0.333, 0.0, -0.333, -0.667, -1.0, -1.333, -1.667, -2.0, -2.333,
              -2.667, -3.0, -3.333, -3.667, -4.0, -4.667, -5.333, -6.148, -7.254,
              -8.843, -11.31, -15.639, -25.0)
#: Relative spread of the per-beam gains of the realistic sensors (uniform +-).
BEAM_GAIN_SPREAD = 0.2
#: Weak-return drop: a return whose raw strength (white Lambertian at the
#: reference range facing the sensor = 1) is ``WEAK_SIGNAL`` has a 50 % chance
#: of being lost; the logistic's width is ``WEAK_WIDTH`` in log strength.
WEAK_SIGNAL = 0.001
WEAK_WIDTH = 0.6
KINDS = ("hdl64", "vlp32", "os128")


@dataclass
class SensorPattern:
    """The rays of one sweep and how the sensor reports them."""
    name: str                  # hdl64 | vlp32 | os128 | rays
    directions: np.ndarray     # (N, 3) unit rays in the sensor frame, in storage order
    origins: np.ndarray        # (N, 3) ray origins in the sensor frame
    beam: np.ndarray           # (N,) beam (row 0 = top) of each ray
    elevations_deg: np.ndarray  # (B,) beam table, top first
    beam_gains: np.ndarray     # (B,) true gain of each beam
    image_shape: tuple         # (rows, cols) of the ground-truth range image
    image_index: np.ndarray    # (N,) flat index of each ray in that image
    weak_drop: bool            # weak returns are lost more often
    realistic_order: bool      # points stored in firing order (not beam by beam)
    rays_file: str | None = None

    @property
    def n_beams(self) -> int:
        return int(self.elevations_deg.size)

    def to_json(self) -> dict:
        return {"sensor": self.name, "beams": self.n_beams,
                "elevation_table_deg": [float(e) for e in self.elevations_deg],
                "beam_gains": [float(g) for g in self.beam_gains],
                "weak_signal_drop": ({"signal_at_half": WEAK_SIGNAL, "log_width": WEAK_WIDTH}
                                     if self.weak_drop else None),
                "rays": self.rays_file, "image_shape": list(self.image_shape)}


def parse_lidar(spec: str) -> tuple[str, str | None]:
    """``(kind, rays file)`` of a ``--lidar`` value; raises :class:`UserError`."""
    spec = str(spec)
    if spec.startswith("rays:"):
        path = spec[5:]
        if not path:
            raise UserError("--lidar rays:FILE needs a file (a .npy (N, 6) or (N, 7) ray list)")
        return "rays", path
    if spec not in KINDS:
        raise UserError("--lidar must be one of %s or rays:FILE (got %r)"
                        % (", ".join(KINDS), spec))
    return spec, None


def load_rays(path: str) -> np.ndarray:
    """A ray file (N, 6) or (N, 7), checked; raises :class:`UserError` naming it."""
    try:
        a = np.load(path)
    except Exception as exc:  # unreadable, not .npy
        raise UserError("%s: cannot read the ray list (%s)" % (path, exc)) from None
    a = np.asarray(a, np.float64)
    if a.ndim != 2 or a.shape[1] not in (6, 7) or a.shape[0] == 0:
        raise UserError("%s: a ray list must be a non-empty (N, 6) or (N, 7) array, got %s"
                        % (path, a.shape))
    if not np.all(np.isfinite(a)):
        raise UserError("%s: the ray list contains NaN or Inf" % path)
    if np.any(np.linalg.norm(a[:, 3:6], axis=1) < 1e-12):
        raise UserError("%s: the ray list has a zero direction" % path)
    if a.shape[1] == 7 and (np.any(a[:, 6] < 0) or np.any(a[:, 6] != np.round(a[:, 6]))):
        raise UserError("%s: column 7 (beam) must hold non-negative integers" % path)
    return a


def _gains(n, seed):
    rng = np.random.default_rng([seed, 11])
    return 1.0 + BEAM_GAIN_SPREAD * rng.uniform(-1.0, 1.0, n)


def _grid(name, elev_deg, steps, gains, laser_order):
    """A spinning sensor's rays in firing order: azimuth step by step, the
    lasers of a step in ``laser_order`` (beam indices)."""
    B = len(elev_deg)
    e = np.radians(np.asarray(elev_deg, np.float64))
    phi = math.pi - 2 * math.pi * (np.arange(steps) + 0.5) / steps
    col = np.repeat(np.arange(steps), B)
    beam = np.tile(np.asarray(laser_order), steps)
    d = np.stack([np.cos(e[beam]) * np.cos(phi[col]), np.cos(e[beam]) * np.sin(phi[col]),
                  np.sin(e[beam])], axis=1)
    return SensorPattern(name, d, np.zeros_like(d), beam, np.asarray(elev_deg, np.float64),
                         gains, (B, steps), beam * steps + col, True, True)


def make_pattern(lidar: str, beams: int, azimuth_steps: int, seed: int) -> SensorPattern:
    """The sensor pattern of ``--lidar`` (see the module docstring)."""
    kind, path = parse_lidar(lidar)
    if kind == "hdl64":
        from .trajectory import lidar_directions
        d = lidar_directions(beams, azimuth_steps)
        B, W = d.shape[:2]
        beam = np.repeat(np.arange(B), W)
        return SensorPattern("hdl64", d.reshape(-1, 3), np.zeros((B * W, 3)), beam,
                             np.linspace(2.0, -24.9, B), np.ones(B), (B, W),
                             np.arange(B * W), False, False)
    if kind == "vlp32":
        # Hardware firing order of the VLP-32C interleaves the table.
        order = np.argsort(np.arange(32) * 7 % 32)
        return _grid("vlp32", VLP32C_DEG, azimuth_steps, _gains(32, seed), order)
    if kind == "os128":
        return _grid("os128", np.linspace(22.5, -22.5, 128), azimuth_steps, _gains(128, seed),
                     np.arange(128))
    from ..physics.beam_layout import ray_beams
    a = load_rays(path)
    d = a[:, 3:6] / np.linalg.norm(a[:, 3:6], axis=1, keepdims=True)
    if a.shape[1] == 7:
        beam = a[:, 6].astype(np.int64)
        B = int(beam.max()) + 1
        el = np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1]))
        table = np.array([np.degrees(np.median(el[beam == k])) if np.any(beam == k) else np.nan
                          for k in range(B)])
    else:
        beam, table = ray_beams(d)
        table = np.degrees(table)
    n = d.shape[0]
    return SensorPattern("rays", d, a[:, :3].copy(), beam, table, _gains(table.size, seed),
                         (1, n), np.arange(n), True, False, rays_file=str(path))


def drop_probability(strength, base_rate: float) -> np.ndarray:
    """Chance that a return of raw ``strength`` is lost (weak-signal model)."""
    s = np.maximum(np.asarray(strength, np.float64), 1e-12)
    weak = 1.0 / (1.0 + np.exp((np.log(s) - math.log(WEAK_SIGNAL)) / WEAK_WIDTH))
    return base_rate + (1.0 - base_rate) * weak


def solid_state_rays(rows: int = 20, per_row: int = 120, fov_deg: float = 100.0) -> np.ndarray:
    """An example explicit pattern (N, 7) of a forward-looking solid-state
    sensor: ``rows`` rows at non-uniform elevations (dense from -1 to -6
    degrees, sparse down to -20), ``per_row`` rays over ``fov_deg`` of
    azimuth, every third row shifted by a fraction of a step (not a grid);
    column 7 is the row (beam). Save it with ``np.save`` for ``--lidar rays:F``."""
    dense = max(rows * 3 // 5, 2)
    el = np.concatenate([np.linspace(-1, -6, dense), np.linspace(-7, -20, rows - dense)])
    out = []
    for k, e in enumerate(el):
        az = np.radians(np.linspace(-fov_deg / 2, fov_deg / 2, per_row) + (k % 3) * 0.27)
        er = np.radians(e)
        d = np.stack([np.cos(er) * np.cos(az), np.cos(er) * np.sin(az),
                      np.full_like(az, np.sin(er))], 1)
        out.append(np.hstack([np.zeros_like(d), d, np.full((per_row, 1), k)]))
    return np.concatenate(out)
