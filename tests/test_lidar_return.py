"""The ``lidar_return`` integrator against the paper's LiDAR equation.

The reference is written out here in numpy (float64), independently of
``mi_invrgbl/physics/brdf.py``:

    I = g (rho + F0 tau^2 min(1, 2 c^2) / (4 c^2 (c^2 (tau^2 - 1) + 1)^2)) P_e c^a / (pi d^b)

with c = cos(theta) between beam and normal, d the range, a = 1, b = 2 and
g = 1 unless the sensor response says otherwise. Each test batches many beams
into one render (explicit-ray mode of the ``lidar`` sensor) and computes every
beam's theta and d itself from the ray geometry.
"""

import numpy as np
import pytest
import drjit as dr
import mitsuba as mi

F0 = 0.04
CH_I, CH_RANGE, CH_HIT, CH_RHO, CH_ALPHA = range(5)


# ------------------------------------------------------------- references

def specular_pi(tau, c, f0=F0):
    tau = np.clip(tau, 1e-3, 1.0)  # documented GGX alpha clamp
    c2 = c * c
    return f0 * tau ** 2 * np.minimum(1, 2 * c2) / (4 * c2 * (c2 * (tau ** 2 - 1) + 1) ** 2)


def paper_intensity(rho, tau, c, d, power, model="pbr", a=1.0, b=2.0, gain=1.0):
    factor = rho + (specular_pi(tau, c) if model == "pbr" else 0.0)
    return gain * factor * power * c ** a / (np.pi * d ** b)


def rotation(axis, angle_deg):
    u = np.asarray(axis, float) / np.linalg.norm(axis)
    a = np.deg2rad(angle_deg)
    K = np.array([[0, -u[2], u[1]], [u[2], 0, -u[0]], [-u[1], u[0], 0]])
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


# ------------------------------------------------------------- scene set-up

def explicit_lidar(tmp_path, dirs_local, to_world=None, near=0.5, far=1000.0, name="rays"):
    rays = np.zeros((len(dirs_local), 6))
    rays[:, 3:] = dirs_local
    path = tmp_path / ("%s.npy" % name)
    np.save(path, rays)
    d = {"type": "lidar", "rays": str(path), "near_clip": near, "far_clip": far}
    if to_world is not None:
        d["to_world"] = to_world
    return d


def pose(R, p):
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = R, p
    return mi.ScalarTransform4f(m.astype(np.float32))


def plane(bsdf, size=100.0):
    """Rectangle z = 0 (normal +z), ``size`` metres from its centre to each edge.

    Not larger than the beams need (they end within 60 m): OptiX reports a
    triangle hit from float32 barycentrics, so its range error grows with the
    triangle's extent. Measured on an H100 over 60 beams: a 1e4 m rectangle
    gave range errors up to 1.1 mm (intensity 3.8e-4 relative, over the
    1e-4 asserted), a 100 m one 8e-6 m (3e-6); Embree is exact to 3e-6 at both.
    """
    return {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale(size), "bsdf": bsdf}


def scene(sensor, shapes, laser=None, **integrator):
    d = {"type": "scene", "integrator": dict({"type": "lidar_return"}, **integrator),
         "sensor": sensor}
    d.update(shapes)
    if laser is not None:
        d["laser"] = {"type": "laser", "power": laser}
    return mi.load_dict(d)


def render(sc, params=None):
    return np.array(mi.render(sc, params) if params is not None else mi.render(sc))[0]


def random_plane_beams(rng, n, max_theta_deg=80.0):
    """Random sensor pose above z = 0 and n downward beams: (R, p, local dirs, cos, d)."""
    p = np.array([rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(0.8, 8.0)])
    R = rotation(rng.normal(size=3), rng.uniform(0, 180))
    theta = np.deg2rad(rng.uniform(0, max_theta_deg, n))
    phi = rng.uniform(0, 2 * np.pi, n)
    d_world = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), -np.cos(theta)], 1)
    d_local = d_world @ R  # R^T d
    # Recompute cos and d from the float32 directions the sensor will use.
    dw = (d_local.astype(np.float32).astype(np.float64)) @ R.T
    dw /= np.linalg.norm(dw, axis=1, keepdims=True)
    cos = -dw[:, 2]
    dist = p[2] / cos
    return R, p, d_local, cos, dist


