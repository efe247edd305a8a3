"""Stage 1's per-frame corrections of the sensor rig's pose
(``mi_invrgbl/fit/rig_poses.py``): corrected rays against rays Mitsuba's own
sensor casts from the moved pose, gradients against finite differences,
interpolation to frames that take no steps, the fit's outputs, and a real
optimisation that recovers a known camera pose error from images alone."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import drjit as dr
import mitsuba as mi

import variant_choice  # noqa: F401  (sets the variant)
from mi_invrgbl.fit import rig_poses as rp
from mi_invrgbl.fit.object_poses import correction_matrix
from mi_invrgbl.fit.observations import camera_rays
from mi_invrgbl.fit.render import camera_unlit
from mi_invrgbl.fit.steps import make_optimizer
from mi_invrgbl.fit.variables import PoseVariable
from mi_invrgbl.scene.frames import CAMERA_FLIP
from test_scene_graph import tiny_scene  # noqa: F401  (fixture)

W, H = 48, 32


def _look(origin, yaw=0.0):
    """A camera at ``origin`` looking along +z turned by ``yaw`` about y (Mitsuba axes)."""
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    T[:3, 3] = origin
    return T


def _sensor(T, fov=50.0):
    return mi.load_dict({"type": "perspective", "fov": fov, "to_world": mi.ScalarTransform4f(T),
                         "film": {"type": "hdrfilm", "width": W, "height": H}})


def _frames(poses, train):
    """Observations with one camera each (no LiDAR); ``train``: positions."""
    obs = []
    for k, T in enumerate(poses):
        sensor = _sensor(T)
        cam = SimpleNamespace(sensor=sensor, rays=camera_rays(sensor, W, H), width=W, height=H)
        obs.append(SimpleNamespace(index=k, held_out=False, camera=cam, lidar=None, poses={}))
    return obs, [obs[k] for k in train]


def _matrix(transform):
    return np.array(transform.matrix, np.float64).reshape(4, 4)


def _numpy_rays(rays):
    return (np.stack([np.array(rays.o[k]) for k in range(3)], 1),
            np.stack([np.array(rays.d[k]) for k in range(3)], 1))


def test_rays_and_sensors_follow_the_corrected_pose():
    """The rays a step traces, and the rays ``bake`` leaves in the frame, are
    the rays Mitsuba's perspective sensor casts once moved to
    ``T @ [R(w) | t]``."""
    obs, train = _frames([_look([0, 1.5, 0], 0.2), _look([0.3, 1.5, 2.0], -0.1)], [0, 1])
    fit = rp.RigPoseFit(obs, train)
    c = np.array([[0.04, -0.02, 0.07, 0.01, -0.015, 0.02], [-0.03, 0.01, 0.0, -0.005, 0.02, 0.0]])
    fit.values["rig", "t"] = mi.Float(c[:, :3].ravel().astype(np.float32))
    fit.values["rig", "w"] = mi.Float(c[:, 3:].ravel().astype(np.float32))
    base = [_matrix(f.camera.sensor.world_transform()) for f in obs]
    idx = dr.arange(mi.UInt32, W * H)
    stepped = [_numpy_rays(fit.rays(f, idx)) for f in obs]
    fit.bake()
    for k, f in enumerate(obs):
        want_T = base[k] @ correction_matrix(c[k])
        np.testing.assert_allclose(_matrix(f.camera.sensor.world_transform()), want_T, atol=2e-6)
        reference = _numpy_rays(camera_rays(_sensor(want_T), W, H))
        for got in (stepped[k], _numpy_rays(f.camera.rays)):
            np.testing.assert_allclose(got[0], reference[0], atol=2e-5)
            np.testing.assert_allclose(got[1], reference[1], atol=2e-5)
    # Baking again does not compound: the corrections apply to the import's poses.
    fit.bake()
    np.testing.assert_allclose(_matrix(obs[0].camera.sensor.world_transform()),
                               base[0] @ correction_matrix(c[0]), atol=2e-6)


@pytest.mark.parametrize("c0", [np.zeros(6), np.array([0.05, -0.02, 0.1, 0.01, 0.02, -0.01])])
def test_ray_gradient_matches_finite_differences(c0):
    """d/d(t, w) of a weighted sum of the corrected rays' origins and
    directions, at the corrections' start (w = 0) and away from it."""
    obs, train = _frames([_look([1.0, 1.5, -2.0], 0.4)], [0])
    fit = rp.RigPoseFit(obs, train)
    rng = np.random.default_rng(5)
    idx = jit = dr.arange(mi.UInt32, 40) * 37
    a = rng.normal(size=(40, 3))
    b = rng.normal(size=(40, 3))
    A = mi.Vector3f(*[mi.Float(a[:, k]) for k in range(3)])
    B = mi.Vector3f(*[mi.Float(b[:, k]) for k in range(3)])

    def value(c, grad=False):
        t = mi.Float(np.float32(c[:3]))
        w = mi.Float(np.float32(c[3:]))
        if grad:
            dr.enable_grad(t, w)
        fit.values["rig", "t"], fit.values["rig", "w"] = t, w
        r = fit.rays(obs[0], jit)
        return dr.sum(dr.dot(A, mi.Vector3f(r.o)) + dr.dot(B, r.d)), t, w

    y, t, w = value(c0, grad=True)
    dr.backward(y)
    grad = np.concatenate([np.array(dr.grad(t)), np.array(dr.grad(w))])
    with dr.suspend_grad():
        fd = np.array([(float(value(c0 + e)[0][0]) - float(value(c0 - e)[0][0])) / 2e-3
                       for e in np.eye(6) * 1e-3])
    assert np.all(np.isfinite(grad)) and len(idx) == 40
    np.testing.assert_allclose(grad, fd, rtol=2e-2, atol=2e-2 * np.abs(fd).max())


