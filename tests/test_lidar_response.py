"""One LiDAR response (:mod:`mi_invrgbl.physics.lidar_response`) for the
``lidar_return`` integrator and the fit: closed form, clamps, gradients, and
the fit's frozen render against the integrator on the same scene."""

import numpy as np
import pytest
import drjit as dr
import mitsuba as mi

from mi_invrgbl.physics import lidar_response as lr


def test_closed_form_and_numpy_agree():
    rng = np.random.default_rng(0)
    n = 200
    f, c, d = rng.uniform(0, 1, n), rng.uniform(0.01, 1, n), rng.uniform(0.5, 80, n)
    g, a, b, p = rng.uniform(0.5, 2, n), 0.7, 1.3, 2.5
    ref = g * f * p * c ** a / (np.pi * d ** b)
    got = np.array(lr.colocated_intensity(mi.Float(f), mi.Float(c), mi.Float(d), mi.Float(g), p,
                                          mi.Float(a), mi.Float(b)))
    assert np.allclose(got, ref, rtol=1e-5)
    assert np.allclose(lr.colocated_intensity_np(f, c, d, g, p, a, b), ref, rtol=1e-12)


def test_clamps_are_shared_and_finite():
    c = np.array([-0.3, 0.0, 1e-9, 0.5, 1.2])
    d = np.array([1.0, 1.0, 1.0, 0.0, 2.0])
    out = lr.colocated_intensity_np(np.ones(5), c, d, 1.0, 1.0, 1.0, 2.0)
    assert np.all(np.isfinite(out))
    assert out[0] == 0 and out[1] == 0                      # at or beyond grazing: nothing
    assert out[3] == pytest.approx(0.5 / (np.pi * lr.MIN_DISTANCE ** 2))
    assert out[4] == pytest.approx(1.0 / (np.pi * 4.0))     # cos clipped to 1
    dj = np.array(lr.colocated_intensity(mi.Float(np.ones(5)), mi.Float(c), mi.Float(d)))
    assert np.allclose(dj, out, rtol=1e-5)


def test_exponent_gradients_finite_at_grazing():
    a = mi.Float(1.0)
    b = mi.Float(2.0)
    dr.enable_grad(a, b)
    out = lr.colocated_intensity(mi.Float(1.0), mi.Float([0.0, 1e-12, 0.3]), mi.Float(3.0),
                                 1.0, 1.0, a, b)
    dr.backward(dr.sum(out))
    assert np.isfinite(np.array(dr.grad(a))).all() and np.isfinite(np.array(dr.grad(b))).all()
    # d/da c^a = c^a log c (c clamped to MIN_COS for the nearly grazing beam;
    # the grazing one returns nothing and has no gradient).
    expect = (0.3 * np.log(0.3) + lr.MIN_COS * np.log(lr.MIN_COS)) / (np.pi * 9)
    assert float(dr.grad(a)[0]) == pytest.approx(expect, rel=1e-5)


def test_beam_gain_lookup_and_single_gain():
    r = lr.LidarResponse(mi.Float(0.0), mi.Float(0.0), mi.Float([1.0, 2.0, 3.0]), mi.Float(1.0))
    out = r.numpy(np.full(4, np.pi), np.ones(4), np.ones(4), [0, 1, 2, 7])
    assert np.allclose(out, [1, 2, 3, 3])
    one = lr.LidarResponse(mi.Float(0.0), mi.Float(0.0), mi.Float([1.5]))
    assert np.allclose(np.array(one(mi.Float(np.pi), 1.0, 1.0, mi.UInt32([0, 5]))), 1.5)
    assert lr.parse_gains(lr.format_gains([0.5, 1.25])) == [0.5, 1.25]