# ------------------------------------------------ closed form on a mesh plane

@pytest.mark.parametrize("kind", ["cooktorrance", "diffuse"])
def test_mesh_plane_matches_paper_equation(tmp_path, kind):
    rng = np.random.default_rng(1 if kind == "cooktorrance" else 2)
    errs_i, errs_r, count = [], [], 0
    for k in range(6):  # 6 random poses/materials x 10 beams = 60 samples
        R, p, d_local, cos, dist = random_plane_beams(rng, 10)
        rho, tau, power = rng.uniform(0.05, 0.9), rng.uniform(0.05, 1.0), rng.uniform(0.5, 3.0)
        if kind == "cooktorrance":
            bsdf = {"type": "cooktorrance", "lidar_albedo": rho, "roughness": tau}
        else:
            bsdf = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [rho] * 3}}
        sc = scene(explicit_lidar(tmp_path, d_local, pose(R, p), name="r%d" % k),
                   {"plane": plane(bsdf)}, laser=power)
        img = render(sc)
        model_ref = paper_intensity(rho, tau, cos, dist, power,
                                    model="pbr" if kind == "cooktorrance" else "lambertian")
        assert np.all(img[:, CH_HIT] == 1)
        errs_i.append(np.abs(img[:, CH_I] / model_ref - 1))
        errs_r.append(np.abs(img[:, CH_RANGE] - dist))
        assert np.allclose(img[:, CH_RHO], rho, atol=1e-6)
        count += len(cos)
    errs_i, errs_r = np.concatenate(errs_i), np.concatenate(errs_r)
    assert count >= 50
    assert errs_i.max() < 1e-4, errs_i.max()
    assert errs_r.max() < 1e-4, errs_r.max()


def test_lambertian_model_drops_exactly_the_specular_term(tmp_path):
    rng = np.random.default_rng(3)
    R, p, d_local, cos, dist = random_plane_beams(rng, 24)
    rho, tau, power = 0.3, 0.35, 1.7
    bsdf = {"type": "cooktorrance", "lidar_albedo": rho, "roughness": tau}
    out = {}
    for model in ("pbr", "lambertian"):
        sc = scene(explicit_lidar(tmp_path, d_local, pose(R, p)), {"plane": plane(bsdf)},
                   laser=power, model=model)
        out[model] = render(sc)
    spec_ref = specular_pi(tau, cos) * power * cos / (np.pi * dist ** 2)
    diff = out["pbr"][:, CH_I] - out["lambertian"][:, CH_I]
    assert np.allclose(diff, spec_ref, rtol=1e-4, atol=0)
    assert np.allclose(out["lambertian"][:, CH_I], paper_intensity(rho, tau, cos, dist, power, "lambertian"),
                       rtol=1e-4)


def test_laser_power_is_used(tmp_path):
    rng = np.random.default_rng(4)
    R, p, d_local, cos, dist = random_plane_beams(rng, 8)
    bsdf = {"type": "cooktorrance", "lidar_albedo": 0.4, "roughness": 0.5}
    imgs = [render(scene(explicit_lidar(tmp_path, d_local, pose(R, p)), {"plane": plane(bsdf)},
                         laser=P)) for P in (1.0, 3.25)]
    assert np.allclose(imgs[1][:, CH_I], 3.25 * imgs[0][:, CH_I], rtol=1e-6)
    # Without a laser, the integrator's own 'power' parameter is P_e.
    no_laser = render(scene(explicit_lidar(tmp_path, d_local, pose(R, p)), {"plane": plane(bsdf)},
                            laser=None, power=3.25))
    assert np.allclose(no_laser[:, CH_I], imgs[1][:, CH_I], rtol=1e-6)


