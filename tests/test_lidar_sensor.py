"""Tests of the ``lidar`` sensor and the ``laser`` emitter.

The expected values are computed here from the documented formulas and from
the ray/plane geometry in float64 numpy, independently of the plugins' code.
"""

import numpy as np
import pytest
import drjit as dr
import mitsuba as mi


def film(width, height, **extra):
    return dict({"type": "hdrfilm", "width": width, "height": height,
                 "rfilter": {"type": "box"}}, **extra)


def expected_dirs(elev_deg, width):
    """(H, W, 3) beam directions from the documented formulas."""
    e = np.deg2rad(np.asarray(elev_deg, dtype=np.float64))[:, None]
    phi = np.pi * (1.0 - 2.0 * (np.arange(width) + 0.5) / width)[None, :]
    return np.stack([np.cos(e) * np.cos(phi), np.cos(e) * np.sin(phi),
                     np.sin(e) * np.ones_like(phi)], axis=-1)


def ray_arrays(ray):
    o = np.asarray(ray.o.numpy(), dtype=np.float64).T
    d = np.asarray(ray.d.numpy(), dtype=np.float64).T
    return o, d, np.asarray(ray.maxt.numpy(), dtype=np.float64)


def matrix(transform):
    return np.asarray(transform.matrix, dtype=np.float64).reshape(4, 4)


# --------------------------------------------------------------- geometry

def test_default_is_hdl64_grid():
    s = mi.load_dict({"type": "lidar"})
    assert (s.width, s.height) == (1024, 64)
    assert tuple(s.film().size()) == (1024, 64)
    assert "BoxFilter" in str(s.film())
    elev, azim = s.beam_grid()
    assert elev.shape == (64,) and azim.shape == (1024,)
    assert np.allclose(np.rad2deg(elev), np.linspace(2.0, -24.9, 64))
    assert np.all(np.diff(elev) < 0), "row 0 must be the highest beam"
    assert np.allclose(azim, np.pi * (1 - 2 * (np.arange(1024) + 0.5) / 1024))
    dirs = s.ray_directions_local()
    assert dirs.shape == (64, 1024, 3)
    assert np.allclose(dirs, expected_dirs(np.linspace(2.0, -24.9, 64), 1024), atol=1e-12)
    assert s.near_clip == 0.5 and s.far_clip == 120.0


def test_row_and_column_conventions():
    s = mi.load_dict({"type": "lidar", "fov_up": 10.0, "fov_down": -10.0,
                      "film": film(8, 3)})
    d = s.ray_directions_local()
    # Column W/2 looks (half a step to the right of) +x; column W/2-1 the other side.
    assert d[1, 4, 0] > 0.9 and d[1, 4, 1] < 0 and d[1, 3, 1] > 0
    # Column 0 looks backwards via the left (+y), the last column via the right.
    assert d[1, 0, 0] < -0.9 and d[1, 0, 1] > 0 and d[1, -1, 1] < 0
    # Column W/4 looks left (+y), 3W/4 right (-y); row 0 up, last row down.
    assert d[1, 2, 1] > 0.9 and d[1, 6, 1] < -0.9
    assert d[0, 4, 2] > 0 and np.isclose(d[1, 4, 2], 0.0) and d[2, 4, 2] < 0


def test_matches_range_image_projection():
    """u = 0.5 (1 - atan2(y, x) / pi) W puts every beam at its pixel's centre."""
    width = 360
    s = mi.load_dict({"type": "lidar", "preset": "vlp16", "film": film(width, 16)})
    d = s.ray_directions_local()
    u = 0.5 * (1.0 - np.arctan2(d[..., 1], d[..., 0]) / np.pi) * width
    assert np.allclose(u, np.arange(width)[None, :] + 0.5, atol=1e-9)


@pytest.mark.parametrize("preset,count,top,bottom", [
    ("hdl64", 64, 2.0, -24.9), ("vlp32", 32, 15.0, -25.0), ("vlp16", 16, 15.0, -15.0)])
def test_presets(preset, count, top, bottom):
    s = mi.load_dict({"type": "lidar", "preset": preset})
    elev, _ = s.beam_grid()
    assert s.height == count and s.width == 1024
    assert np.isclose(np.rad2deg(elev[0]), top) and np.isclose(np.rad2deg(elev[-1]), bottom)
    assert np.all(np.diff(elev) < 0)
    if preset == "vlp16":
        assert np.allclose(np.rad2deg(elev), np.arange(15, -16, -2))
    if preset == "vlp32":
        # The VLP-32C table is finer near the horizon than at its ends.
        steps = -np.diff(np.rad2deg(elev))
        assert steps.min() < 0.34 and steps.max() > 9.0