def test_frames_without_steps_interpolate_and_bounds_hold():
    """A validation or held-out frame between training frames takes the
    interpolated correction (its image is never read); beyond the last it
    holds the last. The variables clamp to the bounds."""
    obs, train = _frames([_look([0, 1.5, z]) for z in (0.0, 1.0, 2.0, 3.0)], [0, 2])
    fit = rp.RigPoseFit(obs, train)
    fit.values["rig", "t"] = mi.Float(np.float32([0.1, 0, 0, 9, 9, 9, 0.3, -0.2, 0, 9, 9, 9]))
    tab = fit.table()
    np.testing.assert_allclose(tab[1, :3], [0.2, -0.1, 0.0], atol=1e-6)
    np.testing.assert_allclose(tab[3, :3], [0.3, -0.2, 0.0], atol=1e-6)
    v = PoseVariable(fit, rp.NAME, "t", rp.TRANSLATION_LR, rp.MAX_TRANSLATION)
    clamped = np.array(v.clamp(mi.Float([5.0, -5.0, 0.1])))
    np.testing.assert_allclose(clamped, [rp.MAX_TRANSLATION, -rp.MAX_TRANSLATION, 0.1])
    state = fit.state_dict()
    other = rp.RigPoseFit(obs, train)
    other.load_state_dict(state)
    np.testing.assert_allclose(other.table(), tab, atol=1e-7)
    # Without two training views there is nothing to correct against.
    assert not rp.RigPoseFit(obs, train[:1])


def _wall_scene():
    """A textured wall of Gaussians 4 m ahead (smooth colours, so a pose
    error of a pixel or two stays in the loss's basin)."""
    gx, gy = np.meshgrid(np.linspace(-4, 4, 60), np.linspace(-0.5, 3.5, 30))
    x, y = gx.ravel(), gy.ravel()
    colour = np.stack([0.5 + 0.4 * np.sin(2 * np.pi * x / 2.5), 0.5 + 0.4 * np.cos(2 * np.pi * y / 1.7),
                       0.5 + 0.3 * np.sin(2 * np.pi * (x + y) / 3.1)], 1)
    m = len(x)
    return mi.load_dict({"type": "scene", "wall": {
        "type": "gaussians",
        "centers": mi.TensorXf(np.stack([x, y, np.full(m, 4.0)], 1).astype(np.float32)),
        "scales": mi.TensorXf(np.tile([0.1, 0.1, 0.01], (m, 1)).astype(np.float32)),
        "quaternions": mi.TensorXf(np.tile([1.0, 0, 0, 0], (m, 1)).astype(np.float32)),
        "opacities": mi.TensorXf(np.full(m, 0.95, np.float32)),
        "albedo": mi.TensorXf(colour.astype(np.float32))}})