def test_sensor_response_parameters(tmp_path):
    # A spinning grid sensor: rows are beams, so each row gets its own gain.
    elev = np.array([-20.0, -35.0, -60.0])
    W, h, power = 12, 2.0, 3.0
    a, b, gains = 2.0, 0.5, np.array([0.5, 1.5, 2.0])
    sensor = {"type": "lidar", "elevations": ",".join("%g" % e for e in elev), "far_clip": 1000.0,
              "to_world": mi.ScalarTransform4f().translate([0, 0, h]),
              "film": {"type": "hdrfilm", "width": W, "height": len(elev), "rfilter": {"type": "box"}}}
    rho, tau = 0.25, 0.6
    bsdf = {"type": "cooktorrance", "lidar_albedo": rho, "roughness": tau}
    img = np.array(mi.render(scene(sensor, {"plane": plane(bsdf)}, laser=power, range_exponent=b,
                                   angle_exponent=a, beam_gains="0.5, 1.5, 2.0")))
    # Documented beam geometry: elevation e, azimuth phi = pi (1 - 2 (col + 0.5) / W).
    cos = np.repeat(np.sin(-np.deg2rad(elev))[:, None], W, 1)
    dist = h / cos
    ref = paper_intensity(rho, tau, cos, dist, power, a=a, b=b, gain=gains[:, None])
    assert np.allclose(img[..., CH_I], ref, rtol=1e-4)
    assert np.allclose(img[..., CH_RANGE], dist, atol=1e-4)
    # A single gain applies to every beam.
    img1 = np.array(mi.render(scene(sensor, {"plane": plane(bsdf)}, laser=power, beam_gains="1.5")))
    assert np.allclose(img1[..., CH_I], paper_intensity(rho, tau, cos, dist, power) * 1.5, rtol=1e-4)


# ------------------------------------------- Gaussian layer vs the mesh plane

def flat_layer(rho, tau, spacing=0.1, half=2.5, flat=0.1, opacity=1.0, z=0.0, gid="layer"):
    """A grid of flat Gaussians on z = const, carrying LiDAR albedo rho and roughness tau.

    flat = thickness / width. It is 0.1, not 1e-3: Mitsuba 3.9.1's ellipsoid
    intersector loses precision for very flat Gaussians (with 1e-3 about 18 %
    of beams through such a layer found no entry at all, and reported entries
    were up to 1.4 m early); from about 0.05 on, no beam is lost.
    """
    xs = np.arange(-half, half + 1e-6, spacing)
    X, Y = np.meshgrid(xs, xs)
    n = X.size
    c = np.stack([X.ravel(), Y.ravel(), np.full(n, z)], 1).astype(np.float32)
    return {"type": "gaussians", "id": gid, "centers": mi.TensorXf(c),
            "scales": mi.TensorXf(np.tile(np.float32([spacing, spacing, spacing * flat]), (n, 1))),
            "opacities": mi.TensorXf(np.full(n, opacity, np.float32)),
            "lidar_albedo": mi.TensorXf(np.full(n, rho, np.float32)),
            "roughness": mi.TensorXf(np.full(n, tau, np.float32))}


def layer_beams(n, h, max_theta_deg=45.0, seed=5):
    rng = np.random.default_rng(seed)
    theta = np.deg2rad(rng.uniform(0, max_theta_deg, n))
    phi = rng.uniform(0, 2 * np.pi, n)
    d = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), -np.cos(theta)], 1)
    return d, np.cos(theta), h / np.cos(theta)


def test_dense_gaussian_layer_matches_mesh_plane(tmp_path):
    rho, tau, h, power = 0.3, 0.4, 1.5, 2.0
    # Oblique beams and near-normal ones: at normal incidence many flat
    # Gaussians of the layer are entered within a millimetre of each other,
    # which the traversal must neither reorder nor skip.
    beams = [layer_beams(64, h), layer_beams(1000, h, max_theta_deg=5.0, seed=11)]
    d, cos, dist = (np.concatenate(x) for x in zip(*beams))
    sensor = explicit_lidar(tmp_path, d, mi.ScalarTransform4f().translate([0, 0, h]))
    g = render(scene(sensor, {"layer": flat_layer(rho, tau)}, laser=power))
    m = render(scene(sensor, {"plane": plane({"type": "cooktorrance", "lidar_albedo": rho,
                                              "roughness": tau})}, laser=power))
    ref = paper_intensity(rho, tau, cos, dist, power)
    assert np.allclose(m[:, CH_I], ref, rtol=1e-4)
    assert np.all(g[:, CH_HIT] == 1)
    rel = np.abs(g[:, CH_I] / m[:, CH_I] - 1)
    drange = np.abs(g[:, CH_RANGE] - m[:, CH_RANGE])
    # Measured (64 beams up to 45 deg, 1000 up to 5 deg; LLVM): mean rel.
    # intensity error 7e-4 (the layer is always the darker one), max 3.8e-3;
    # range error 0.8 mm. A traversal that records the intersector's far hits
    # as they come lost the strongest Gaussian of some near-normal beams here
    # (max 4.9e-2; on an H100 machine 2.7e-2 with 64 + 64 beams, both backends).
    # Asserted with a margin: mean < 0.5 %, max < 1 %, range < 2 mm. The residual is (1) the transmittance
    # left behind the layer: each hit's alpha is clamped to 0.99 and
    # traversal stops below min_transmittance = 1e-3, so the weights sum to
    # 1 - T with T up to ~1e-3; intensity is not renormalised by alpha (range
    # is); (2) the layer's thickness: each Gaussian's response peaks where
    # the beam passes closest to its centre in the Gaussian's own metric,
    # a little off z = 0 for oblique beams through off-centre Gaussians.
    assert rel.mean() < 0.005 and rel.max() < 0.01, (rel.mean(), rel.max())
    assert drange.max() < 0.002, drange.max()
    assert np.all(g[:, CH_ALPHA] > 0.99)
    assert np.allclose(g[:, CH_RHO], rho, atol=1e-4)


