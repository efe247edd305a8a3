"""Poses: parsing them from the command line and files, checking them, moving shapes.

A pose is a 4x4 ``world_from_object`` matrix. On the command line it is
``x,y,z`` or ``x,y,z,yaw`` (yaw in degrees about +z, from +x towards +y) or
16 numbers (row-major 4x4). Trajectory files hold one pose per frame: JSON
(a list of poses in either form, or a dict with ``poses``, ``world_from_velo``
or ``lidar_to_world`` per frame) or text with one pose per line (KITTI's
12-number 3x4 rows, or 4 numbers ``x y z yaw``).

Moving a shape of a loaded scene to a pose is
:func:`mi_invrgbl.scene.posing.place`'s job.
"""

from __future__ import annotations

import json
import math
import os

import numpy as np

from ..errors import UserError


def pose_from_values(values, what: str = "--pose") -> np.ndarray:
    """A 4x4 pose from 3 (x y z), 4 (x y z yaw_deg), 12 (3x4) or 16 (4x4) numbers."""
    v = np.asarray(values, np.float64).ravel()
    if not np.all(np.isfinite(v)):
        raise UserError("%s: pose values must be finite numbers" % what)
    m = np.eye(4)
    if v.size in (3, 4):
        m[:3, 3] = v[:3]
        if v.size == 4:
            c, s = math.cos(math.radians(v[3])), math.sin(math.radians(v[3]))
            m[:2, :2] = [[c, -s], [s, c]]
    elif v.size in (12, 16):
        m[:v.size // 4] = v.reshape(-1, 4)
        lin = m[:3, :3]
        scale = np.cbrt(np.linalg.det(lin))
        if not scale > 1e-9 or not np.allclose((lin / scale) @ (lin / scale).T, np.eye(3), atol=1e-3):
            raise UserError("%s: the 3x3 part must be a rotation (optionally uniformly scaled)"
                            % what)
    else:
        raise UserError("%s: expected x,y,z or x,y,z,yaw or 12/16 matrix values, got %d numbers"
                        % (what, v.size))
    return m


def parse_pose(text: str, what: str = "--pose") -> np.ndarray:
    try:
        values = [float(t) for t in text.replace(",", " ").split()]
    except ValueError:
        raise UserError("%s: cannot read '%s' as numbers (use x,y,z,yaw)" % (what, text)) from None
    return pose_from_values(values, what)


def read_trajectory(path: str, key: str | None = None) -> list[np.ndarray]:
    """Poses of a trajectory file (see the module docstring)."""
    if not os.path.isfile(path):
        raise UserError("%s: trajectory file not found" % path)
    what = path
    if path.endswith(".json"):
        try:
            with open(path) as f:
                data = json.load(f)
        except ValueError as exc:
            raise UserError("%s: not valid JSON (%s)" % (path, exc)) from None
        if isinstance(data, dict):
            keys = [key] if key else ["poses", "world_from_velo", "lidar_to_world", "frames"]
            found = [k for k in keys if k in data]
            if not found:
                raise UserError("%s: expected a list of poses or a dict with one of %s"
                                % (path, ", ".join(keys)))
            data = data[found[0]]
            if found[0] == "frames":   # frames.json
                data = [f.get("lidar_to_world") for f in data]
        if not isinstance(data, list) or not data:
            raise UserError("%s: no poses in the file" % path)
        poses = []
        for i, item in enumerate(data):
            if item is None:
                raise UserError("%s: pose %d is missing" % (path, i))
            poses.append(pose_from_values(np.asarray(item, np.float64), "%s (pose %d)" % (what, i)))
        return poses
    try:
        rows = np.loadtxt(path, ndmin=2)
    except ValueError as exc:
        raise UserError("%s: cannot read poses (%s)" % (path, exc)) from None
    if rows.size == 0:
        raise UserError("%s: no poses in the file" % path)
    return [pose_from_values(r, "%s (line %d)" % (what, i + 1)) for i, r in enumerate(rows)]


def check_inside(position, bbox, what: str, margin: float = 2.0) -> None:
    """Refuse a position outside the scene's bounding box (plus ``margin`` metres)."""
    lo = np.array(bbox.min, np.float64).ravel() - margin
    hi = np.array(bbox.max, np.float64).ravel() + margin
    p = np.asarray(position, np.float64)[:3]
    if not bbox.valid() or np.any(p < lo) or np.any(p > hi):
        raise UserError("%s: position (%.2f, %.2f, %.2f) lies outside the scene, whose bounds "
                        "are x %.1f..%.1f, y %.1f..%.1f, z %.1f..%.1f (m)"
                        % ((what,) + tuple(p) + (lo[0] + margin, hi[0] - margin, lo[1] + margin,
                                                 hi[1] - margin, lo[2] + margin, hi[2] - margin)))


def scene_bounds(scene, exclude: str | None = None):
    """Bounding box of a scene's shapes (all but ``exclude``), from their vertices.

    ``Shape.bbox()`` is not enough: Mitsuba 3.9 merges meshes that share a
    BSDF into one and keeps only the first one's box.
    """
    import mitsuba as mi
    bbox = mi.ScalarBoundingBox3f()
    for s in scene.shapes():
        if exclude is not None and s.id() == exclude:
            continue
        if isinstance(s, mi.Mesh) and s.vertex_count() > 0:
            v = np.array(s.vertex_positions_buffer(), np.float64).reshape(-1, 3)
            bbox.expand(mi.ScalarBoundingBox3f(mi.ScalarPoint3f(*v.min(axis=0)),
                                               mi.ScalarPoint3f(*v.max(axis=0))))
        else:
            bbox.expand(s.bbox())
    return bbox