def test_stage1_path_recovers_a_known_camera_error():
    """Images rendered from the true camera poses; the "imported" poses are
    4 cm and 0.6 degrees off. Adam on the corrections alone, through the
    rays a stage-1 step traces, brings the cameras back."""
    scene = _wall_scene()
    true = [_look([0.3 * k - 0.3, 1.5, 0.2 * k]) for k in range(3)]
    error = correction_matrix([0.04, -0.03, 0.0, 0.0, np.radians(0.6), np.radians(-0.4)])
    obs, train = _frames([T @ np.linalg.inv(error) for T in true], [0, 1, 2])
    targets = []
    with dr.suspend_grad():
        for T in true:
            rgb, _, _ = camera_unlit(scene, camera_rays(_sensor(T), W, H))
            dr.eval(rgb)
            targets.append(mi.Color3f(rgb))
    fit = rp.RigPoseFit(obs, train)
    keys = {fit.key(n, p): (n, p) for (n, p) in fit.values}
    adam = make_optimizer({k: fit.values[v] for k, v in keys.items()},
                          {k: {"t": 2e-3, "w": 4e-4}[v[1]] for k, v in keys.items()})
    idx = dr.arange(mi.UInt32, W * H)

    def loss_at(frame, grad=True):
        for k, v in keys.items():
            fit.values[v] = adam[k] if grad else dr.detach(adam[k])
        rgb, _, _ = camera_unlit(scene, fit.rays(frame, idx))
        return dr.mean(dr.squared_norm(rgb - targets[frame.index]), axis=None)

    with dr.suspend_grad():
        start = sum(float(loss_at(f, grad=False)[0]) for f in obs)
    for it in range(240):
        loss = loss_at(obs[it % 3])
        dr.backward(loss)
        adam.step()
    with dr.suspend_grad():
        end = sum(float(loss_at(f, grad=False)[0]) for f in obs)
    def on_wall(rays):
        o, d = _numpy_rays(rays)
        return o + (4.0 - o[:, 2:]) / d[:, 2:] * d

    before = [np.abs(on_wall(f.camera.rays) - on_wall(camera_rays(_sensor(T), W, H))).max()
              for f, T in zip(obs, true)]
    fit.bake()
    # A flat wall cannot tell a small tilt from a small shift; what the
    # images pin down is where each pixel's ray meets the wall: there the
    # corrected rays agree with the true ones to a sixth of a pixel (a
    # pixel is 7 cm on the wall), from about a pixel.
    for f, T, b in zip(obs, true, before):
        after = np.abs(on_wall(f.camera.rays) - on_wall(camera_rays(_sensor(T), W, H))).max()
        assert b > 0.06 and after < 0.012, (b, after)
    # (What is left of the loss is the wall's fine structure at a tenth of
    # a pixel: 0.0174 -> 0.0031 when written.)
    assert end < 0.3 * start


def _on_wall(rays):
    """Where ``rays`` meet the wall plane z = 4."""
    o, d = _numpy_rays(rays)
    return o + (4.0 - o[:, 2:]) / d[:, 2:] * d


def _relative_errors(poses, true):
    """Between neighbouring frames: how far apart their pixels' errors on
    the wall are (each pixel's ray meets the wall at some distance from
    where its true ray does; the largest difference of those offsets
    between the two frames, metres). A shift of both cameras together, or
    a tilt a shift makes up for, leaves the images agreeing and counts 0."""
    offsets = [_on_wall(camera_rays(_sensor(P), W, H)) - _on_wall(camera_rays(_sensor(T), W, H))
               for P, T in zip(poses, true)]
    return np.array([np.abs(a - b).max() for a, b in zip(offsets[:-1], offsets[1:])])


