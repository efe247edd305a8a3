"""Stage 1 keeps a moving object's Gaussians inside the box of its imported
centres (``mi_invrgbl.fit.object_bounds``), so that an object cannot paint its
own shadow on the road around it."""

import numpy as np
import pytest
import drjit as dr
import mitsuba as mi

from fit_scene import build_with_block
from mi_invrgbl.fit.config import FitConfig
from mi_invrgbl.fit.init import load_state
from mi_invrgbl.fit.object_bounds import CENTRE_MARGIN, MARGIN, SUPPORT, ObjectBox, boxed_objects
from mi_invrgbl.io.motion import FROM_LIDAR_MOTION
from mi_invrgbl.fit.steps import make_optimizer
from mi_invrgbl.physics.gaussian_ply import quaternion_to_matrix

W, H, COLUMNS, FRAMES = 32, 12, 64, 4


def _reach(centers, scales, quats_xyzw):
    """Per Gaussian and box axis: how far its support reaches from its centre."""
    R = quaternion_to_matrix(np.asarray(quats_xyzw)[:, [3, 0, 1, 2]])
    return SUPPORT * np.sqrt(np.einsum("nij,nj->ni", R ** 2, np.asarray(scales) ** 2))


def _adam(box, c, s, q):
    keys = box.keys()
    return make_optimizer({keys[0]: mi.Float(c.ravel()), keys[1]: mi.Float(np.log(s).ravel()),
                           keys[2]: mi.Float(q.ravel())}, {k: 1e-2 for k in keys}), keys


def test_supports_end_inside_the_box_and_gaussians_inside_are_left_alone():
    rng = np.random.default_rng(3)
    n = 400
    box = ObjectBox("car", np.array([-2.0, -0.9, -0.7]), np.array([2.0, 0.9, 0.7]))
    # Half small and well inside, half anywhere and up to 1.6 m wide.
    half = n // 2
    c = np.concatenate([rng.uniform(0.8 * box.lo, 0.8 * box.hi, (half, 3)),
                        rng.uniform(-3.0, 3.0, (n - half, 3))])
    s = np.exp(np.concatenate([rng.uniform(-6.0, -3.0, (half, 3)),
                               rng.uniform(-5.0, 0.5, (n - half, 3))]))
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    adam, keys = _adam(box, c, s, q)
    # One step so that Adam has moments the clamp must keep.
    for k in keys:
        dr.enable_grad(adam[k])
    dr.backward(sum(dr.sum(dr.square(adam[k])) for k in keys))
    adam.step()
    c0, logs0 = np.array(adam[keys[0]]).reshape(n, 3), np.array(adam[keys[1]]).reshape(n, 3)
    q0 = np.array(adam[keys[2]]).reshape(n, 4)
    moments = {k: [np.array(v) for v in adam.state[k][3][1:3]] for k in keys}
    box.apply(adam)
    c1, s1 = np.array(adam[keys[0]]).reshape(n, 3), np.exp(np.array(adam[keys[1]]).reshape(n, 3))
    reach = _reach(c1, s1, q0)
    tol = 1e-4
    assert np.all(c1 >= box.lo - CENTRE_MARGIN - tol) and np.all(c1 <= box.hi + CENTRE_MARGIN + tol)
    assert np.all(c1 - reach >= box.lo - MARGIN - tol) and np.all(c1 + reach <= box.hi + MARGIN + tol)
    # Those that fitted before are untouched, bit for bit.
    before = _reach(c0, np.exp(logs0), q0)
    inside = np.all((c0 - before >= box.lo - MARGIN) & (c0 + before <= box.hi + MARGIN), axis=1)
    assert inside[:half].all() and half < inside.sum() < n
    np.testing.assert_array_equal(c1[inside], c0[inside])
    np.testing.assert_array_equal(np.array(adam[keys[1]]).reshape(n, 3)[inside], logs0[inside])
    # The others shrank evenly (all three scales by one factor; a few only had
    # their centres clipped) and kept their rotation.
    ratio = s1[~inside] / np.exp(logs0[~inside])
    assert np.all(ratio <= 1.0) and np.mean(ratio[:, 0] < 1.0) > 0.5
    np.testing.assert_allclose(ratio / ratio[:, :1], 1.0, rtol=1e-4)
    np.testing.assert_array_equal(np.array(adam[keys[2]]).reshape(n, 4), q0)
    for k in keys:
        for a, b in zip(moments[k], adam.state[k][3][1:3]):
            np.testing.assert_array_equal(a, np.array(b))