def test_elevation_table_sets_height():
    s = mi.load_dict({"type": "lidar", "elevations": "5, 0.5, -1,-7.25"})
    assert (s.width, s.height) == (1024, 4)
    assert np.allclose(np.rad2deg(s.beam_grid()[0]), [5, 0.5, -1, -7.25])
    with pytest.raises(Exception, match="film"):
        mi.load_dict({"type": "lidar", "elevations": "5, 0", "film": film(16, 3)})
    with pytest.raises(Exception, match="elevations"):
        mi.load_dict({"type": "lidar", "elevations": "5, x"})
    with pytest.raises(Exception, match="preset"):
        mi.load_dict({"type": "lidar", "preset": "hdl32e"})


def test_sample_ray_is_the_exact_beam_in_world_space():
    to_world = (mi.ScalarTransform4f().translate([1.0, -2.0, 1.5])
                .rotate([0.3, 1.0, 0.2], 37.0))
    s = mi.load_dict({"type": "lidar", "fov_up": 15.0, "fov_down": -30.0,
                      "near_clip": 0.25, "far_clip": 50.0,
                      "to_world": to_world, "film": film(40, 12)})
    W, H = 40, 12
    m = matrix(to_world)
    local = expected_dirs(np.linspace(15.0, -30.0, H), W).reshape(-1, 3)
    d_ref = local @ m[:3, :3].T
    d_ref /= np.linalg.norm(d_ref, axis=1, keepdims=True)
    o_ref = m[:3, 3] + 0.25 * d_ref

    o, d, maxt = ray_arrays(s.all_rays())
    assert np.allclose(d, d_ref, atol=2e-6) and np.allclose(o, o_ref, atol=2e-6)
    assert np.allclose(maxt, 50.0 - 0.25)
    o0, _, maxt0 = ray_arrays(s.all_rays(clip=False))
    assert np.allclose(o0, m[:3, 3], atol=1e-6) and np.allclose(maxt0, 50.0)
    assert np.allclose(np.asarray(s.origin().numpy()).ravel(), m[:3, 3])

    # Random samples anywhere inside a pixel all give that pixel's beam.
    rng = np.random.default_rng(1)
    n = 2000
    pos = rng.random((n, 2))
    sample = mi.Point2f(pos[:, 0].astype(np.float32), pos[:, 1].astype(np.float32))
    # The pixel is decided on the float32 sample the plugin sees.
    col = np.floor(np.float32(pos[:, 0]).astype(np.float64) * W).astype(int)
    row = np.floor(np.float32(pos[:, 1]).astype(np.float64) * H).astype(int)
    for method in (s.sample_ray, s.sample_ray_differential):
        ray, weight = method(mi.Float(0.0), mi.Float(0.5), sample, mi.Point2f(0.5))
        o, d, _ = ray_arrays(ray)
        k = row * W + col
        assert np.allclose(d, d_ref[k], atol=2e-6) and np.allclose(o, o_ref[k], atol=2e-6)
        assert np.allclose(np.asarray(weight.numpy()), 1.0)


def test_explicit_rays(tmp_path):
    rng = np.random.default_rng(2)
    n = 37
    rays = np.concatenate([rng.normal(size=(n, 3)) * 0.1, rng.normal(size=(n, 3)) * 3.0], axis=1)
    path = tmp_path / "pattern.npy"
    np.save(path, rays)
    to_world = mi.ScalarTransform4f().translate([0.0, 0.0, 2.0]).rotate([0, 0, 1], 90.0)
    s = mi.load_dict({"type": "lidar", "rays": str(path), "to_world": to_world,
                      "near_clip": 0.1})
    assert (s.width, s.height) == (n, 1) and s.explicit_rays
    dirs = rays[:, 3:] / np.linalg.norm(rays[:, 3:], axis=1, keepdims=True)
    assert np.allclose(s.ray_directions_local(), dirs[None])
    m = matrix(to_world)
    d_ref = dirs @ m[:3, :3].T
    o_ref = rays[:, :3] @ m[:3, :3].T + m[:3, 3] + 0.1 * d_ref
    o, d, _ = ray_arrays(s.all_rays())
    assert np.allclose(d, d_ref, atol=2e-6) and np.allclose(o, o_ref, atol=2e-6)
    with pytest.raises(Exception, match="explicit-ray"):
        s.beam_grid()
    with pytest.raises(Exception, match="film"):
        mi.load_dict({"type": "lidar", "rays": str(path), "film": film(n, 2)})
    np.save(tmp_path / "bad.npy", rays[:, :5])
    with pytest.raises(Exception, match="rays"):
        mi.load_dict({"type": "lidar", "rays": str(tmp_path / "bad.npy")})