def test_fit_and_integrator_render_the_same_response(tmp_path):
    """The fit's frozen LiDAR render and ``lidar_return`` agree on one scene
    with a laser power, non-default exponents and per-beam gains."""
    from mi_invrgbl.fit import render as fit_render
    from mi_invrgbl.physics import hits as hitlib
    from mi_invrgbl.plugins.lidar_return import LidarReturnIntegrator
    assert fit_render.Response is lr.LidarResponse
    xs = np.arange(-6, 6.01, 0.2)
    X, Y = np.meshgrid(xs, xs)
    n = X.size
    c = np.stack([X.ravel(), Y.ravel(), np.zeros(n)], 1).astype(np.float32)
    layer = {"type": "gaussians", "id": "layer", "centers": mi.TensorXf(c),
             "scales": mi.TensorXf(np.tile(np.float32([0.2, 0.2, 0.02]), (n, 1))),
             "opacities": mi.TensorXf(np.full(n, 1.0, np.float32)),
             "lidar_albedo": mi.TensorXf(np.full(n, 0.3, np.float32)),
             "roughness": mi.TensorXf(np.full(n, 0.5, np.float32))}
    elev = [-25.0, -35.0, -50.0]
    scene = mi.load_dict({"type": "scene", "layer": layer,
                          "laser": {"type": "laser", "power": 2.5},
                          "lidar": {"type": "lidar", "elevations": ",".join(map(str, elev)),
                                    "to_world": mi.ScalarTransform4f().translate([0, 0, 2.0]),
                                    "film": {"type": "hdrfilm", "width": 16, "height": 3,
                                             "rfilter": {"type": "box"}}}})
    integ = mi.load_dict({"type": "lidar_return", "range_exponent": 1.2, "angle_exponent": 0.8,
                          "beam_gains": "0.5, 1.0, 2.0"})
    ref = np.array(mi.render(scene, integrator=integ))[..., 0].ravel()
    sensor = scene.sensors()[0]
    rays, row, _, near = LidarReturnIntegrator.beam_rays(sensor)
    fh = fit_render.freeze(scene, rays, max_hits=64, min_transmittance=1e-3, min_weight=0.0)
    nodes = hitlib.gaussian_nodes(scene)
    got = fit_render.lidar_shaded(nodes, rays, row, mi.Float(near), fh, integ.response(scene))
    got = np.array(got["intensity"])
    assert np.all(ref > 0)
    assert np.allclose(got, ref, rtol=2e-3), np.c_[got, ref]
    # Power is part of the response: the fit without the scene's laser differs by P_e.
    bare = lr.LidarResponse(integ.range_exponent, integ.angle_exponent, integ.beam_gains)
    got1 = np.array(fit_render.lidar_shaded(nodes, rays, row, mi.Float(near), fh, bare)["intensity"])
    assert np.allclose(got1 * 2.5, ref, rtol=2e-3)


@pytest.mark.parametrize("beam_column", [True, False])
def test_rays_mode_gain_follows_each_rays_beam(tmp_path, beam_column):
    """A ray list (film N x 1) renders the same per-beam gains as the grid
    sensor with the same beams: carried in column 7, or derived from the
    rays' elevations."""
    elev = np.array([-20.0, -35.0, -60.0])
    W, h = 8, 2.0
    grid = {"type": "lidar", "elevations": ",".join("%g" % e for e in elev), "far_clip": 1000.0,
            "to_world": mi.ScalarTransform4f().translate([0, 0, h]),
            "film": {"type": "hdrfilm", "width": W, "height": 3, "rfilter": {"type": "box"}}}
    grid_sensor = mi.load_dict(grid)
    d = grid_sensor.ray_directions_local().reshape(-1, 3)
    beam = np.repeat(np.arange(3), W)
    perm = np.random.default_rng(0).permutation(len(d))      # any ray order
    cols = [np.zeros((len(d), 3)), d] + ([beam[:, None]] if beam_column else [])
    np.save(tmp_path / "rays.npy", np.hstack(cols)[perm])
    rays = {"type": "lidar", "rays": str(tmp_path / "rays.npy"), "far_clip": 1000.0,
            "to_world": mi.ScalarTransform4f().translate([0, 0, h])}
    sensor = mi.load_dict(rays)
    assert sensor.n_beams == 3
    assert np.array_equal(np.array(sensor.beam_index()), beam[perm])
    integ = mi.load_dict({"type": "lidar_return", "beam_gains": "0.5, 1.5, 2.0"})
    plane = {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale(100.0),
             "bsdf": {"type": "cooktorrance", "lidar_albedo": 0.25, "roughness": 0.6}}
    out = {}
    for name, s in (("grid", grid), ("rays", rays)):
        scene = mi.load_dict({"type": "scene", "plane": plane, "lidar": s})
        out[name] = np.array(mi.render(scene, integrator=integ))[..., 0].ravel()
    assert np.all(out["grid"] > 0)
    assert np.allclose(out["rays"], out["grid"][perm], rtol=1e-5)
    # Each ray carries its own beam's gain, not beam 0's.
    scene = mi.load_dict({"type": "scene", "plane": plane, "lidar": rays})
    unit = np.array(mi.render(scene, integrator=mi.load_dict({"type": "lidar_return"})))[..., 0].ravel()
    assert np.allclose(out["rays"] / unit, np.array([0.5, 1.5, 2.0])[beam[perm]], rtol=1e-5)


def test_bad_beam_column_is_refused(tmp_path):
    a = np.zeros((3, 7))
    a[:, 5] = -1.0
    a[0, 6] = 0.5
    np.save(tmp_path / "r.npy", a)
    with pytest.raises(Exception, match="column 7"):
        mi.load_dict({"type": "lidar", "rays": str(tmp_path / "r.npy")})
