"""Stage 2's frozen fast path against the plugins' own ``mi.render``.

Stage 2 never traces: it renders from hit lists cached once per frame
(:class:`~mi_invrgbl.fit.stage2.FrozenScene`). Here the same frozen scene
(tests/fit_scene.py, the model pushed into it) is rendered both ways, for a
camera (``invrgbl``) and a LiDAR (``lidar_return``), forward and gradient.

Where the tolerances come from:

* Cached with every hit (``min_weight = 0``) the two paths evaluate the same
  formulas on the same hits; they differ only in float32 rounding (kernels
  fused differently, sums reduced in another order): a few ulps per
  operation over ~100 operations, about 1e-5 relative. Asserted: 1e-4
  relative to the largest value (a 10x margin), forward and gradient.
* Cached as the fit does (``min_weight = 1e-4``), hits blended with weight
  below 1e-4 are dropped. A pixel then loses at most its dropped weight
  (the plugin's accumulated opacity minus the cache's) times the largest
  per-hit colour: that bound, computed per pixel, plus the rounding term.
* LiDAR: the fit's response clamps cos(theta) at 1e-4 where the plugin
  uses cos(theta) itself, which changes a hit's return by at most
  ``1e-4^a`` of a normal-incidence return: with ``a = 1`` that is inside the
  1e-4 relative term.
"""

import numpy as np
import pytest
import drjit as dr
import mitsuba as mi

from fit_scene import build
from mi_invrgbl.fit.config import FitConfig
from mi_invrgbl.fit.init import load_state
from mi_invrgbl.fit.render import frozen_gaussian_hits
from mi_invrgbl.fit.stage2 import FrozenScene, Stage2
from mi_invrgbl.physics.lighting import GaussianLighting

W, H, COLUMNS = 32, 12, 64
ROUNDING = 1e-4


@pytest.fixture(scope="module")
def scene_path(tmp_path_factory):
    return build(str(tmp_path_factory.mktemp("frozen")), n_frames=2, width=W, height=H, columns=COLUMNS)


def frozen_setup(scene_path, tmp_path, sun_visibility="learn", min_weight=0.0):
    cfg = FitConfig(output=str(tmp_path), fit_width=W, lidar_columns=COLUMNS, samples=8, sun="on",
                    sun_visibility=sun_visibility, validation_every=0)
    state = load_state(scene_path, cfg, log=lambda *a: None)
    frame = state.train_frames[0]
    state.model.push(frame.poses, stage=2)
    stage2 = Stage2(state, FrozenScene(state, [frame], min_weight=min_weight))
    return state, frame, stage2


def pixel_centre_camera(sensor):
    """The frame's camera, sampling each pixel once at its centre (as the fit's rays do)."""
    film = sensor.film()
    to_world = np.array(sensor.world_transform().matrix, np.float64).reshape(4, 4)
    return mi.load_dict({
        "type": "perspective", "fov": 80, "fov_axis": "x", "to_world": mi.ScalarTransform4f(to_world),
        "sampler": {"type": "stratified", "sample_count": 1, "jitter": False},
        "film": {"type": "hdrfilm", "width": film.size()[0], "height": film.size()[1],
                 "rfilter": {"type": "box"}}})


def camera_integrator(state, stage2):
    return mi.load_dict({"type": "invrgbl", "samples": state.config.samples,
                         "bounces": state.config.bounces, "max_hits": state.config.max_hits,
                         "min_transmittance": state.config.min_transmittance,
                         "shadowing": state.config.shadowing,
                         "sun_visibility": "attribute" if stage2.learn_sun_visibility else "trace"})


def lidar_integrator(state):
    r = state.response
    return mi.load_dict({"type": "lidar_return", "max_hits": state.config.max_hits,
                         "min_transmittance": state.config.min_transmittance,
                         "range_exponent": float(r.range_exponent[0]),
                         "angle_exponent": float(r.angle_exponent[0]),
                         "beam_gains": " ".join("%.9g" % g for g in np.array(r.beam_gains))})


def rows(v, k):
    return np.stack([np.array(v[i]) for i in range(k)], 1) if k > 1 else np.array(v)[:, None]


def weights(n, k, seed):
    return np.random.default_rng(seed).uniform(0.2, 1.0, (n, k)).astype(np.float32)


def close(a, b, what):
    tol = ROUNDING * max(np.abs(b).max(), 1e-12)
    err = np.abs(a - b).max()
    assert err <= tol, "%s: max difference %.3g > %.3g" % (what, err, tol)


