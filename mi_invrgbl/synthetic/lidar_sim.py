"""LiDAR sweeps with the paper's reflectance model, range noise and ray drop.

Per frame, every (beam, azimuth) ray of the sensor is cast from the LiDAR's
pose; the hit's true LiDAR albedo and roughness give the return through
:func:`mi_invrgbl.physics.brdf.lidar_intensity`:

    I = (rho_lidar + F0 tau^2 min(1, 2 cos^2) / (4 cos^2 (cos^2 (tau^2 - 1) + 1)^2))
        * P_e cos / (pi d^2)

The sweep is instantaneous (no motion during the spin). Stored raw
intensities are ``clip(g_beam I * INTENSITY_SCALE * (1 + noise), 0, 1)``;
range-compensated ones (``--intensity reflectivity``) are
``clip(g_beam I pi d^2 / P_e (1 + noise), 0, 1)``. The sensors
(:mod:`.sensors`) set the beam gains ``g_beam`` and whether weak returns
drop more often.
"""

from __future__ import annotations

import math

import numpy as np
import mitsuba as mi

from ..physics import brdf
from ..physics.host_arrays import jit_array
from . import sensors
from .groundtruth import oriented_normals

#: Emitted power of the laser (arbitrary units).
POWER = 1.0
#: Fixed intensity scale: a white Lambertian facing the sensor at 2 m reads 1.0.
REFERENCE_RANGE = 2.0
INTENSITY_SCALE = math.pi * REFERENCE_RANGE ** 2 / POWER
#: Sensor noise and ray drop.
RANGE_NOISE = 0.01          #: metres, Gaussian
INTENSITY_NOISE = 0.02      #: relative, Gaussian
DROP_RATE = 0.02            #: returns lost at random
FAR_RANGE = 80.0            #: no return beyond this range (metres)
MIN_RANGE = 0.5


def sweep(scene, table, world_from_velo: np.ndarray, pattern, rng: np.random.Generator,
          intensity: str = "raw") -> dict:
    """One sweep of ``pattern`` (:class:`~mi_invrgbl.synthetic.sensors.SensorPattern`).

    ``intensity`` is ``raw`` (return strength, falling as ``cos / d^2``) or
    ``reflectivity`` (range-compensated, as KITTI's HDL-64E reports:
    ``g_beam (rho + pi f_s) cos``). Returns the ground-truth range image
    channels ``intensity``, ``range``, ``hit`` (``pattern.image_shape``),
    ``points`` (N, 4) in the sensor frame in the pattern's storage order, and
    ``part`` (mesh hit per image pixel, -1 for none).
    """
    local = pattern.directions
    R, t = world_from_velo[:3, :3], world_from_velo[:3, 3]
    world_d = local @ R.T
    world_o = pattern.origins @ R.T + t
    ray = mi.Ray3f(mi.Point3f(world_o.astype(np.float32).T),
                   mi.Vector3f(world_d.astype(np.float32).T))
    si = scene.ray_intersect(ray)
    g = table.lookup(si)
    n = oriented_normals(g["n"], world_d)
    cos = np.clip(-np.sum(n * world_d, axis=1), 0.0, 1.0)
    dist = np.maximum(g["t"], MIN_RANGE)
    clean = np.array(brdf.lidar_intensity(jit_array(mi.Float, g["lidar_albedo"]),
                                          jit_array(mi.Float, g["roughness"]),
                                          jit_array(mi.Float, cos),
                                          jit_array(mi.Float, dist), power=POWER),
                     dtype=np.float64)
    gain = pattern.beam_gains[pattern.beam]
    strength = gain * clean * INTENSITY_SCALE
    # Draw every random number for every ray, so the noise of one ray does not
    # depend on which other rays hit (stable under scene edits).
    range_noise = rng.normal(0.0, RANGE_NOISE, len(local))
    gain_noise = rng.normal(0.0, INTENSITY_NOISE, len(local))
    u = rng.random(len(local))
    p_drop = sensors.drop_probability(strength, DROP_RATE) if pattern.weak_drop else DROP_RATE
    dropped = u < p_drop
    hit = g["hit"] & (g["t"] >= MIN_RANGE) & (g["t"] <= FAR_RANGE) & ~dropped
    rng_m = np.where(hit, g["t"] + range_noise, 0.0)
    if intensity == "reflectivity":
        value = gain * clean * math.pi * dist ** 2 / POWER
    else:
        value = strength
    inten = np.where(hit, np.clip(value * (1 + gain_noise), 0.0, 1.0), 0.0)
    points = np.concatenate([pattern.origins[hit] + local[hit] * rng_m[hit, None],
                             inten[hit, None]], axis=1)
    shape = tuple(pattern.image_shape)
    size = shape[0] * shape[1]

    def image(values, fill=0.0, dtype=np.float32):
        out = np.full(size, fill, dtype)
        out[pattern.image_index] = values
        return out.reshape(shape)

    return {"intensity": image(inten), "range": image(rng_m),
            "hit": image(hit.astype(np.float32)),
            "points": points.astype(np.float32),
            "part": image(np.where(hit, g["part"], -1), -1, np.int64)}