def test_crop_window_maps_to_the_full_film():
    s = mi.load_dict({"type": "lidar", "preset": "vlp16",
                      "film": film(64, 16, crop_offset_x=10, crop_offset_y=3,
                                   crop_width=20, crop_height=5)})
    ray, _ = s.sample_ray(mi.Float(0.0), mi.Float(0.5), mi.Point2f(0.01, 0.01), mi.Point2f(0.5))
    d_ref = expected_dirs(np.arange(15, -16, -2), 64)[3, 10]
    assert np.allclose(ray_arrays(ray)[1][0], d_ref, atol=2e-6)


# ---------------------------------------------------------- stock pipeline

def random_rotation(rng):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def to_transform(rot, trans, scale=1.0):
    m = np.eye(4)
    m[:3, :3] = rot * scale
    m[:3, 3] = trans
    return mi.ScalarTransform4f(m.astype(np.float32)), m


def closed_form(m_sensor, elev_deg, width, m_plane, rho, power, near, far):
    """Per-pixel rho/pi P cos / d^2 of a rectangle, a mask of pixels whose
    hit/miss decision is within float32 round-off (plane edge, clip ranges),
    and the mask of beams that reach the plane (from either side)."""
    local = expected_dirs(elev_deg, width).reshape(-1, 3)
    d = local @ m_sensor[:3, :3].T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = m_sensor[:3, 3]
    c = m_plane[:3, 3]
    ex, ey, n = m_plane[:3, 0], m_plane[:3, 1], m_plane[:3, 2]
    n = n / np.linalg.norm(n)
    denom = d @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((c - o) @ n) / denom
    p = o + t[:, None] * d
    # Rectangle: local [-1, 1]^2; ex, ey carry the scale.
    u = (p - c) @ ex / (ex @ ex)
    v = (p - c) @ ey / (ey @ ey)
    inside = (np.abs(u) <= 1) & (np.abs(v) <= 1)
    hit = inside & (t >= near) & (t <= far) & np.isfinite(t)
    front = (o - c) @ n > 0  # Mitsuba's diffuse BSDF is one-sided
    cos = np.abs(denom)
    value = np.where(hit & front, rho / np.pi * power * cos / np.where(hit, t, 1.0) ** 2, 0.0)
    ambiguous = ((np.abs(np.abs(u) - 1) < 1e-4) | (np.abs(np.abs(v) - 1) < 1e-4)
                 | (np.abs(t - near) < 1e-4 * far) | (np.abs(t - far) < 1e-4 * far))
    shape = (len(elev_deg), width)
    return value.reshape(shape), ambiguous.reshape(shape), hit.reshape(shape)


def render_plane(sensor_tf, plane_tf, rho, power, fov, size, near, far):
    sensor = {"type": "lidar", "to_world": sensor_tf, "fov_up": fov[0], "fov_down": fov[1],
              "near_clip": near, "far_clip": far, "film": film(*size),
              "sampler": {"type": "independent", "sample_count": 1}}
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 2},
        "lidar": sensor,
        "laser": {"type": "laser", "to_world": sensor_tf, "power": power},
        "plane": {"type": "rectangle", "to_world": plane_tf,
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": rho}}},
    })
    img = np.asarray(mi.render(scene, sensor=scene.sensors()[0]), dtype=np.float64)
    assert img.shape == (size[1], size[0], 3)
    return img