# ------------------------------------------------------------------ camera
@pytest.mark.parametrize("sun_visibility", ["learn", "trace"])
def test_camera_forward_matches_mi_render(scene_path, tmp_path, sun_visibility):
    state, frame, stage2 = frozen_setup(scene_path, tmp_path, sun_visibility)
    with dr.suspend_grad():
        fast = stage2.render_frame(frame, stage2.values(), lidar=False)["camera"]
        ref = np.array(mi.render(state.scene, sensor=pixel_centre_camera(frame.camera.sensor),
                                 integrator=camera_integrator(state, stage2), spp=1)).reshape(H * W, -1)
    assert ref[:, 3 + 9].mean() > 0.5               # alpha AOV: the Gaussians fill the view
    close(rows(fast["rgb"], 3), ref[:, :3], "rgb")
    close(rows(fast["albedo"], 3), ref[:, 3:6], "albedo AOV")
    close(rows(fast["alpha"], 1)[:, 0], ref[:, 12], "alpha AOV")


def test_camera_forward_with_the_fits_hit_threshold(scene_path, tmp_path):
    state, frame, stage2 = frozen_setup(scene_path, tmp_path, min_weight=1e-4)
    with dr.suspend_grad():
        vals = stage2.values()
        fast = stage2.render_frame(frame, vals, lidar=False)["camera"]
        ref = np.array(mi.render(state.scene, sensor=pixel_centre_camera(frame.camera.sensor),
                                 integrator=camera_integrator(state, stage2), spp=1)).reshape(H * W, -1)
        # Largest per-hit colour, over every hit (a cache that drops none).
        full = FrozenScene(state, [frame], min_weight=0.0)
        nodes = full.nodes(frame, vals)
        fh = full.camera[frame.index]
        lighting = GaussianLighting(state.scene, nodes, state.config.samples, full.caches[frame.index],
                                    trace_sun=not stage2.learn_sun_visibility,
                                    bounces=state.config.bounces)
        g = frozen_gaussian_hits(nodes, frame.camera.rays, fh)
        colour = state.camera_integrator.shade_gaussian_hits(lighting, nodes, frame.camera.rays, fh, g)[0]
        c_max = rows(colour, 3).max(axis=0)
    dropped = np.maximum(ref[:, 12] - rows(fast["alpha"], 1)[:, 0], 0.0)
    assert dropped.max() < state.config.max_hits * 1e-4 + 1e-5  # at most max_hits hits of weight < 1e-4
    bound = dropped[:, None] * c_max[None, :] + ROUNDING * np.abs(ref[:, :3]).max()
    err = np.abs(rows(fast["rgb"], 3) - ref[:, :3])
    assert np.all(err <= bound), "worst excess %.3g" % (err - bound).max()


def test_sky_patterns_average_towards_the_sky_integral(scene_path, tmp_path):
    """Stage 2 turns the sky directions to another pattern each step: each
    pattern is a different M-direction estimate, and their mean is closer to
    the many-direction one than pattern 0 alone (what one fixed set would
    let the albedo absorb)."""
    from mi_invrgbl.physics.lighting import LightingCache
    state, frame, stage2 = frozen_setup(scene_path, tmp_path, "trace")
    K = 4
    with dr.suspend_grad():
        vals = stage2.values()
        rgb = [rows(stage2.render_frame(frame, vals, lidar=False, pattern=p)["camera"]["rgb"], 3)
               for p in range(K)]
        ref = rows(stage2.render_frame(frame, vals, lidar=False, samples=256,
                                       caches={frame.index: LightingCache()})["camera"]["rgb"], 3)
    assert len(stage2.frozen.pattern_caches) == K - 1
    assert np.abs(rgb[1] - rgb[0]).max() > 1e-3        # another pattern is another estimate
    err_one = np.abs(rgb[0] - ref).mean()
    err_mean = np.abs(np.mean(rgb, 0) - ref).mean()
    print("mean abs error vs M=256: pattern 0 %.5f, mean of %d patterns %.5f" % (err_one, K, err_mean))
    assert err_mean < 0.75 * err_one


def test_camera_gradients_match_mi_render(scene_path, tmp_path):
    state, frame, stage2 = frozen_setup(scene_path, tmp_path)
    u = weights(H * W, 3, seed=1)
    keys = ("background.albedo", "background.normal")
    vals = stage2.values()
    rgb = stage2.render_frame(frame, vals, lidar=False)["camera"]["rgb"]
    dr.backward(dr.sum(sum(mi.Float(u[:, c]) * rgb[c] for c in range(3))))
    fast = {k: np.array(dr.grad(stage2.opt.adam[k])) for k in keys}

    params = mi.traverse(state.scene)
    for k in keys:
        dr.enable_grad(params[k])
    params.update()
    img = mi.render(state.scene, params, sensor=pixel_centre_camera(frame.camera.sensor),
                    integrator=camera_integrator(state, stage2), spp=1)
    dr.backward(dr.sum(mi.TensorXf(u.reshape(H, W, 3)) * img[..., :3], axis=None))
    for k in keys:
        ref = np.array(dr.grad(params[k]))
        assert np.abs(ref).max() > 0, k
        close(fast[k], ref, "d/d " + k)


# ------------------------------------------------------------------- LiDAR
def lidar_pair(state, frame, stage2, params=None):
    out = stage2.render_frame(frame, stage2.values(), camera=False)["lidar"]
    img = mi.render(state.scene, params, sensor=frame.lidar.sensor, integrator=lidar_integrator(state))
    return out, img