def test_a_box_needs_finite_centres():
    assert ObjectBox.around("car", np.full((3, 3), np.nan)) is None
    assert ObjectBox.around("car", np.zeros((0, 3))) is None
    box = ObjectBox.around("car", np.array([[0.0, 1.0, 2.0], [np.nan, 0, 0], [1.0, -1.0, 0.5]]))
    np.testing.assert_array_equal(box.lo, [0.0, -1.0, 0.5])
    np.testing.assert_array_equal(box.hi, [1.0, 1.0, 2.0])


def test_only_objects_whose_extent_the_import_knew_are_boxed():
    """A track found by LiDAR motion has the box of the points seen of it:
    left free. Labelled tracks and objects without a track report are boxed."""
    from types import SimpleNamespace as NS
    frames = NS(objects={"object_0": NS(track_id=0), "object_1000": NS(track_id=1000),
                         "object_7": NS(track_id=7)},
                extra={"tracks": [{"track_id": 0, "kind": "Car"},
                                  {"track_id": 1000, "kind": "moving", "from": FROM_LIDAR_MOTION}]})
    assert boxed_objects(frames) == {"object_0", "object_7"}
    assert boxed_objects(NS(objects=frames.objects, extra={})) == set(frames.objects)


@pytest.fixture(scope="module")
def moving_scene(tmp_path_factory):
    """The fit scene of tests/fit_scene.py with a 1 m block of Gaussians driving along it."""
    return build_with_block(str(tmp_path_factory.mktemp("bounds")), n_frames=FRAMES,
                            width=W, height=H, columns=COLUMNS)


@pytest.mark.parametrize("bounds", [True, False])
def test_stage1_holds_the_moving_block_inside_its_imported_box(moving_scene, tmp_path, bounds):
    """The block's Gaussians are blown up to 2 m before stage 1: after one
    step they fit the box of the imported centres again, unless the fit is
    told to let them grow (then they stay far out)."""
    from mi_invrgbl.fit.stage1 import Stage1
    cfg = FitConfig(output=str(tmp_path), fit_width=W, lidar_columns=COLUMNS, samples=8,
                    batch_rays=256, lidar_batch_rays=128, seed=2, object_poses=False,
                    object_bounds=bounds)
    state = load_state(moving_scene, cfg, log=lambda *a: None)
    node = state.model.nodes["object_1"]
    centres = node.numpy("center")
    if bounds:
        (box,) = state.object_boxes
        np.testing.assert_allclose(box.lo, centres.min(0), atol=1e-6)
        np.testing.assert_allclose(box.hi, centres.max(0), atol=1e-6)
    else:
        assert state.object_boxes == []
    node.values["log_scale"] = mi.Float(np.full(3 * node.count, np.log(2.0 / SUPPORT), np.float32))
    s1 = Stage1(state)
    s1.iteration(1)
    s1.pull()
    c = node.numpy("center")
    reach = _reach(c, np.exp(node.numpy("log_scale")), node.numpy("rotation"))
    lo, hi = centres.min(0) - MARGIN - 1e-4, centres.max(0) + MARGIN + 1e-4
    inside = np.all((c - reach >= lo) & (c + reach <= hi), axis=1)
    if bounds:
        assert inside.all()
    else:
        assert not inside.any()
    assert np.isfinite(c).all() and np.isfinite(node.numpy("log_scale")).all()
