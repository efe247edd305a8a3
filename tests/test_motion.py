"""Moving objects from the LiDAR alone: a box driving between two static
walls, scanned by a simulated spinning LiDAR on a moving ego vehicle."""

import numpy as np
import pytest

from mi_invrgbl.io import motion

N_FRAMES = 14
EGO_STEP = 0.5           # metres per sweep, along x
BOX_START = np.array([8.0, 3.0, 0.8])
BOX_STEP = 1.0           # metres per sweep, along x
BOX_HALF = np.array([2.0, 1.0, 0.8])
WALL_Y = 8.0
SENSOR_Z = 1.7


def _rays(beams=32, steps=720):
    el = np.radians(np.linspace(2.0, -24.0, beams))
    az = np.arange(steps) * 2 * np.pi / steps
    e, a = np.meshgrid(el, az, indexing="ij")
    return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)


def _slab(o, d, lo, hi):
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - o) / d
        t2 = (hi - o) / d
    tn = np.nanmax(np.minimum(t1, t2), axis=1)
    tf = np.nanmin(np.maximum(t1, t2), axis=1)
    return np.where((tf >= tn) & (tn > 0), tn, np.inf)


def _sweep(frame, with_box=True):
    """Sensor-frame points of one sweep (the sensor is axis-aligned)."""
    origin = np.array([EGO_STEP * frame, 0.0, SENSOR_Z])
    d = _rays()
    o = np.broadcast_to(origin, d.shape)
    t = np.full(len(d), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        tg = -origin[2] / d[:, 2]                          # road z = 0
        t = np.where(tg > 0, np.minimum(t, tg), t)
        for y in (WALL_Y, -WALL_Y):                        # facades, 6 m tall
            tw = (y - origin[1]) / d[:, 1]
            z = origin[2] + tw * d[:, 2]
            t = np.where((tw > 0) & (z < 6.0), np.minimum(t, tw), t)
    # two static pillars for structure
    for cx in (15.0, 30.0):
        t = np.minimum(t, _slab(o, d, np.array([cx - 0.3, -5.3, 0]), np.array([cx + 0.3, -4.7, 3])))
    if with_box:
        c = BOX_START + np.array([BOX_STEP * frame, 0, 0])
        t = np.minimum(t, _slab(o, d, c - BOX_HALF, c + BOX_HALF))
    ok = np.isfinite(t) & (t < 80)
    return d[ok] * t[ok, None]


def _poses():
    P = np.tile(np.eye(4), (N_FRAMES, 1, 1))
    P[:, 0, 3] = EGO_STEP * np.arange(N_FRAMES)
    P[:, 2, 3] = SENSOR_Z
    return P


def _on_box(points_world, frame):
    c = BOX_START + np.array([BOX_STEP * frame, 0, 0])
    return np.all(np.abs(points_world - c) <= BOX_HALF + 0.05, axis=1)


@pytest.fixture(scope="module")
def drive():
    return [_sweep(i) for i in range(N_FRAMES)], _poses()


def test_moving_box_becomes_a_rigid_node(drive):
    scans, poses = drive
    res = motion.detect_motion(scans, poses)
    assert len(res.objects) == 1
    obj = res.objects[0]
    # Static walls, pillars and road are not dynamic.
    for i, s in enumerate(scans):
        world = s + poses[i, :3, 3]
        box = _on_box(world, i)
        assert res.dynamic[i][~box].mean() < 0.005
    # The node moves with the box: BOX_STEP per sweep along x, no sideways drift.
    lab = np.nonzero(obj.labelled)[0]
    assert len(lab) >= motion.MotionOptions().min_frames
    t = obj.poses[lab, :3, 3]
    steps = np.diff(t, axis=0) / np.diff(lab)[:, None]
    assert abs(np.median(steps[:, 0]) - BOX_STEP) < 0.05
    assert np.allclose(steps[:, 0], BOX_STEP, atol=0.2)
    assert np.abs(steps[:, 1]).max() < 0.1
    # Heading along the travel; the box's footprint near the truth.
    assert abs(obj.poses[lab[0], 0, 0]) > 0.99
    h, w, l = obj.size_hwl
    assert abs(l - 2 * BOX_HALF[0]) < 0.6 and abs(w - 2 * BOX_HALF[1]) < 0.6
    # Its centre at a labelled frame (x, y) within 0.5 m of the box's.
    c = BOX_START[:2] + np.array([BOX_STEP * lab[0], 0])
    assert np.linalg.norm(obj.poses[lab[0], :2, 3] - c) < 0.5
    assert res.stats["masked_points"] < 0.05 * res.stats["dynamic_points"]


def test_untrackable_motion_is_masked_not_modelled(drive):
    scans, poses = drive
    res = motion.detect_motion(scans, poses, motion.MotionOptions(min_frames=N_FRAMES + 1))
    assert res.objects == []
    box_pts = masked_on_box = wall_masked = 0
    for i, s in enumerate(scans):
        box = _on_box(s + poses[i, :3, 3], i)
        box_pts += box.sum()
        masked_on_box += res.masked[i][box].sum()
        wall_masked += res.masked[i][~box].sum()
    assert masked_on_box > 0.6 * box_pts
    assert wall_masked < 0.01 * masked_on_box


def test_camera_mask_covers_the_box():
    K = np.array([[200.0, 0, 159.5], [0, 200.0, 59.5], [0, 0, 1]])
    # camera at the ego's first pose, looking along +x (OpenCV axes)
    cam = np.eye(4)
    cam[:3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)
    cam[:3, 3] = [0, 0, SENSOR_Z]
    s = _sweep(0)
    box = _on_box(s + [0, 0, SENSOR_Z], 0)
    world = s[box] + [0, 0, SENSOR_Z]
    mask = motion.camera_mask(world, np.zeros(len(world), int), np.linalg.inv(cam), K, (320, 120))
    from mi_invrgbl.io.init_gaussians import project
    uv, _, ok = project(world, np.linalg.inv(cam), K, (320, 120))
    px = np.round(uv[ok]).astype(int)
    assert (mask[px[:, 1], px[:, 0]] == 255).all()
    # a wall point on the other side stays unmasked
    wall = np.array([[12.0, -WALL_Y, 2.0]])
    uv, _, ok = project(wall, np.linalg.inv(cam), K, (320, 120))
    assert ok[0] and mask[int(round(uv[0, 1])), int(round(uv[0, 0]))] == 0
