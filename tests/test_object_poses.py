"""Stage 1's per-frame corrections of the moving objects' poses
(``mi_invrgbl/fit/object_poses.py``): the Dr.Jit pose against its numpy
matrix, gradients against finite differences, interpolation to the frames
that take no steps, and a real optimisation that recovers a known pose error
from rendered images alone."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import drjit as dr
import mitsuba as mi

import variant_choice  # noqa: F401  (sets the variant)
from mi_invrgbl.fit import object_poses as op
from mi_invrgbl.fit.model import GaussianModel
from mi_invrgbl.fit.render import camera_unlit
from mi_invrgbl.fit.steps import make_optimizer
from mi_invrgbl.physics.gaussian_ply import quaternion_to_matrix
from test_scene_graph import tiny_scene  # noqa: F401  (fixture)


def _random_pose(rng):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    T = np.eye(4)
    T[:3, :3] = quaternion_to_matrix(q[None])[0]
    T[:3, 3] = rng.normal(size=3) * 5
    return T


def _quat_matrix(q):
    x, y, z, w = (float(v[0]) for v in (q.x, q.y, q.z, q.w))
    return quaternion_to_matrix(np.array([[w, x, y, z]]))[0]


@pytest.mark.parametrize("c", [np.zeros(6), [0.3, -0.1, 0.05, 0.02, -0.05, 0.1],
                               [-2.0, 2.0, 0.0, 0.2, 0.2, -0.2]])
def test_corrected_pose_is_the_matrix_product(c):
    base = _random_pose(np.random.default_rng(3))
    c = np.asarray(c, np.float64)
    p = op.RigidPose.from_matrix(base).corrected(mi.Vector3f(*map(float, c[:3])), mi.Vector3f(*map(float, c[3:])))
    want = base @ op.correction_matrix(c)
    R = np.array([[float(p.rotation[i][j][0]) for j in range(3)] for i in range(3)])
    np.testing.assert_allclose(R, want[:3, :3], atol=2e-6)
    np.testing.assert_allclose([float(v[0]) for v in p.translation], want[:3, 3], atol=2e-5)
    np.testing.assert_allclose(_quat_matrix(p.quaternion), want[:3, :3], atol=2e-6)
    np.testing.assert_allclose(op.correction_matrix(c)[:3, :3] @ op.correction_matrix(c)[:3, :3].T,
                               np.eye(3), atol=1e-12)


@pytest.mark.parametrize("w0", [np.zeros(3), np.array([0.05, -0.02, 0.1])])
def test_pose_gradient_matches_finite_differences(w0):
    """d/d(t, w) of a weighted sum of posed points, at the corrections' start
    (w = 0, where the rotation's parametrisation must stay smooth) and away."""
    rng = np.random.default_rng(7)
    base = _random_pose(rng)
    pts = rng.normal(size=(20, 3))
    a = rng.normal(size=(20, 3))

    def f_numpy(c):
        T = base @ op.correction_matrix(c)
        return float(np.sum(a * (pts @ T[:3, :3].T + T[:3, 3])))

    t = mi.Vector3f(0.1, -0.2, 0.05)
    w = mi.Vector3f(*map(float, w0))
    dr.enable_grad(t, w)
    p = op.RigidPose.from_matrix(base).corrected(t, w)
    P = mi.Vector3f(*[mi.Float(pts[:, k]) for k in range(3)])
    A = mi.Vector3f(*[mi.Float(a[:, k]) for k in range(3)])
    y = dr.sum(dr.dot(A, p.rotation @ P + p.translation))
    dr.backward(y)
    grad = np.array([float(g[0]) for g in dr.grad(t)] + [float(g[0]) for g in dr.grad(w)])
    c0 = np.concatenate([[0.1, -0.2, 0.05], w0])
    fd = np.array([(f_numpy(c0 + e) - f_numpy(c0 - e)) / 2e-5 for e in np.eye(6) * 1e-5])
    assert np.all(np.isfinite(grad))
    np.testing.assert_allclose(grad, fd, rtol=2e-3, atol=2e-3 * np.abs(fd).max())


def _frames(n, train, name="object_1"):
    poses = [{name: np.eye(4) + np.diag([0, 0, 0, 0])} for _ in range(n)]
    for k, p in enumerate(poses):
        p[name][0, 3] = 0.5 * k               # the object drives along x
    obs = [SimpleNamespace(index=10 + k, held_out=False, poses=p) for k, p in enumerate(poses)]
    return obs, [obs[k] for k in train]


def test_frames_without_steps_interpolate_and_bake_does_not_compound():
    obs, train = _frames(6, [1, 3, 4])
    fit = op.ObjectPoseFit(obs, train, ["object_1", "object_9"])
    assert fit.objects == ["object_1"] and bool(fit)
    t = np.zeros((6, 3))
    t[[1, 3, 4], 0] = [0.2, 0.4, -0.1]
    fit.values["object_1", "t"] = mi.Float(t.ravel().astype(np.float32))
    for _ in range(2):                          # baking twice changes nothing
        fit.bake()
    x = [f.poses["object_1"][0, 3] - 0.5 * k for k, f in enumerate(obs)]
    np.testing.assert_allclose(x, [0.2, 0.2, 0.3, 0.4, -0.1, -0.1], atol=1e-6)
    assert fit.summary()["object_1"]["translation_m_max"] == pytest.approx(0.4, abs=1e-6)
    # the same poses go to the fit's own frames.json
    records = SimpleNamespace(frames=[SimpleNamespace(index=f.index, objects={"object_1": np.eye(4)})
                                      for f in obs])
    records.frames[0].objects["object_1"][0, 3] = 0.0
    out = fit.corrected_frames(records)
    assert out is not records and records.frames[2].objects["object_1"][0, 3] == 0.0
    np.testing.assert_allclose(out.frames[2].objects["object_1"][:3, 3], obs[2].poses["object_1"][:3, 3])
    # no training frame, or no moving object: nothing to fit
    assert not op.ObjectPoseFit(obs, [], ["object_1"])
    assert not op.ObjectPoseFit(obs, train, [])


def test_state_round_trip_and_bounds():
    from mi_invrgbl.fit.variables import PoseVariable
    obs, train = _frames(4, [0, 2])
    fit = op.ObjectPoseFit(obs, train, ["object_1"])
    fit.values["object_1", "w"] = mi.Float(np.arange(12, dtype=np.float32) * 0.01)
    state = fit.state_dict()
    other = op.ObjectPoseFit(obs, train, ["object_1"])
    other.load_state_dict(state)
    np.testing.assert_array_equal(np.array(other.values["object_1", "w"]), state["pose.object_1.w"])
    other.load_state_dict({"pose.object_1.w": np.zeros(5, np.float32)})   # another fit's: ignored
    np.testing.assert_array_equal(np.array(other.values["object_1", "w"]), state["pose.object_1.w"])
    v = PoseVariable(fit, "object_1", "t", op.TRANSLATION_LR, op.MAX_TRANSLATION)
    clamped = np.array(v.clamp(mi.Float([5.0, -5.0, float("nan"), 0.3])))
    np.testing.assert_allclose(clamped[[0, 1, 3]], [op.MAX_TRANSLATION, -op.MAX_TRANSLATION, 0.3])


def _panel_scene():
    """A static grey wall and, in front of it, a moving panel of coloured
    Gaussians (the object), seen by a pinhole camera at the origin looking
    down +z."""
    gx, gy = np.meshgrid(np.linspace(-0.5, 0.5, 16), np.linspace(-0.3, 0.3, 10))
    n = gx.size
    # Smooth colours (periods of about the panel's size): a pose error of a
    # tenth of it stays within the loss's basin.
    x, y = gx.ravel(), gy.ravel()
    colour = np.stack([0.5 + 0.4 * np.sin(2 * np.pi * x), 0.5 + 0.4 * np.cos(2 * np.pi * y / 0.8),
                       0.5 + 0.3 * np.sin(2 * np.pi * (x + y) / 0.9)], 1)
    panel = dict(centers=np.stack([x, y, np.zeros(n)], 1), albedo=colour)
    wx, wy = np.meshgrid(np.linspace(-4, 4, 30), np.linspace(-2, 2, 16))
    wall = dict(centers=np.stack([wx.ravel(), wy.ravel(), np.full(wx.size, 3.0)], 1),
                albedo=np.full((wx.size, 3), 0.5))

    def shape(c, albedo, scale):
        m = len(c)
        return {"type": "gaussians",
                "centers": mi.TensorXf(c.astype(np.float32)),
                "scales": mi.TensorXf(np.tile([scale, scale, 0.01], (m, 1)).astype(np.float32)),
                "quaternions": mi.TensorXf(np.tile([1.0, 0, 0, 0], (m, 1)).astype(np.float32)),
                "opacities": mi.TensorXf(np.full(m, 0.95, np.float32)),
                "albedo": mi.TensorXf(albedo.astype(np.float32))}
    return mi.load_dict({"type": "scene", "background": shape(wall["centers"], wall["albedo"], 0.2),
                         "object_1": shape(panel["centers"], panel["albedo"], 0.04)})


def _rays(width=64, height=40, fov=1.2):
    u, v = np.meshgrid((np.arange(width) + 0.5) / width - 0.5, (np.arange(height) + 0.5) / height - 0.5)
    d = np.stack([u.ravel() * fov, v.ravel() * fov * height / width, np.ones(u.size)], 1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    zero = dr.zeros(mi.Float, len(d))
    rays = mi.Ray3f(mi.Point3f(zero, zero, zero),
                    mi.Vector3f(*[mi.Float(d[:, k].astype(np.float32)) for k in range(3)]))
    rays.maxt = dr.full(mi.Float, 1e4, len(d))
    return rays


def test_stage1_path_recovers_a_known_pose_error():
    """Images rendered with the panel at its true poses; the "imported" poses
    are 12 cm and 2 degrees off. Adam on the corrections alone, through the
    same push and render stage 1 uses, brings the panel back."""
    scene = _panel_scene()
    model = GaussianModel(scene, object_names=["object_1"])
    rays = _rays()
    true = []
    for k in range(3):
        T = np.eye(4)
        T[:3, 3] = [0.2 * k - 0.2, 0.0, 1.5]
        true.append(T)
    error = op.correction_matrix([0.12, -0.06, 0.0, 0.0, 0.0, np.radians(2.0)])
    obs = [SimpleNamespace(index=k, held_out=False, poses={"object_1": T @ np.linalg.inv(error)})
           for k, T in enumerate(true)]
    targets = []
    with dr.suspend_grad():
        for T in true:
            model.push({"object_1": T}, stage=1)
            rgb, _, _ = camera_unlit(scene, rays)
            dr.eval(rgb)
            targets.append(mi.Color3f(rgb))
    fit = op.ObjectPoseFit(obs, obs, ["object_1"])
    keys = {fit.key(n, p): (n, p) for (n, p) in fit.values}
    adam = make_optimizer({k: fit.values[v] for k, v in keys.items()},
                          {k: {"t": 1e-2, "w": 2e-3}[v[1]] for k, v in keys.items()})

    def loss_at(frame, grad=True):
        for k, v in keys.items():
            fit.values[v] = adam[k] if grad else dr.detach(adam[k])
        model.push(fit.poses(frame), stage=1)
        rgb, _, _ = camera_unlit(scene, rays)
        return dr.mean(dr.squared_norm(rgb - targets[frame.index]), axis=None)

    with dr.suspend_grad():
        start = sum(float(loss_at(f, grad=False)[0]) for f in obs)
    for it in range(150):
        f = obs[it % 3]
        loss = loss_at(f)
        dr.backward(loss)
        adam.step()
    with dr.suspend_grad():
        end = sum(float(loss_at(f, grad=False)[0]) for f in obs)
    fit.bake()
    # The corrections undo the error: each frame's corrected pose is the true one.
    for f, T in zip(obs, true):
        np.testing.assert_allclose(f.poses["object_1"][:3, 3], T[:3, 3], atol=0.02)
        # The in-image rotation (about the panel's normal) is what the images
        # pin down; the tilts barely change them (Adam walks those by its rate).
        R = T[:3, :3].T @ f.poses["object_1"][:3, :3]
        assert abs(np.degrees(np.arctan2(R[1, 0], R[0, 0]))) < 0.5    # from 2 degrees
    assert end < 0.1 * start


class _StripView:
    """A fake training view of an object whose import pose is ``error`` metres
    off along its heading: it sees a smooth colour pattern painted along the
    object's true x axis."""

    def __init__(self, error):
        self.error = error
        self.image = np.zeros((1, 1, 3))

    def sample(self, world):
        x = world[:, 0] + self.error
        c = np.stack([0.5 + 0.3 * np.sin(2 * np.pi * x / 1.3), 0.5 + 0.3 * np.cos(2 * np.pi * x / 0.9),
                      0.5 + 0.2 * np.sin(2 * np.pi * x / 2.1)], 1)
        return c, np.abs(world[:, 0]) < 3.0


def test_heading_search_recovers_track_errors():
    """Offsets along the heading, smooth in time as a sliding registration
    leaves them, are found up to the object's free shift."""
    errors = np.array([0.35, 0.3, 0.22, 0.12, 0.05, 0.0, -0.02, 0.0, 0.06, 0.1])
    views = [_StripView(e) for e in errors]
    pts = np.stack([np.linspace(-2.5, 2.5, 600), np.zeros(600), np.zeros(600)], 1)
    offsets, before, after = op._align(views, [np.eye(4)] * len(views), pts)
    assert after < 0.2 * before
    found = offsets - np.median(offsets)
    want = -errors - np.median(-errors)
    np.testing.assert_allclose(found, want, atol=op.SEARCH_STEP)
    # a frame without a pose (the object not in it) takes no part
    offsets, _, _ = op._align(views, [np.eye(4)] * 4 + [None] + [np.eye(4)] * 5, pts)
    assert np.isnan(offsets[4]) and np.isfinite(offsets[[0, 5, 9]]).all()
    # nothing seen: nothing aligned, and no offsets invented
    blind = [SimpleNamespace(image=np.zeros((1, 1, 3)),
                             sample=lambda w: (np.zeros((len(w), 3)), np.zeros(len(w), bool)))] * 3
    offsets, before, after = op._align(blind, [np.eye(4)] * 3, pts)
    assert np.isnan(offsets).all() and np.isnan(before)


def test_frame_view_samples_the_pixel_a_point_projects_to():
    """The heading search's projection agrees with the camera's own rays."""
    from mi_invrgbl.fit.observations import camera_rays
    W, H = 40, 24
    T = np.eye(4)
    T[:3, :3] = quaternion_to_matrix(np.array([[0.9, 0.1, -0.3, 0.2]]) / np.linalg.norm([0.9, 0.1, -0.3, 0.2]))[0]
    T[:3, 3] = [1.0, -2.0, 0.5]
    sensor = mi.load_dict({"type": "perspective", "fov": 70, "to_world": mi.ScalarTransform4f(T.tolist()),
                           "film": {"type": "hdrfilm", "width": W, "height": H}})
    image = np.random.default_rng(2).uniform(0, 1, (H, W, 3)).astype(np.float32)
    cam = SimpleNamespace(sensor=sensor, rays=camera_rays(sensor, W, H), image=image, width=W, height=H)
    view = op._FrameView(SimpleNamespace(camera=cam))
    o = np.stack([np.array(cam.rays.o[k]) for k in range(3)], 1)
    d = np.stack([np.array(cam.rays.d[k]) for k in range(3)], 1)
    pick = np.array([0, 5 * W + 7, 13 * W + 30, H * W - 1])
    colours, seen = view.sample(o[pick] + 4.0 * d[pick])
    assert seen.all()
    np.testing.assert_allclose(colours, image.reshape(-1, 3)[pick], atol=1e-3)
    _, seen = view.sample(o[pick] - 4.0 * d[pick])          # behind the camera
    assert not seen.any()
    assert not op._FrameView(SimpleNamespace(camera=None)).sample(o[pick])[1].any()


def test_fit_outputs_place_objects_at_their_corrected_poses(tiny_scene, tmp_path):
    """What ``eval`` and the applications read back -- the fit's scene.xml
    (objects load at frame 0's pose) and its frames.json -- puts each
    object where the fit had it at every frame."""
    import shutil
    from mi_invrgbl.fit.config import FitConfig
    from mi_invrgbl.fit.outputs import fitted_xml
    from mi_invrgbl.scene.frames import Frames
    from mi_invrgbl.scene.posing import set_frame
    root, cloud, _ = tiny_scene
    frames = Frames.load(root)
    obs = [SimpleNamespace(index=r.index, held_out=r.held_out, poses=dict(r.objects)) for r in frames]
    fit = op.ObjectPoseFit(obs, obs[:2], ["object_7"])
    fit.values["object_7", "t"] = mi.Float(np.float32([0.3, -0.2, 0.1, -0.4, 0.1, 0.0, 0, 0, 0]))
    fit.values["object_7", "w"] = mi.Float(np.float32([0.05, 0.0, 0.2, 0.0, -0.1, 0.1, 0, 0, 0]))
    ctx = SimpleNamespace(scene_path=str(root / "scene.xml"), params={"sky": mi.Float(np.zeros(27))},
                          sky_key="sky", sh_order=2, sky_emitter=SimpleNamespace(order=2),
                          use_sun=False, selection={}, sun_visibility_learned=False,
                          config=FitConfig(samples=8),
                          object_poses=fit, frames=frames)
    out = tmp_path / "fit"
    out.mkdir()
    (out / "scene.xml").write_text(fitted_xml(ctx))
    shutil.copy(root / "object_7.ply", out / "object_7.ply")
    fit.corrected_frames(frames).save(out / "frames.json")
    fitted = Frames.load(out)
    scene = mi.load_file(str(out / "scene.xml"))
    fit.bake()
    for i in (1, 2, 0):                  # frame 2 takes frame 1's correction (held)
        set_frame(scene, fitted, i)
        shape = [s for s in scene.shapes() if s.id() == "object_7"][0]
        data = np.array(mi.traverse(shape)["data"]).reshape(-1, 10)
        T = obs[i].poses["object_7"]
        np.testing.assert_allclose(fitted[i].objects["object_7"], T, atol=1e-9)
        np.testing.assert_allclose(data[:, :3], cloud.centers @ T[:3, :3].T + T[:3, 3], atol=2e-4)
    assert not np.allclose(obs[0].poses["object_7"], frames[0].objects["object_7"])
