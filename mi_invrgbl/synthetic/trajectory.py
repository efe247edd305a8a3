"""Poses of the ego vehicle, its camera and LiDAR, and the moving car.

Frames used here (all right-handed, 4x4 homogeneous matrices):

* world  -- z up, x along the street, y left (see :mod:`.layout`);
* ego    -- x forward, y left, z up, on the road below the LiDAR;
* velo   -- the LiDAR, KITTI's velodyne frame: ego raised by ``LIDAR_HEIGHT``;
* cam    -- KITTI camera frame: x right, y down, z forward (``poses/00.txt``);
* mitsuba camera -- Mitsuba's perspective sensor looks along +z with +y up,
  hence +x to the left: ``world_from_cam = world_from_mitsuba @ diag(-1, -1, 1, 1)``.

The ego drives ``step`` metres per frame along x in the right lane with a
gentle, bounded sideways sway (a slight curve that never leaves the lane).
"""

from __future__ import annotations

import math

import numpy as np

from . import layout

LIDAR_HEIGHT = 1.73
#: Camera position in the ego frame (KITTI: 0.27 m ahead of, 8 cm below the LiDAR).
CAMERA_IN_EGO = np.array([0.27, 0.0, 1.65])
#: Sideways sway of the ego path: amplitude (m) and period (m).
SWAY = (0.35, 40.0)
#: The moving car: start ahead in the other lane, and its speed in steps per frame.
MOVING_CAR_START_X = 8.0
MOVING_CAR_SPEED = 1.3

#: Rotation taking velo/ego axes (x fwd, y left, z up) to KITTI camera axes.
R_CAM_FROM_EGO = np.array([[0.0, -1.0, 0.0],
                           [0.0, 0.0, -1.0],
                           [1.0, 0.0, 0.0]])
#: Mitsuba camera axes -> KITTI camera axes (flip x and y).
KITTI_FROM_MITSUBA = np.diag([-1.0, -1.0, 1.0, 1.0])


def rigid(R, t) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = R
    m[:3, 3] = t
    return m


def rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def ego_poses(frames: int, step: float) -> np.ndarray:
    """world_from_ego for each frame, (frames, 4, 4)."""
    amp, period = SWAY
    k = 2 * math.pi / period
    out = []
    for i in range(frames):
        x = i * step
        y = layout.EGO_LANE_Y + amp * (1 - math.cos(k * x))
        yaw = math.atan(amp * k * math.sin(k * x))
        out.append(rigid(rot_z(yaw), (x, y, 0.0)))
    return np.array(out)


def velo_from_ego() -> np.ndarray:
    return rigid(np.eye(3), (0.0, 0.0, -LIDAR_HEIGHT))


def cam_from_velo() -> np.ndarray:
    """KITTI's Tr: velodyne -> camera 0 (the same for every frame)."""
    cam_in_velo = CAMERA_IN_EGO - np.array([0.0, 0.0, LIDAR_HEIGHT])
    return rigid(R_CAM_FROM_EGO, -R_CAM_FROM_EGO @ cam_in_velo)


def world_from_velo(ego: np.ndarray) -> np.ndarray:
    return ego @ np.linalg.inv(velo_from_ego())


def world_from_cam(ego: np.ndarray) -> np.ndarray:
    """World pose of the KITTI camera frame (x right, y down, z forward)."""
    return world_from_velo(ego) @ np.linalg.inv(cam_from_velo())


def world_from_mitsuba_cam(ego: np.ndarray) -> np.ndarray:
    """``to_world`` of Mitsuba's perspective sensor for this ego pose."""
    return world_from_cam(ego) @ KITTI_FROM_MITSUBA


def kitti_poses(world_from_cams: np.ndarray) -> np.ndarray:
    """KITTI odometry poses: camera i expressed in camera 0's frame, (N, 4, 4)."""
    base = np.linalg.inv(world_from_cams[0])
    return np.array([base @ m for m in world_from_cams])


def moving_car_poses(frames: int, step: float) -> np.ndarray:
    """world_from_car for each frame: straight down the other lane, ahead of the ego."""
    return np.array([rigid(np.eye(3), (MOVING_CAR_START_X + MOVING_CAR_SPEED * step * i,
                                       layout.OTHER_LANE_Y, 0.0)) for i in range(frames)])


def parked_car_pose() -> np.ndarray:
    x, y = layout.PARKED_CAR_XY
    return rigid(np.eye(3), (x, y, 0.0))


def intrinsics(width: int, height: int, fov_deg: float) -> np.ndarray:
    """3x3 camera matrix of Mitsuba's perspective sensor (``fov_axis = x``).

    OpenCV/KITTI convention: pixel (u, v) has its centre at integer
    coordinates, so the principal point of a centred sensor is
    ``((W - 1) / 2, (H - 1) / 2)``.
    """
    f = (width / 2.0) / math.tan(math.radians(fov_deg) / 2.0)
    return np.array([[f, 0.0, (width - 1) / 2.0],
                     [0.0, f, (height - 1) / 2.0],
                     [0.0, 0.0, 1.0]])


def lidar_directions(beams: int, azimuth_steps: int) -> np.ndarray:
    """Unit ray directions in the velo frame, (beams, azimuth_steps, 3).

    Rows: elevations evenly from +2 deg (row 0) down to -24.9 deg (HDL-64-like).
    Columns: azimuth ``phi_j = pi - 2 pi (j + 0.5) / W`` (counter-clockwise
    from x forward), so column 0 looks backwards-left, column W/2 forward and
    the sweep turns clockwise seen from above, as a Velodyne does.
    """
    elev = np.radians(np.linspace(2.0, -24.9, beams))
    phi = math.pi - 2 * math.pi * (np.arange(azimuth_steps) + 0.5) / azimuth_steps
    e, p = np.meshgrid(elev, phi, indexing="ij")
    return np.stack([np.cos(e) * np.cos(p), np.cos(e) * np.sin(p), np.sin(e)], axis=-1)