@pytest.mark.parametrize("seed", range(8))
def test_stock_path_matches_closed_form(seed):
    rng = np.random.default_rng(100 + seed)
    rot_s = random_rotation(rng)
    pos_s = rng.uniform(-5, 5, size=3)
    sensor_tf, m_s = to_transform(rot_s, pos_s)
    # A large rectangle 2-15 m away along a random direction, tilted at random,
    # facing the sensor (or, one time in four, showing it its back).
    towards = rng.normal(size=3)
    towards /= np.linalg.norm(towards)
    centre = pos_s + rng.uniform(2.0, 15.0) * towards
    rot_p = random_rotation(rng)
    facing = (pos_s - centre) @ rot_p[:, 2] > 0
    if facing == (seed % 4 == 3):
        rot_p[:, 1:] *= -1  # flip the normal (keeps a rotation)
    plane_tf, m_p = to_transform(rot_p, centre, scale=rng.uniform(5.0, 30.0))
    rho, power = rng.uniform(0.1, 0.9), rng.uniform(0.5, 3.0)
    fov = (rng.uniform(0.0, 80.0), rng.uniform(-80.0, -5.0))
    size = (96, 24)
    near, far = 0.5, 40.0

    img = render_plane(sensor_tf, plane_tf, rho, power, fov, size, near, far)
    m_p32 = matrix(plane_tf)  # the float32 transforms Mitsuba actually used
    m_s32 = matrix(sensor_tf)
    ref, ambiguous, reaches = closed_form(m_s32, np.linspace(fov[0], fov[1], size[1]), size[0],
                                 m_p32, rho, power, near, far)
    assert np.allclose(img[..., 0], img[..., 1]) and np.allclose(img[..., 0], img[..., 2])
    got = img[..., 0]
    ok = ~ambiguous
    assert ok.mean() > 0.95
    miss = ok & (ref == 0)
    assert np.all(got[miss] == 0), "pixels that miss the plane must be 0"
    hit = ok & (ref > 0)
    # The geometry must put many beams on the plane; one case in four shows
    # the sensor the back of the one-sided diffuse plane: all zeros then.
    assert (ok & reaches).sum() > 50
    if seed % 4 == 3:
        assert hit.sum() == 0
    rel = np.abs(got[hit] - ref[hit]) / ref[hit]
    assert rel.size == 0 or rel.max() <= 1e-3, rel.max()


# -------------------------------------------------------------- hard cases

def wall_scene(distance, near, rho=0.5, power=1.0, extra=None):
    """Sensor at the origin with 3 beams (+10, 0 exactly, -10 degrees); a wall
    facing it ``distance`` ahead along +x."""
    wall_tf = (mi.ScalarTransform4f().translate([distance, 0.0, 0.0])
               .rotate([0, 1, 0], -90.0).scale(100.0))
    d = {"type": "scene",
         "integrator": {"type": "path", "max_depth": 2},
         "lidar": {"type": "lidar", "elevations": "10, 0, -10", "near_clip": near,
                   "film": film(8, 3)},
         "laser": {"type": "laser", "power": power},
         "wall": {"type": "rectangle", "to_world": wall_tf,
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": rho}}}}
    d.update(extra or {})
    return mi.load_dict(d)


def test_horizontal_beams_are_exact():
    scene = wall_scene(5.0, 0.5)
    s = scene.sensors()[0]
    _, d, _ = ray_arrays(s.all_rays())
    assert np.all(d.reshape(3, 8, 3)[1, :, 2] == 0.0), "0 degree beams must be exactly level"
    img = np.asarray(mi.render(scene, sensor=s), dtype=np.float64)[..., 0]
    # Columns 2..5 look forward (|phi| < 90 deg) and hit the wall x = 5.
    phi = np.pi * (1 - 2 * (np.arange(8) + 0.5) / 8)
    for row, e in enumerate(np.deg2rad([10.0, 0.0, -10.0])):
        cos = np.cos(e) * np.cos(phi)
        ref = np.where(cos > 0, 0.5 / np.pi * cos ** 3 / 25.0, 0.0)
        assert np.allclose(img[row], ref, rtol=1e-4, atol=0)


def test_horizontal_beams_miss_a_level_ground():
    ground = {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([0, 0, -1.7]).scale(50),
              "bsdf": {"type": "diffuse"}}
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 2},
                          "lidar": {"type": "lidar", "elevations": "0, -10", "film": film(16, 2)},
                          "laser": {"type": "laser"}, "ground": ground})
    img = np.asarray(mi.render(scene), dtype=np.float64)[..., 0]
    assert np.all(img[0] == 0) and np.all(img[1] > 0)


def test_near_clip():
    """Rays start near_clip along the beam. A surface closer than that is not
    seen, and it blocks the laser, so that beam returns nothing."""
    centre = (slice(None), slice(3, 5))  # columns looking along +x
    far_img = np.asarray(mi.render(wall_scene(0.7, 0.5)), dtype=np.float64)[..., 0]
    phi = np.pi * (1 - 2 * (np.arange(3, 5) + 0.5) / 8)
    cos = np.cos(phi)
    assert np.allclose(far_img[1, 3:5], 0.5 / np.pi * cos ** 3 / 0.49, rtol=1e-4)
    near_img = np.asarray(mi.render(wall_scene(0.3, 0.5)), dtype=np.float64)[..., 0]
    assert np.all(near_img[centre] == 0)
    # With near_clip 0.2 the same wall at 0.3 m is seen again.
    seen = np.asarray(mi.render(wall_scene(0.3, 0.2)), dtype=np.float64)[..., 0]
    assert np.allclose(seen[1, 3:5], 0.5 / np.pi * cos ** 3 / 0.09, rtol=1e-4)
    # Something behind a too-close occluder does not shine through either.
    behind = {"back": {"type": "rectangle", "to_world": mi.ScalarTransform4f()
                       .translate([3.0, 0, 0]).rotate([0, 1, 0], -90.0).scale(100.0),
                       "bsdf": {"type": "diffuse"}}}
    img = np.asarray(mi.render(wall_scene(0.3, 0.5, extra=behind)), dtype=np.float64)[..., 0]
    assert np.all(img[centre] == 0)