# ---------------------------------------------------------------- stability

def test_grazing_beams_stay_finite_and_exact(tmp_path):
    h = 0.01
    theta = np.deg2rad(np.array([85.0, 89.0, 89.9, 89.99]))
    d = np.stack([np.sin(theta), np.zeros_like(theta), -np.cos(theta)], 1)
    sensor = explicit_lidar(tmp_path, d, mi.ScalarTransform4f().translate([0, 0, h]), near=0.0, far=1e5)
    for tau in (0.0, 0.3, 1.0):
        img = render(scene(sensor, {"plane": plane({"type": "cooktorrance", "lidar_albedo": 0.3,
                                                    "roughness": tau}, size=1e3)}, laser=1.0))
        assert np.all(np.isfinite(img))
        dw = d.astype(np.float32).astype(np.float64)
        dw /= np.linalg.norm(dw, axis=1, keepdims=True)
        cos = -dw[:, 2]
        ref = paper_intensity(0.3, tau, cos, h / cos, 1.0)
        # Grazing intersections lose float32 precision (cos ~ 1.7e-4 at 89.99
        # deg): looser tolerance than at moderate angles.
        assert np.allclose(img[:, CH_I], ref, rtol=2e-3), (img[:, CH_I], ref)


@pytest.mark.parametrize("tau", [0.0, 1e-4, 1e-3, 1.0])
def test_roughness_extremes(tmp_path, tau):
    rng = np.random.default_rng(6)
    R, p, d_local, cos, dist = random_plane_beams(rng, 16)
    d_local[0] = R.T @ np.array([0.0, 0.0, -1.0])  # normal incidence: the smooth peak
    cos[0], dist[0] = 1.0, p[2]
    sc = scene(explicit_lidar(tmp_path, d_local, pose(R, p)),
               {"plane": plane({"type": "cooktorrance", "lidar_albedo": 0.2, "roughness": tau})}, laser=1.0)
    img = render(sc)
    assert np.all(np.isfinite(img))
    ref = paper_intensity(0.2, tau, cos, dist, 1.0)  # tau < 1e-3 is clamped to 1e-3 (documented)
    # Near normal incidence a smooth lobe turns float32 rounding of cos^2
    # into a large relative change: d ln D / d cos^2 = 2 (1 - a^2) / (1 - cos^2 (1 - a^2)),
    # 1.3e4 for the beam at cos = 0.99992 with a = 1e-3, so one ulp of cos^2
    # (1.2e-7) moves it by 1.5e-3 (measured on CUDA: 1.03e-3). Each beam's
    # tolerance is 1e-3 plus four ulps of cos^2 through that sensitivity.
    a2 = max(tau, 1e-3) ** 2
    sens = 2 * (1 - a2) / (1 - cos ** 2 * (1 - a2))
    rtol = 1e-3 + 4 * np.finfo(np.float32).eps * sens
    assert np.all(np.abs(img[1:, CH_I] / ref[1:] - 1) <= rtol[1:]), \
        (np.abs(img[1:, CH_I] / ref[1:] - 1) / rtol[1:]).max()
    # At normal incidence a smooth lobe is so sharp that float32 rounding of
    # the beam direction (sin^2 ~ 1e-7 vs alpha^2 = 1e-6) moves the value:
    # require a finite return below the exact peak, and exactness for rough tau.
    assert 0 < img[0, CH_I] <= ref[0] * (1 + 1e-4)
    if tau >= 0.1:
        assert np.isclose(img[0, CH_I], ref[0], rtol=1e-4)


