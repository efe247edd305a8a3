"""LiDAR sweeps with the paper's reflectance model, range noise and ray drop.

Per frame, every (beam, azimuth) ray of the sensor is cast from the LiDAR's
pose; the hit's true LiDAR albedo and roughness give the return through
:func:`mi_invrgbl.physics.brdf.lidar_intensity`:

    I = (rho_lidar + F0 tau^2 min(1, 2 cos^2) / (4 cos^2 (cos^2 (tau^2 - 1) + 1)^2))
        * P_e cos / (pi d^2)

The sweep is instantaneous (no motion during the spin). Stored intensities
are ``clip(I * INTENSITY_SCALE * (1 + noise), 0, 1)``.
"""

from __future__ import annotations

import math

import numpy as np
import mitsuba as mi

from ..physics import brdf
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


def sweep(scene, table, world_from_velo: np.ndarray, directions: np.ndarray,
          rng: np.random.Generator) -> dict:
    """One sweep: range image channels (beams, azimuths) and the KITTI point list.

    ``directions`` are unit rays in the sensor frame, (beams, azimuths, 3).
    Returns ``intensity``, ``range``, ``hit`` images, ``points`` (N, 4) in the
    sensor frame and the noise-free ``clean_range`` / ``clean_intensity``.
    """
    beams, steps, _ = directions.shape
    local = directions.reshape(-1, 3)
    R, t = world_from_velo[:3, :3], world_from_velo[:3, 3]
    world_d = local @ R.T
    ray = mi.Ray3f(mi.Point3f(np.tile(t.astype(np.float32), (len(local), 1)).T),
                   mi.Vector3f(world_d.astype(np.float32).T))
    si = scene.ray_intersect(ray)
    g = table.lookup(si)
    n = oriented_normals(g["n"], world_d)
    cos = np.clip(-np.sum(n * world_d, axis=1), 0.0, 1.0)
    dist = np.maximum(g["t"], MIN_RANGE)
    clean = np.array(brdf.lidar_intensity(mi.Float(g["lidar_albedo"].astype(np.float32)),
                                          mi.Float(g["roughness"].astype(np.float32)),
                                          mi.Float(cos.astype(np.float32)),
                                          mi.Float(dist.astype(np.float32)), power=POWER),
                     dtype=np.float64)
    # Draw every random number for every ray, so the noise of one ray does not
    # depend on which other rays hit (stable under scene edits).
    range_noise = rng.normal(0.0, RANGE_NOISE, len(local))
    gain_noise = rng.normal(0.0, INTENSITY_NOISE, len(local))
    dropped = rng.random(len(local)) < DROP_RATE
    hit = g["hit"] & (g["t"] >= MIN_RANGE) & (g["t"] <= FAR_RANGE) & ~dropped
    rng_m = np.where(hit, g["t"] + range_noise, 0.0)
    intensity = np.where(hit, np.clip(clean * INTENSITY_SCALE * (1 + gain_noise), 0.0, 1.0), 0.0)
    points = np.concatenate([local[hit] * rng_m[hit, None], intensity[hit, None]], axis=1)
    shape = (beams, steps)
    return {"intensity": intensity.reshape(shape).astype(np.float32),
            "range": rng_m.reshape(shape).astype(np.float32),
            "hit": hit.reshape(shape).astype(np.float32),
            "points": points.astype(np.float32),
            "part": np.where(hit, g["part"], -1).reshape(shape)}
