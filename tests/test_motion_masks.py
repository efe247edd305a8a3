"""Motion masks (``frames.json`` ``masks``): the fit leaves masked camera
pixels and LiDAR beams out of its losses, batches and scores.

The scene is tests/fit_scene.py's; every frame gets a camera mask over the
left half of the image and a LiDAR mask over the first half of the range
image's columns.
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import mitsuba as mi
import drjit as dr

from fit_scene import build, small_config
from mi_invrgbl.errors import UserError

WIDTH, HEIGHT, COLUMNS = 48, 16, 128


def _config(out, **kw):
    base = dict(stage1_iterations=4, stage2_iterations=4, fit_width=24, lidar_columns=64,
                batch_rays=256, lobe_iterations=4)
    base.update(kw)
    return small_config(out, **base)


def _write_masks(root, camera_shape=(HEIGHT, WIDTH), lidar_shape=(64, COLUMNS)):
    """Left half of every image and first half of every scan masked; listed in frames.json."""
    import cv2
    path = os.path.join(root, "frames.json")
    meta = json.load(open(path))
    for f in meta["frames"]:
        i = f["index"]
        cam = np.zeros(camera_shape, np.uint8)
        cam[:, : camera_shape[1] // 2] = 255
        lid = np.zeros(lidar_shape, np.uint8)
        lid[:, : lidar_shape[1] // 2] = 255
        cv2.imwrite(os.path.join(root, "observations", "motion_%04d.png" % i), cam)
        cv2.imwrite(os.path.join(root, "observations", "motion_lidar_%04d.png" % i), lid)
        f["masks"] = {"camera": "observations/motion_%04d.png" % i,
                      "lidar": "observations/motion_lidar_%04d.png" % i}
    json.dump(meta, open(path, "w"))


@pytest.fixture(scope="module")
def scene_path(tmp_path_factory):
    d = tmp_path_factory.mktemp("maskscene")
    path = build(str(d), n_frames=5, width=WIDTH, height=HEIGHT, columns=COLUMNS)
    _write_masks(str(d))
    return path


@pytest.fixture(scope="module")
def state(scene_path, tmp_path_factory):
    from mi_invrgbl.fit.init import load_state
    return load_state(scene_path, _config(tmp_path_factory.mktemp("fit")), log=lambda *a: None)


def _left_half(width, height):
    col = np.arange(width * height) % width
    return col < width // 2


def test_masks_load_at_the_fit_resolution(state):
    for f in state.observations:
        cam, lid = f.camera, f.lidar
        assert cam.width == 24 and cam.excluded.shape == (cam.height, cam.width)
        # Area-resized with any coverage kept: exactly the left half at 24 wide.
        assert np.array_equal(~cam.valid(), _left_half(cam.width, cam.height))
        # Thinned with the scan's columns (every 2nd of 128): the first 32 kept columns.
        assert lid.excluded.shape == lid.intensity.shape == (64, 64)
        assert np.array_equal(~lid.valid(), _left_half(64, 64))
        assert len(cam.valid_index()) == cam.width * cam.height // 2


def test_stage1_never_samples_masked_pixels_or_beams(state, monkeypatch):
    from mi_invrgbl.fit import stage1
    drawn = []
    real = stage1._gather_rays

    def spy(rays, idx):
        drawn.append((dr.width(rays.o), np.array(idx)))
        return real(rays, idx)

    monkeypatch.setattr(stage1, "_gather_rays", spy)
    st = stage1.Stage1(state)
    frame = state.train_frames[0]
    for _ in range(3):
        st.loss_terms(frame)
    cam_n = frame.camera.width * frame.camera.height
    cam = np.concatenate([i for n, i in drawn if n == cam_n])
    lid = np.concatenate([i for n, i in drawn if n != cam_n])
    assert cam.size and lid.size
    assert frame.camera.valid()[cam].all()
    assert frame.lidar.valid()[lid].all()
    # Both halves of the valid region are reached (the pool is not degenerate).
    assert len(np.unique(cam % frame.camera.width)) > frame.camera.width // 4


def test_stage2_losses_give_masked_pixels_no_gradient(state):
    from mi_invrgbl.fit.stage2 import FrozenScene, Stage2
    from mi_invrgbl.fit.losses import LossWeights
    frame = state.train_frames[0]
    st = Stage2(state, FrozenScene(state, [frame]))
    with dr.suspend_grad():
        out = st.render_frame(frame, st.values())
    # Every rendered channel becomes a leaf with a gradient of its own.
    leaves = {}
    for sensor, channels in out.items():
        for name, value in channels.items():
            if isinstance(value, (mi.Float, mi.Color3f, mi.Vector3f)):
                leaf = type(value)(dr.detach(value))
                dr.enable_grad(leaf)
                channels[name] = leaves[(sensor, name)] = leaf
    weights = LossWeights.parse("rgb=1,lidar=1,rgb2lidar=1,lidar2rgb=1")
    terms = st.loss_terms(frame, out, weights)
    assert {"rgb", "lidar", "rgb2lidar", "lidar2rgb"} <= set(terms)
    dr.backward(weights.combine(terms))

    def per_pixel(v):
        g = dr.grad(v)
        if isinstance(g, mi.Float):
            return np.abs(np.array(g))
        return np.abs(np.stack([np.array(g[k]) for k in range(3)], 1)).sum(axis=1)

    cam_masked = ~frame.camera.valid()
    lid_masked = ~frame.lidar.valid()
    for (sensor, name), leaf in leaves.items():
        g = per_pixel(leaf)
        masked = cam_masked if sensor == "camera" else lid_masked
        assert g.size == masked.size, (sensor, name)
        assert not g[masked].any(), (sensor, name)
    # ...while the unmasked pixels and beams do get gradients.
    assert per_pixel(leaves[("camera", "rgb")])[~cam_masked].any()
    assert per_pixel(leaves[("lidar", "intensity")])[~lid_masked].any()


def test_scores_ignore_masked_pixels(state):
    from mi_invrgbl.fit.evaluate import score_stage1
    frame = state.validation_frames[0]
    before = score_stage1(state, [frame])
    img = frame.camera.image
    saved = img.copy()
    try:
        img.reshape(-1, 3)[~frame.camera.valid()] = 1.0 - img.reshape(-1, 3)[~frame.camera.valid()]
        assert score_stage1(state, [frame]) == pytest.approx(before, abs=1e-9)
        img.reshape(-1, 3)[frame.camera.valid()] *= 0.5
        assert abs(score_stage1(state, [frame]) - before) > 0.1    # the score does look
    finally:
        img[...] = saved


def _load(scene_path, **kw):
    from mi_invrgbl.fit.observations import load_observations
    from mi_invrgbl.scene.frames import Frames
    scene = mi.load_file(scene_path)
    return load_observations(scene, Frames.load(scene_path), 24, 64, **kw)


@pytest.mark.parametrize("kind", ["camera", "lidar"])
def test_mask_of_the_wrong_size_is_one_line_error(tmp_path, kind):
    import cv2
    path = build(str(tmp_path), n_frames=5, width=WIDTH, height=HEIGHT, columns=COLUMNS)
    _write_masks(str(tmp_path))
    bad = tmp_path / "observations" / ("motion_0003.png" if kind == "camera"
                                       else "motion_lidar_0003.png")
    cv2.imwrite(str(bad), np.zeros((7, 5), np.uint8))
    with pytest.raises(UserError) as info:
        _load(path)
    msg = str(info.value)
    assert "\n" not in msg and str(bad) in msg and "5x7" in msg
    bad.write_bytes(b"not a png")
    with pytest.raises(UserError, match="cannot read the mask") as info:
        _load(path)
    assert "\n" not in str(info.value) and str(bad) in str(info.value)


def test_without_masks_nothing_is_excluded(tmp_path):
    path = build(str(tmp_path), n_frames=5, width=WIDTH, height=HEIGHT, columns=COLUMNS)
    _write_masks(str(tmp_path))
    os.remove(tmp_path / "observations" / "motion_0001.png")
    notes = []
    obs = _load(path, log=notes.append)
    assert len(notes) == 1 and "motion_0001.png" in notes[0]
    assert obs[1].camera.excluded is None and obs[1].camera.valid().all()
    assert obs[1].camera.valid_mask() is None
    assert obs[1].lidar.excluded is not None          # its LiDAR mask is still read
    assert obs[0].camera.excluded is not None


def test_frames_json_keeps_the_masks(scene_path, tmp_path):
    from mi_invrgbl.scene.frames import Frames
    frames = Frames.load(scene_path)
    assert frames[2].masks["lidar"].name == "motion_lidar_0002.png"
    frames.save(tmp_path / "frames.json")
    again = Frames.load(tmp_path / "frames.json")
    assert again[2].masks == frames[2].masks


def test_eval_scores_inside_and_outside_the_camera_mask():
    from mi_invrgbl.eval.scoring import masked_image_metrics
    from mi_invrgbl.io.kitti import srgb_to_linear
    rng = np.random.default_rng(0)
    observed = rng.uniform(0.2, 0.8, (12, 20, 3))
    render = srgb_to_linear(observed).copy()
    masked = np.zeros((12, 20), bool)
    masked[3:9, 5:11] = True
    render[masked] = 0.0                       # a moving truck the model left out
    out = masked_image_metrics(render, observed, masked)
    assert out["moving_fraction"] == pytest.approx(36 / 240)
    assert out["psnr_static"] > 60
    assert out["psnr_moving"] < 15


def test_import_lists_the_masks_it_writes_and_fit_reads_them(tmp_path):
    # io.importer writes io.motion's masks and lists them in frames.json;
    # here a box of masked LiDAR points 8 m ahead of every frame's sensors.
    from types import SimpleNamespace
    from mi_invrgbl.io.importer import _write_motion_masks
    from mi_invrgbl.scene.frames import Frames
    path = build(str(tmp_path), n_frames=5, width=WIDTH, height=HEIGHT, columns=COLUMNS)
    frames = Frames.load(path)
    g = np.stack(np.meshgrid(np.linspace(-0.5, 0.5, 5), np.linspace(-1, 1, 5),
                             np.linspace(-1.2, 0.0, 5)), -1).reshape(-1, 3)
    pts = g + [8.0, 0.0, 0.0]                    # LiDAR frame (x forward, z up)
    index = np.full((64, COLUMNS), -1, np.int64)
    index[20:22, :len(pts) // 2] = np.arange(len(pts) // 2 * 2).reshape(2, -1)
    n = len(frames)
    state = SimpleNamespace(
        motion=SimpleNamespace(masked=[np.ones(len(pts), bool)] * n, dynamic=None, tracks=[]),
        scans=[(pts, None)] * n, poses=[f.lidar_to_world for f in frames],
        cam_poses=[f.camera_to_world for f in frames], K=frames.camera.K, size=(WIDTH, HEIGHT),
        range_images=[SimpleNamespace(shape=(64, COLUMNS), index=index)] * n, counts={})
    assert _write_motion_masks(state, frames, tmp_path) == n
    again = Frames.load(path)
    assert again[3].masks["camera"] == tmp_path / "observations" / "motion_0003.png"
    obs = _load(path)
    for o in obs:
        assert 0 < (~o.camera.valid()).mean() < 0.5        # the box's hull, not the frame
        # every 2nd column kept: half of the 2 x 62 masked beams
        assert (~o.lidar.valid()).sum() == len(pts) // 2


def test_sky_lookalike_statistics_leave_masked_pixels_out(state):
    import warnings
    from mi_invrgbl.fit.sky_lookalikes import accumulate, frame_statistics
    frame = state.train_frames[0]
    state.model.push(frame.poses, stage=1)
    with dr.suspend_grad():
        full = frame_statistics(state.scene, frame.camera.rays)
        part = frame_statistics(state.scene, frame.camera.rays, valid=frame.camera.valid())
    assert len(part[2]) == len(full[2]) and (part[2] <= full[2]).all()
    assert 0.2 < part[2].sum() / full[2].sum() < 0.8      # the left half's hits weigh 0
    # A masked hit on a ray without evidence behind it (mismatch inf) adds
    # nothing, and no 0 x inf warning reaches the user.
    acc = {"a": np.zeros((2, 3))}
    stats = (np.array([7, 7], np.uint32), np.array([0, 1]), np.array([0.0, 0.5]),
             np.zeros(2), np.array([np.inf, 0.1]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        accumulate(acc, {"a": 7}, stats)
    assert np.array_equal(acc["a"][:, 2], [0.0, 0.05])