@pytest.mark.parametrize("surface", ["mesh", "gaussians"])
def test_surface_inside_near_clip_gives_no_return(tmp_path, surface):
    d, _, _ = layer_beams(16, 0.3, max_theta_deg=20)
    sensor = explicit_lidar(tmp_path, d, mi.ScalarTransform4f().translate([0, 0, 0.3]), near=0.5)
    shape = ({"plane": plane({"type": "cooktorrance"})} if surface == "mesh"
             else {"layer": flat_layer(0.3, 0.4, half=1.0)})
    img = render(scene(sensor, shape, laser=1.0))
    assert np.all(np.isfinite(img)) and np.all(img == 0)
    # Without a minimum range a surface 1 mm away still gives a finite return.
    sensor = explicit_lidar(tmp_path, d, mi.ScalarTransform4f().translate([0, 0, 1e-3]), near=0.0)
    img = render(scene(sensor, {"plane": plane({"type": "cooktorrance"})}, laser=1.0))
    assert np.all(np.isfinite(img)) and np.all(img[:, CH_HIT] == 1)


def test_empty_scene_returns_nothing(tmp_path):
    d, _, _ = layer_beams(32, 1.0, max_theta_deg=90)
    img = render(scene(explicit_lidar(tmp_path, d), {}, laser=1.0))
    assert np.all(np.isfinite(img)) and np.all(img == 0)


def test_zero_opacity_layer_returns_nothing_and_reveals_mesh(tmp_path):
    h = 1.5
    d, cos, dist = layer_beams(16, h)
    sensor = explicit_lidar(tmp_path, d, mi.ScalarTransform4f().translate([0, 0, h]))
    img = render(scene(sensor, {"layer": flat_layer(0.3, 0.4, opacity=0.0, half=2.0)}, laser=1.0))
    assert np.all(img == 0)
    # The same invisible layer 0.5 m above a mesh: the mesh's return, unchanged.
    bsdf = {"type": "cooktorrance", "lidar_albedo": 0.5, "roughness": 0.2}
    img = render(scene(sensor, {"layer": flat_layer(0.3, 0.4, opacity=0.0, half=2.0, z=0.5),
                                "plane": plane(bsdf)}, laser=1.0))
    assert np.allclose(img[:, CH_I], paper_intensity(0.5, 0.2, cos, dist, 1.0), rtol=1e-4)


def test_nan_gaussian_parameter_is_refused():
    layer = flat_layer(0.3, 0.4, half=0.2)
    r = np.array(layer["roughness"])
    r[3] = np.nan
    layer["roughness"] = mi.TensorXf(r)
    with pytest.raises(Exception, match="roughness"):
        mi.load_dict({"type": "scene", "layer": layer})


# ---------------------------------------------------------------- gradients

def grad_of(sc, keys):
    """Gradients of sum(intensity) w.r.t. params[keys] via mi.render(scene, params)."""
    params = mi.traverse(sc)
    for k in keys:
        dr.enable_grad(params[k])
    params.update()
    img = mi.render(sc, params)
    dr.backward(dr.sum(img[..., CH_I], axis=None))
    return {k: np.array(dr.grad(params[k])) for k in keys}


