"""KITTI tracking labels of the cars from their true poses.

A car is labelled in a frame when its 3D box lies at least partly in front
of the camera and its projected box overlaps the image. ``location`` is the
bottom centre of the box in camera coordinates, ``rotation_y`` the heading
about the camera's y axis (KITTI: forward = (cos ry, 0, -sin ry)),
``alpha = ry - atan2(x, z)``. Occlusion is not estimated and is written as 0.
"""

from __future__ import annotations

import math

import numpy as np

from . import layout

TRACK_MOVING = 0
TRACK_PARKED = 1


def wrap(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


def box_corners(hwl) -> np.ndarray:
    """8 corners of a car's box in its own frame (x forward, y left, z up)."""
    h, w, l = hwl
    xs, ys, zs = np.meshgrid((-l / 2, l / 2), (-w / 2, w / 2), (0.0, h), indexing="ij")
    return np.stack([xs.ravel(), ys.ravel(), zs.ravel()], axis=1)


def label(frame, track_id, world_from_car, world_from_cam, K, width, height):
    """One label row, or None when the car is not in view."""
    cam_from_car = np.linalg.inv(world_from_cam) @ world_from_car
    corners = box_corners(layout.CAR_HWL) @ cam_from_car[:3, :3].T + cam_from_car[:3, 3]
    if corners[:, 2].max() < 0.5:
        return None
    front = corners[corners[:, 2] > 0.1]
    uv = front @ K.T
    uv = uv[:, :2] / uv[:, 2:3]
    left, top = uv.min(axis=0)
    right, bottom = uv.max(axis=0)
    # Clip to the image (pixel centres at integers: the image spans -0.5 .. W-0.5).
    cl, ct = max(left, -0.5), max(top, -0.5)
    cr, cb = min(right, width - 0.5), min(bottom, height - 0.5)
    if cr <= cl or cb <= ct:
        return None
    truncated = int(len(front) < 8 or (cl, ct, cr, cb) != (left, top, right, bottom))
    loc = cam_from_car[:3, 3]
    forward = cam_from_car[:3, 0]
    ry = wrap(math.atan2(-forward[2], forward[0]))
    alpha = wrap(ry - math.atan2(loc[0], loc[2]))
    return {"frame": frame, "track_id": track_id, "type": "Car", "truncated": truncated,
            "occluded": 0, "alpha": alpha, "bbox": [cl, ct, cr, cb],
            "dimensions": list(layout.CAR_HWL), "location": [float(c) for c in loc],
            "rotation_y": ry}


def tracking_rows(moving_poses, parked_pose, world_from_cams, K, width, height) -> list:
    rows = []
    for i, cam in enumerate(world_from_cams):
        for track, pose in ((TRACK_MOVING, moving_poses[i]), (TRACK_PARKED, parked_pose)):
            row = label(i, track, pose, cam, K, width, height)
            if row is not None:
                rows.append(row)
    return rows


def car_pose_from_label(row, world_from_cam) -> np.ndarray:
    """Inverse of :func:`label`: world_from_car from a label row and its camera pose."""
    ry = row["rotation_y"]
    forward = np.array([math.cos(ry), 0.0, -math.sin(ry)])
    up = np.array([0.0, -1.0, 0.0])
    cam_from_car = np.eye(4)
    cam_from_car[:3, 0] = forward
    cam_from_car[:3, 1] = np.cross(up, forward)
    cam_from_car[:3, 2] = up
    cam_from_car[:3, 3] = row["location"]
    return world_from_cam @ cam_from_car