def test_search_aligns_cameras_whose_images_disagree():
    """Five views of the wall; the imported poses of two are 4-5 cm and
    0.3-0.4 degrees off. The start's search, from the images and the wall's
    points alone, makes neighbouring views agree: from a pixel apart on the
    wall to under a third of one (0.1-0.25 when written). (The images
    cannot tell where the cameras are all together: a move of every camera
    and the scene with it looks the same, so relative poses are what it
    fixes.)"""
    scene = _wall_scene()
    true = [_look([0.3 * k - 0.6, 1.5, 0.25 * k]) for k in range(5)]
    errors = [np.zeros(6), [0.05, -0.03, 0.0, 0.0, np.radians(0.4), 0.0], np.zeros(6),
              [-0.04, 0.02, 0.03, np.radians(-0.3), 0.0, np.radians(0.3)], np.zeros(6)]
    imported = [T @ np.linalg.inv(correction_matrix(e)) for T, e in zip(true, errors)]
    obs, train = _frames(imported, range(5))
    with dr.suspend_grad():
        for f, T in zip(obs, true):
            rgb, _, _ = camera_unlit(scene, camera_rays(_sensor(T), W, H))
            f.camera.image = np.stack([np.array(rgb[c]) for c in range(3)], 1).reshape(H, W, 3)
    points = np.array(mi.traverse(scene)["wall.data"]).reshape(-1, 10)[:, :3]
    fit = rp.RigPoseFit(obs, train)
    report = fit.align_from_images(points)
    fit.bake()
    corrected = [_matrix(f.camera.sensor.world_transform()) for f in obs]
    before, after = _relative_errors(imported, true), _relative_errors(corrected, true)
    assert report["used"] and report["mean_colour_difference"][1] < report["mean_colour_difference"][0]
    pixel = 2 * 4.0 * np.tan(np.radians(25.0)) / W            # 7.8 cm on the wall
    assert before.max() > pixel, before
    assert after.max() < 0.3 * pixel, (before, after)


def test_fit_outputs_move_the_sensors(tiny_scene, tmp_path):
    """The fit's scene.xml and frames.json carry every frame's corrected
    camera and LiDAR poses, held-out frames included (interpolated)."""
    from mi_invrgbl.fit.config import FitConfig
    from mi_invrgbl.fit.outputs import corrected_frames, fitted_xml
    from mi_invrgbl.scene.frames import Frames
    root, _, _ = tiny_scene
    frames = Frames.load(root)
    poses = [r.camera_to_world @ CAMERA_FLIP for r in frames]
    lidar = [r.lidar_to_world for r in frames]
    obs = []
    for r, T, L in zip(frames, poses, lidar):
        cam = SimpleNamespace(sensor=_sensor(T), width=W, height=H)
        cam.rays = camera_rays(cam.sensor, W, H)
        lid_sensor = mi.load_dict({"type": "lidar", "to_world": mi.ScalarTransform4f(L),
                                   "film": {"type": "hdrfilm", "width": 8, "height": 2}})
        lid = SimpleNamespace(sensor=lid_sensor, rays=camera_rays(cam.sensor, W, H))
        obs.append(SimpleNamespace(index=r.index, held_out=r.held_out, camera=cam, lidar=lid,
                                   poses=dict(r.objects)))
    fit = rp.RigPoseFit(obs, obs[:2])
    fit.values["rig", "t"] = mi.Float(np.float32([0.05, -0.02, 0.1, -0.04, 0.01, 0.0, 0, 0, 0]))
    fit.values["rig", "w"] = mi.Float(np.float32([0.01, 0.0, 0.02, 0.0, -0.01, 0.01, 0, 0, 0]))
    ctx = SimpleNamespace(scene_path=str(root / "scene.xml"), params={"sky": mi.Float(np.zeros(27))},
                          sky_key="sky", sh_order=2, sky_emitter=SimpleNamespace(order=2),
                          use_sun=False, selection={}, sun_visibility_learned=False,
                          config=FitConfig(samples=8), object_poses=None, rig_poses=fit,
                          frames=frames)
    out = tmp_path / "fit"
    out.mkdir()
    (out / "scene.xml").write_text(fitted_xml(ctx))
    (out / "object_7.ply").write_bytes((root / "object_7.ply").read_bytes())
    corrected_frames(ctx).save(out / "frames.json")
    fitted = Frames.load(out)
    scene = mi.load_file(str(out / "scene.xml"))
    fit.bake()
    sensors = {s.id(): s for s in scene.sensors()}
    for k, r in enumerate(fitted):
        cam = _matrix(sensors[r.camera].world_transform())
        np.testing.assert_allclose(cam, _matrix(obs[k].camera.sensor.world_transform()), atol=2e-5)
        np.testing.assert_allclose(r.camera_to_world_mitsuba, cam, atol=2e-5)
        np.testing.assert_allclose(r.lidar_to_world,
                                   _matrix(obs[k].lidar.sensor.world_transform()), atol=2e-5)
        # The rig moves as one: the LiDAR keeps its pose relative to the camera.
        np.testing.assert_allclose(np.linalg.inv(r.camera_to_world) @ r.lidar_to_world,
                                   np.linalg.inv(frames[k].camera_to_world) @ frames[k].lidar_to_world,
                                   atol=2e-6)
    assert not np.allclose(fitted[2].camera_to_world, frames[2].camera_to_world)   # held: frame 1's
