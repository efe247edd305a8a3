"""Stage 1 traces its random batches in sorted order (fit/render.batch_order).

Sorting is a speed measure (coherent SIMD packets); it must not change what
any ray renders or the gradients it sends back. Checked against the same rays
traced in draw order, on the fit tests' street, and that stage 1 really hands
the tracer sorted camera and LiDAR batches.
"""

import numpy as np
import pytest
import drjit as dr
import mitsuba as mi

from fit_scene import build
from mi_invrgbl.fit import stage1 as stage1_module
from mi_invrgbl.fit.config import FitConfig
from mi_invrgbl.fit.init import load_state
from mi_invrgbl.fit.render import batch_order, camera_unlit, gather_rays
from mi_invrgbl.fit.stage1 import Stage1


@pytest.fixture(scope="module")
def state(tmp_path_factory):
    d = tmp_path_factory.mktemp("batchorder")
    path = build(str(d), n_frames=5, width=48, height=16, columns=128)
    cfg = FitConfig(output=str(d / "fit"), fit_width=48, lidar_columns=128, batch_rays=512,
                    lidar_batch_rays=256, samples=8, seed=3)
    return load_state(path, cfg, log=lambda *a: None)


def _render(state, frame, index):
    """Colour, alpha, depth of the pixels ``index`` and d(sum of colour)/d(colour field)."""
    node = state.model.nodes["background"]
    colour = node.values["colour"]
    dr.enable_grad(colour)
    state.model.push(frame.poses, stage=1)
    rays = gather_rays(frame.camera.rays, mi.UInt32(index.astype(np.uint32)))
    rgb, alpha, depth = camera_unlit(state.scene, rays, 32, 1e-2)
    # Weight each ray by its pixel so that a mix-up of rays changes the gradient.
    w = mi.Float((1.0 + index % 7).astype(np.float32))
    dr.backward(dr.sum((rgb[0] + 2.0 * rgb[1] + 3.0 * rgb[2]) * w))
    grad = np.array(dr.grad(colour))
    dr.disable_grad(colour)
    out = [np.stack([np.array(rgb[c]) for c in range(3)], 1), np.array(alpha), np.array(depth)]
    return out, grad


def test_sorted_batches_render_and_differentiate_each_ray_as_in_draw_order(state):
    frame = state.train_frames[0]
    rng = np.random.default_rng(0)
    drawn = rng.integers(0, frame.camera.width * frame.camera.height, 600)   # with repeats
    (rgb_d, alpha_d, depth_d), grad_d = _render(state, frame, drawn)
    order = np.argsort(drawn, kind="stable")
    sorted_index = batch_order(drawn)
    np.testing.assert_array_equal(sorted_index, drawn[order])
    (rgb_s, alpha_s, depth_s), grad_s = _render(state, frame, sorted_index)
    assert alpha_d.max() > 0.5 and np.ptp(rgb_d) > 0.01      # the rays do meet Gaussians
    np.testing.assert_allclose(rgb_s, rgb_d[order], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(alpha_s, alpha_d[order], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(depth_s, depth_d[order], rtol=1e-5, atol=1e-5)
    assert np.abs(grad_d).max() > 0
    np.testing.assert_allclose(grad_s, grad_d, rtol=1e-4, atol=1e-6 * np.abs(grad_d).max())


def test_stage1_hands_the_tracer_sorted_camera_and_lidar_batches(state, monkeypatch):
    seen = []
    real = stage1_module._gather_rays

    def spy(rays, idx):
        seen.append(np.array(idx))
        return real(rays, idx)

    monkeypatch.setattr(stage1_module, "_gather_rays", spy)
    s1 = Stage1(state)
    frame = state.train_frames[0]
    assert frame.camera is not None and frame.lidar is not None
    s1.model.push(frame.poses, stage=1)
    terms = s1.loss_terms(frame)
    assert {"rgb", "range", "raydrop"} <= set(terms)
    assert [len(i) for i in seen] == [512, 256]
    for idx in seen:
        assert np.all(np.diff(idx.astype(np.int64)) >= 0)
        assert len(np.unique(idx)) > len(idx) // 2            # a random draw, not a range