@pytest.mark.parametrize("case", ["moderate", "grazing", "smooth"])
def test_gradients_are_finite(tmp_path, case):
    max_theta, tau = {"moderate": (45, 0.4), "grazing": (89.9, 0.4), "smooth": (45, 0.0)}[case]
    h = 1.0
    theta = np.deg2rad(np.linspace(0, max_theta, 16))
    d = np.stack([np.sin(theta), np.zeros_like(theta), -np.cos(theta)], 1)
    sensor = explicit_lidar(tmp_path, d, mi.ScalarTransform4f().translate([0.013, 0.021, h]),
                            near=0.1, far=1e4)
    # Gaussian layer (half opaque, so opacity matters) above a mesh plane.
    sc = scene(sensor, {"layer": flat_layer(0.3, tau, opacity=0.5, z=0.2, half=3.0),
                        "plane": plane({"type": "cooktorrance", "lidar_albedo": 0.4, "roughness": tau})},
               laser=1.0)
    keys = ["layer.lidar_albedo", "layer.roughness", "layer.opacities", "layer.data",
            "plane.bsdf.lidar_albedo", "plane.bsdf.roughness"]
    grads = grad_of(sc, keys)
    for k, g in grads.items():
        assert np.all(np.isfinite(g)), k
        if not k.endswith("roughness") or tau > 0:  # the clamp zeroes d/dtau at tau = 0
            assert np.any(g != 0), k


def fd_check(tmp_path, key, step, rel_tol, opacity=1.0, tau=0.4, select=None):
    """Total derivative of sum(intensity) for a uniform change of params[key]
    (optionally only the components `select` picks), AD vs central differences."""
    h = 1.2
    d, _, _ = layer_beams(48, h, max_theta_deg=40, seed=8)
    sensor = explicit_lidar(tmp_path, d, mi.ScalarTransform4f().translate([0, 0, h]))
    shapes = {"layer": flat_layer(0.3, tau, opacity=opacity, half=2.0)}
    if opacity < 1:  # something behind a semi-transparent layer
        shapes["plane"] = plane({"type": "cooktorrance", "lidar_albedo": 0.6, "roughness": 0.3})
        shapes["plane"]["to_world"] = mi.ScalarTransform4f().translate([0, 0, -0.5]).scale(1e4)
    sc = scene(sensor, shapes, laser=1.0)
    params = mi.traverse(sc)
    x0 = np.array(params[key]).ravel()
    mask = np.ones_like(x0, bool) if select is None else select(x0)

    def primal(delta):
        params[key] = type(params[key])(np.where(mask, x0 + delta, x0).astype(np.float32).reshape(
            np.array(params[key]).shape))
        params.update()
        return float(np.sum(np.array(mi.render(sc))[..., CH_I], dtype=np.float64))

    fd = (primal(step) - primal(-step)) / (2 * step)
    primal(0.0)
    g = grad_of(sc, [key])[key].ravel()
    ad = float(np.sum(g[mask], dtype=np.float64))
    assert np.isfinite(ad) and abs(fd) > 0
    assert abs(ad / fd - 1) < rel_tol, (key, ad, fd)
    return ad, fd


def test_fd_lidar_albedo(tmp_path):
    # Intensity is linear in rho: the central difference is exact up to rounding.
    fd_check(tmp_path, "layer.lidar_albedo", 0.05, 0.01)


def test_fd_roughness(tmp_path):
    fd_check(tmp_path, "layer.roughness", 0.01, 0.03)


def test_fd_opacity(tmp_path):
    # Below the 0.99 alpha clamp (opacity 0.3), over a mesh plane 0.5 m below.
    fd_check(tmp_path, "layer.opacities", 0.01, 0.03, opacity=0.3)


def test_fd_centre_height(tmp_path):
    # Moving every centre up by dz brings the layer closer: d(1/d^2)/dz.
    n10 = np.arange(10)

    def z_entries(x):
        return np.tile(n10 == 2, x.size // 10)
    fd_check(tmp_path, "layer.data", 2e-3, 0.03, select=z_entries)


# ----------------------------------------------------------- example scenes

def test_example_scene_lidar_gaussians(scenes_dir):
    if not (scenes_dir / "gaussians_plane.ply").exists():
        pytest.skip("run scenes/make_examples.py first")
    img = np.array(mi.render(mi.load_file(str(scenes_dir / "lidar_gaussians.xml"))))
    assert img.shape == (8, 900, 5) and np.all(np.isfinite(img))
    # The -35 degree beam, 1.2 m up, meets the Gaussian ground at 1.2 / sin 35
    # everywhere (except where the box stands in the way).
    bottom = img[-1]
    assert np.all(bottom[:, CH_HIT] == 1)
    expected = 1.2 / np.sin(np.deg2rad(35.0))
    assert np.median(np.abs(bottom[:, CH_RANGE] - expected)) < 0.01
    assert np.isclose(np.median(bottom[:, CH_RHO]), 0.3, atol=0.01)