def test_lidar_forward_matches_mi_render(scene_path, tmp_path):
    state, frame, stage2 = frozen_setup(scene_path, tmp_path)
    with dr.suspend_grad():
        fast, img = lidar_pair(state, frame, stage2)
    ref = np.array(img).reshape(-1, 5)
    hit = ref[:, 2] > 0
    assert hit.mean() > 0.3
    close(np.array(fast["alpha"]), ref[:, 4], "alpha")
    close(np.array(fast["intensity"])[hit], ref[hit, 0], "intensity")
    close(np.array(fast["range"])[hit], ref[hit, 1] * ref[hit, 4], "range x alpha")
    close(np.array(fast["lidar_albedo"])[hit], ref[hit, 3] * ref[hit, 4], "LiDAR albedo x alpha")


def test_lidar_gradients_match_mi_render(scene_path, tmp_path):
    state, frame, stage2 = frozen_setup(scene_path, tmp_path)
    keys = ("background.lidar_albedo", "background.roughness")
    with dr.suspend_grad():
        ref_img = np.array(mi.render(state.scene, sensor=frame.lidar.sensor,
                                     integrator=lidar_integrator(state))).reshape(-1, 5)
    # Beams with a return: the plugin reports no intensity elsewhere.
    u = weights(ref_img.shape[0], 1, seed=2)[:, 0] * (ref_img[:, 2] > 0)
    vals = stage2.values()
    out = stage2.render_frame(frame, vals, camera=False)["lidar"]
    dr.backward(dr.sum(mi.Float(u) * out["intensity"]))
    fast = {k: np.array(dr.grad(stage2.opt.adam[k])) for k in keys}

    params = mi.traverse(state.scene)
    for k in keys:
        dr.enable_grad(params[k])
    params.update()
    img = mi.render(state.scene, params, sensor=frame.lidar.sensor, integrator=lidar_integrator(state))
    dr.backward(dr.sum(mi.TensorXf(u.reshape(img.shape[0], img.shape[1])) * img[..., 0], axis=None))
    for k in keys:
        ref = np.array(dr.grad(params[k]))
        assert np.abs(ref).max() > 0, k
        close(fast[k], ref, "d/d " + k)


def test_camera_after_the_normals_turned_matches_mi_render(scene_path, tmp_path):
    """Stage 2 learns the normals while its sky visibility stays cached; the
    M sky directions turn with each normal. After
    :meth:`Stage2.refresh_lighting` the frozen path renders what the fitted
    scene renders (the plugin traces the turned directions afresh); before
    it, the cache still holds the old directions' visibility."""
    state, frame, stage2 = frozen_setup(scene_path, tmp_path, "trace")
    key = "background.normal"
    with dr.suspend_grad():
        stage2.render_frame(frame, stage2.values(), lidar=False)   # fills the cache
        n = np.array(stage2.opt.adam[key], np.float64).reshape(-1, 3)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        t = np.cross(n, [0.0, 0.0, 1.0])
        t[np.linalg.norm(t, axis=1) < 1e-6] = [1.0, 0.0, 0.0]
        t /= np.linalg.norm(t, axis=1, keepdims=True)
        turned = n.copy()
        turned[::2] = np.cos(np.radians(20)) * n[::2] + np.sin(np.radians(20)) * t[::2]
        flat = mi.Float(turned.ravel().astype(np.float32))
        stage2.opt.adam[key] = flat
        params = mi.traverse(state.scene)
        params[key] = mi.Float(flat)
        params.update()
        ref = np.array(mi.render(state.scene, sensor=pixel_centre_camera(frame.camera.sensor),
                                 integrator=camera_integrator(state, stage2), spp=1)).reshape(H * W, -1)
        stale = rows(stage2.render_frame(frame, stage2.values(), lidar=False)["camera"]["rgb"], 3)
        stage2.lighting_stale = True
        count = stage2.refresh_lighting()
        fresh = rows(stage2.render_frame(frame, stage2.values(), lidar=False)["camera"]["rgb"], 3)
    total = state.model.nodes["background"].count
    assert total // 2 <= count <= total // 2 + 1
    assert stage2.retraced["refreshes"] == 1 and stage2.retraced["gaussians"] == count
    # A subset re-traced in its own batch meets the ellipsoid intersector's
    # packet dependence (tests/test_lighting_cache.py) on a few shadow rays:
    # 0.4 % of the values differ by more than the rounding term (at most
    # 5e-4), against a stale cache's 0.037.
    tol = ROUNDING * np.abs(ref[:, :3]).max()
    err, err_stale = np.abs(fresh - ref[:, :3]), np.abs(stale - ref[:, :3])
    assert np.mean(err <= tol) > 0.98 and err.mean() < 0.01 * err_stale.mean()
    assert err.max() < 0.05 * err_stale.max()
    # Nothing turned since: a second refresh traces nothing.
    stage2.lighting_stale = True
    assert stage2.refresh_lighting() == 0
