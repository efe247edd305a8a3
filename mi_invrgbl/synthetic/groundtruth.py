"""Per-pixel ground truth by ray casting the street (no rendering involved).

For every camera pixel one ray through the pixel centre is traced with
``mi.Scene.ray_intersect``; the shape it hits is mapped to its true material
through :class:`MaterialTable`. The road's albedo and LiDAR albedo come from
evaluating its textures at the hit's UV, with the same bitmap texture the
renderer uses. ``sun_visibility`` is a shadow ray towards the time-A sun.
"""

from __future__ import annotations

import os

import numpy as np
import drjit as dr
import mitsuba as mi

from ..physics.host_arrays import jit_array


def rows(v) -> np.ndarray:
    """A Dr.Jit 3-vector array (3 x N) as a numpy (N, 3) array."""
    return np.array(v, dtype=np.float64).reshape(3, -1).T


class MaterialTable:
    """Maps Mitsuba shapes of a loaded street scene to their true materials."""

    def __init__(self, scene, parts, materials, scene_dir: str):
        self.names = [p.name for p in parts]
        index = {name: i for i, name in enumerate(self.names)}
        n = len(parts)
        self.albedo = np.zeros((n, 3), np.float32)
        self.roughness = np.zeros(n, np.float32)
        self.lidar_albedo = np.zeros(n, np.float32)
        self.textures = {}
        for i, part in enumerate(parts):
            mat = materials[part.material]
            self.albedo[i] = mat.albedo
            self.roughness[i] = mat.roughness
            self.lidar_albedo[i] = mat.lidar_albedo
            if mat.albedo_texture:
                self.textures[i] = (
                    mi.load_dict({"type": "bitmap", "filter_type": "bilinear",
                                  "filename": os.path.join(scene_dir, mat.albedo_texture)}),
                    mi.load_dict({"type": "bitmap", "filter_type": "bilinear", "raw": True,
                                  "filename": os.path.join(scene_dir, mat.lidar_texture)}))
        # Shape pointers reinterpret as small registry ids: build id -> part index.
        ids = [int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(s))[0]) for s in scene.shapes()]
        self.lut = np.full(max(ids) + 1, -1, np.int64)
        for s, sid in zip(scene.shapes(), ids):
            self.lut[sid] = index[s.id()]

    def lookup(self, si) -> dict:
        """True surface properties at the hits of ``si`` (numpy, one row per ray)."""
        valid = np.array(si.is_valid(), dtype=bool)
        sid = np.array(dr.reinterpret_array(mi.UInt32, si.shape), dtype=np.int64)
        part = np.where(valid, self.lut[np.clip(sid, 0, len(self.lut) - 1)], -1)
        safe = np.maximum(part, 0)
        albedo = self.albedo[safe].copy()
        lidar = self.lidar_albedo[safe].copy()
        for i, (tex_rgb, tex_lidar) in self.textures.items():
            sel = part == i
            if sel.any():
                rgb = rows(tex_rgb.eval(si)).astype(np.float32)
                grey = np.array(tex_lidar.eval_1(si), dtype=np.float32).reshape(-1)
                albedo[sel] = rgb[sel]
                lidar[sel] = grey[sel]
        hit = part >= 0
        return {"hit": hit, "part": part,
                "albedo": np.where(hit[:, None], albedo, 0.0),
                "roughness": np.where(hit, self.roughness[safe], 0.0),
                "lidar_albedo": np.where(hit, lidar, 0.0),
                "t": np.where(hit, np.array(si.t, dtype=np.float64), 0.0),
                "n": rows(si.n)}


def oriented_normals(n: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Flip geometric normals to face the incoming ray (thin and one-sided parts)."""
    flip = np.sum(n * d, axis=1) > 0
    return np.where(flip[:, None], -n, n)


def sun_visibility(scene, si, normals: np.ndarray, sun: np.ndarray, hit: np.ndarray) -> np.ndarray:
    """1 where a shadow ray towards the sun escapes, 0 where blocked or facing away."""
    direction = mi.Vector3f(np.tile(sun.astype(np.float32), (len(hit), 1)).T)
    blocked = np.array(scene.ray_test(si.spawn_ray(direction)), dtype=bool)
    facing = normals @ sun > 0
    return (hit & facing & ~blocked).astype(np.float32)


def camera_rays(sensor, width: int, height: int):
    """One ray per pixel centre from Mitsuba's own sensor (row-major, top row first)."""
    u, v = np.meshgrid((np.arange(width) + 0.5) / width, (np.arange(height) + 0.5) / height)
    pos = mi.Point2f(jit_array(mi.Float, u), jit_array(mi.Float, v))
    ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5, 0.5))
    return ray


def camera_maps(scene, table: MaterialTable, width: int, height: int,
                world_from_cam: np.ndarray, sun: np.ndarray) -> dict:
    """Ground-truth maps of the current frame (scene already posed), each (H, W[, 3])."""
    ray = camera_rays(scene.sensors()[0], width, height)
    si = scene.ray_intersect(ray)
    g = table.lookup(si)
    d = rows(ray.d)
    n = oriented_normals(g["n"], d)
    hit = g["hit"]
    points = rows(ray.o) + d * g["t"][:, None]
    cam_z = world_from_cam[:3, 2]
    depth = np.where(hit, (points - world_from_cam[:3, 3]) @ cam_z, 0.0)
    vis = sun_visibility(scene, si, n, sun, hit)
    shape2 = (height, width)
    return {"albedo": g["albedo"].reshape(height, width, 3),
            "roughness": g["roughness"].reshape(shape2),
            "normal": np.where(hit[:, None], n, 0.0).reshape(height, width, 3),
            "lidar_albedo": g["lidar_albedo"].reshape(shape2),
            "sun_visibility": vis.reshape(shape2),
            "depth": depth.reshape(shape2),
            "mesh_id": g["part"].astype(np.float32).reshape(shape2)}