def test_far_clip():
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 2},
                          "lidar": {"type": "lidar", "elevations": "0", "far_clip": 4.0,
                                    "film": film(8, 1)},
                          "laser": {"type": "laser"},
                          "wall": {"type": "rectangle", "to_world": mi.ScalarTransform4f()
                                   .translate([5.0, 0, 0]).rotate([0, 1, 0], -90.0).scale(100.0),
                                   "bsdf": {"type": "diffuse"}}})
    assert np.all(np.asarray(mi.render(scene)) == 0)
    with pytest.raises(Exception, match="far_clip"):
        mi.load_dict({"type": "lidar", "near_clip": 2.0, "far_clip": 1.0})
    with pytest.raises(Exception, match="near_clip"):
        mi.load_dict({"type": "lidar", "near_clip": -1.0})


def test_nan_pose_is_refused():
    bad = mi.ScalarTransform4f().translate([0.0, float("nan"), 1.0])
    with pytest.raises(Exception, match="to_world"):
        mi.load_dict({"type": "lidar", "to_world": bad})
    with pytest.raises(Exception, match="to_world"):
        mi.load_dict({"type": "laser", "to_world": bad})
    with pytest.raises(Exception, match="position"):
        mi.load_dict({"type": "laser", "position": [0.0, float("nan"), 0.0]})
    # Also when the pose is changed through mi.traverse.
    s = mi.load_dict({"type": "lidar"})
    params = mi.traverse(s)
    params["to_world"] = mi.Transform4f().translate([float("nan"), 0.0, 0.0])
    with pytest.raises(Exception, match="to_world"):
        params.update()


@pytest.mark.parametrize("size", [(0, 64), (1024, 0)])
def test_zero_size_film_is_refused(size):
    with pytest.raises(Exception, match="film"):
        mi.load_dict({"type": "lidar", "film": film(*size)})


# ------------------------------------------------------------------ laser

def test_laser_interface():
    e = mi.load_dict({"type": "laser", "power": 2.5, "position": [1.0, 2.0, 3.0]})
    assert e.flags() & mi.EmitterFlags.DeltaPosition
    assert np.allclose(e.power.numpy(), 2.5)
    it = dr.zeros(mi.Interaction3f)
    it.p = mi.Point3f(1.0, 2.0, 7.0)
    ds, w = e.sample_direction(it, mi.Point2f(0.3, 0.6))
    assert np.allclose(np.asarray(w.numpy()), 2.5 / 16.0)
    assert np.allclose(np.asarray(ds.d.numpy()).ravel(), [0, 0, -1])
    assert np.allclose(ds.dist.numpy(), 4.0) and bool(ds.delta.numpy()[0])
    assert np.allclose(ds.pdf.numpy(), 1.0)
    assert np.allclose(e.pdf_direction(it, ds).numpy(), 0.0)
    params = mi.traverse(e)
    assert not (params.flags("power") & mi.ParamFlags.NonDifferentiable)
    params["power"] = mi.Float(4.0)
    params.update()
    assert np.allclose(e.power.numpy(), 4.0)
    with pytest.raises(Exception, match="power"):
        mi.load_dict({"type": "laser", "power": -1.0})


def test_laser_power_is_differentiable():
    scene = wall_scene(2.0, 0.5)
    params = mi.traverse(scene)
    key = [k for k in params.keys() if k.endswith("power")][0]
    dr.enable_grad(params[key])
    params.update()
    img = mi.render(scene, params, spp=1)
    dr.backward(dr.sum(img, axis=None))
    grad = float(np.asarray(dr.grad(params[key]).numpy()).ravel()[0])
    # The image is linear in P_e (= 1 here): d(sum)/dP_e = sum.
    assert np.isclose(grad, float(np.sum(np.asarray(img))), rtol=1e-4)
