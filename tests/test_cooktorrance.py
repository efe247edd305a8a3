"""Tests of the ``cooktorrance`` BSDF: sampling, the paper's LiDAR equation
reproduced by Mitsuba's own ``path`` integrator, physics and hard cases."""

import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

F0 = 0.04


def make_bsdf(albedo=0.5, roughness=0.5, **extra):
    albedo = albedo if isinstance(albedo, dict) else {"type": "rgb", "value": [albedo] * 3}
    return mi.load_dict({"type": "cooktorrance", "albedo": albedo,
                         "roughness": roughness, **extra})


def direction(theta_deg, phi_deg=0.0):
    t, p = np.radians(theta_deg), np.radians(phi_deg)
    return np.array([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)])


def interaction(wi, n=None):
    """SurfaceInteraction3f with local ``wi`` (one direction, or a (3, N) array)."""
    wi = np.asarray(wi, dtype=np.float64)
    if wi.ndim == 1:
        wi = np.repeat(wi[:, None], n or 1, axis=1)
    si = dr.zeros(mi.SurfaceInteraction3f, wi.shape[1])
    si.wi = mi.Vector3f(wi)
    si.uv = mi.Point2f(0.5, 0.5)
    return si


def paper_intensity(rho, tau, cos_t, d, power):
    """The paper's LiDAR equation, written out independently of brdf.py."""
    c2 = cos_t ** 2
    spec = F0 * tau ** 2 * np.minimum(1.0, 2.0 * c2) / (4.0 * c2 * (c2 * (tau ** 2 - 1.0) + 1.0) ** 2)
    return (rho + spec) * power * cos_t / (np.pi * d ** 2)


# --------------------------------------------------------------------- sampling

@pytest.mark.parametrize("roughness, albedo, theta", [
    (0.05, 0.5, 30.0), (0.05, 0.05, 70.0), (0.3, 0.8, 0.0), (0.3, 0.0, 80.0),
    (1.0, 0.5, 60.0), (1.0, 0.0, 10.0)])
def test_chi2_sampling_matches_pdf(roughness, albedo, theta):
    wi = mi.Vector3f(*[float(x) for x in direction(theta, 20.0)])
    sample, pdf = mi.chi2.BSDFAdapter("cooktorrance", {
        "type": "cooktorrance", "roughness": roughness,
        "albedo": {"type": "rgb", "value": [albedo] * 3}}, wi=wi)
    chi2 = mi.chi2.ChiSquareTest(domain=mi.chi2.SphericalDomain(), sample_func=sample,
                                 pdf_func=pdf, sample_dim=3, res=101, ires=16)
    assert chi2.run(), chi2.messages


def test_sample_weight_is_eval_over_pdf_and_components():
    bsdf = make_bsdf(albedo=0.4, roughness=0.2)
    n = 4096
    rng = np.random.default_rng(1)
    si = interaction(direction(45.0), n)
    ctx = mi.BSDFContext()
    bs, weight = bsdf.sample(ctx, si, mi.Float(rng.random(n)), mi.Point2f(rng.random((2, n))))
    value, pdf = bsdf.eval_pdf(ctx, si, bs.wo)
    ok = bs.pdf > 0
    assert dr.all((dr.abs(pdf - bs.pdf) <= 1e-5 * dr.maximum(pdf, 1.0)) | ~ok)
    assert dr.all(dr.abs(pdf - bsdf.pdf(ctx, si, bs.wo)) <= 1e-6 * dr.maximum(pdf, 1.0))
    assert dr.all(dr.abs(value - bsdf.eval(ctx, si, bs.wo)) <= 1e-6, axis=None)
    expected = dr.select(ok, value / dr.maximum(pdf, 1e-20), 0.0)
    assert dr.all(dr.abs(weight - expected) <= 1e-4 * dr.maximum(expected, 1.0), axis=None)
    # Both lobes are actually used, and the labels say which one was sampled.
    comp = np.array(bs.sampled_component)[np.array(ok)]
    assert 0.05 < comp.mean() < 0.95
    glossy = np.array(bs.sampled_type)[np.array(ok)] == int(mi.BSDFFlags.GlossyReflection)
    assert np.array_equal(glossy, comp == 1)


# ------------------------------------------------- co-located (LiDAR) reproduction

TAUS = (0.005, 0.02, 0.05, 0.2, 0.5, 1.0)
RHOS = (0.0, 0.3, 1.0)
THETAS = tuple(np.linspace(0.0, 89.0, 12))


@pytest.fixture(scope="module")
def colocated_scene():
    """Many small tilted planes around a point light at the origin.

    Plane k sits at distance d_k in a Fibonacci direction u_k, its normal
    tilted by theta_k away from -u_k, so a ray from the light to its centre
    arrives at exactly theta_k. Planes are small enough that none shadows
    another. One BSDF per (tau, rho) pair, shared by all angles.
    """
    power = 2.5
    scene = {"type": "scene",
             "light": {"type": "point", "position": [0.0, 0.0, 0.0],
                       "intensity": {"type": "rgb", "value": [power] * 3}}}
    for i, tau in enumerate(TAUS):
        for j, rho in enumerate(RHOS):
            scene["m%d_%d" % (i, j)] = {"type": "cooktorrance", "roughness": tau,
                                        "albedo": {"type": "rgb", "value": [rho] * 3}}
    cases = [(i, j, th) for i in range(len(TAUS)) for j in range(len(RHOS)) for th in THETAS]
    golden = math.pi * (3.0 - math.sqrt(5.0))
    rows = []
    for k, (i, j, theta) in enumerate(cases):
        z = 1.0 - 2.0 * (k + 0.5) / len(cases)
        u = np.array([math.sqrt(1 - z * z) * math.cos(golden * k),
                      math.sqrt(1 - z * z) * math.sin(golden * k), z])
        d = 2.0 + (k % 3) * 0.75
        tangent = np.cross(u, [0.3, 0.5, 0.8])
        tangent /= np.linalg.norm(tangent)
        normal = math.cos(math.radians(theta)) * -u + math.sin(math.radians(theta)) * tangent
        centre = d * u
        to_world = (mi.ScalarTransform4f().look_at(origin=centre, target=centre + normal,
                                                   up=tangent if theta < 1 else u)
                    @ mi.ScalarTransform4f().scale(0.08))
        scene["plane%d" % k] = {"type": "rectangle", "to_world": to_world,
                                "bsdf": {"type": "ref", "id": "m%d_%d" % (i, j)}}
        rows.append((TAUS[i], RHOS[j], theta, d, *u))
    return mi.load_dict(scene), np.array(rows), power


def test_colocated_path_integrator_reproduces_paper_equation(colocated_scene):
    scene, rows, power = colocated_scene
    tau, rho, theta, d, u = rows[:, 0], rows[:, 1], rows[:, 2], rows[:, 3], rows[:, 4:7].T
    ray = mi.Ray3f(mi.Point3f(0.0, 0.0, 0.0), mi.Vector3f(u))
    # Every ray must hit its own plane at the planned distance (no occlusion).
    si = scene.ray_intersect(ray)
    assert np.allclose(np.array(si.t), d, rtol=1e-5)
    integrator = mi.load_dict({"type": "path", "max_depth": 2})
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(0, len(d))
    radiance, valid, _ = integrator.sample(scene, sampler, ray)
    got = np.array(radiance)[0]
    expected = paper_intensity(rho, tau, np.cos(np.radians(theta)), d, power)
    rel = np.abs(got - expected) / expected.clip(1e-30)
    print("co-located: max relative error %.3g over %d (tau, rho, theta)" % (rel.max(), len(d)))
    assert np.all(np.array(valid))
    assert rel.max() <= 1e-3, rows[np.argmax(rel), :4]


@pytest.mark.parametrize("k", [0, 11, 25, 47, 215])
def test_colocated_camera_render(colocated_scene, k):
    """Same check through a real perspective camera, film and box filter."""
    scene, rows, power = colocated_scene
    tau, rho, theta, d = rows[k, :4]
    u = rows[k, 4:7]
    up = np.cross(u, [0.6, 0.0, 0.8])
    sensor = mi.load_dict({
        "type": "perspective", "fov": 1e-4,
        "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=u, up=up),
        "film": {"type": "hdrfilm", "width": 1, "height": 1, "rfilter": {"type": "box"}},
        "sampler": {"type": "independent", "sample_count": 4}})
    image = mi.render(scene, sensor=sensor, integrator=mi.load_dict({"type": "path", "max_depth": 2}))
    got = float(np.array(image).ravel()[0])
    expected = paper_intensity(rho, tau, math.cos(math.radians(theta)), d, power)
    assert abs(got - expected) <= 1e-3 * expected


# ---------------------------------------------------------------------- physics

def directional_albedo(bsdf, theta, n=200_000, seed=3):
    rng = np.random.default_rng(seed)
    si = interaction(direction(theta), n)
    _, weight = bsdf.sample(mi.BSDFContext(), si, mi.Float(rng.random(n)),
                            mi.Point2f(rng.random((2, n))))
    return np.array(weight).mean(axis=1)


@pytest.mark.parametrize("roughness", [0.05, 0.4, 1.0])
@pytest.mark.parametrize("theta", [0.0, 45.0, 75.0, 88.0])
def test_energy(roughness, theta):
    # The specular lobe alone, with a perfect mirror Fresnel (f0 = 1), may not
    # reflect more than it receives: this is what the V-cavity G guarantees.
    mirror = directional_albedo(make_bsdf(albedo=0.0, roughness=roughness, f0=1.0), theta)
    assert np.all(mirror <= 1.01), mirror
    # The paper's material adds the specular lobe to an undiminished diffuse
    # one, so a white albedo reflects 1 + (specular albedo): a few per cent
    # for rough surfaces away from grazing, more towards grazing where
    # Schlick's Fresnel rises.
    spec = directional_albedo(make_bsdf(albedo=0.0, roughness=roughness), theta)
    full = directional_albedo(make_bsdf(albedo=1.0, roughness=roughness), theta)
    assert np.allclose(full, 1.0 + spec, atol=0.01), (full, spec)
    if roughness >= 0.4 and theta <= 45.0:
        assert np.all(full <= 1.05), full


def test_below_horizon_and_reciprocity():
    bsdf = make_bsdf(albedo={"type": "rgb", "value": [0.2, 0.5, 0.8]}, roughness=0.3)
    rng = np.random.default_rng(7)
    n = 2000
    a = rng.normal(size=(3, n))
    b = rng.normal(size=(3, n))
    a /= np.linalg.norm(a, axis=0)
    b /= np.linalg.norm(b, axis=0)
    ctx = mi.BSDFContext()
    f_ab = np.array(bsdf.eval(ctx, interaction(a), mi.Vector3f(b)))
    f_ba = np.array(bsdf.eval(ctx, interaction(b), mi.Vector3f(a)))
    below = (a[2] <= 0) | (b[2] <= 0)
    assert np.all(f_ab[:, below] == 0) and np.all(f_ba[:, below] == 0)
    assert np.all(np.array(bsdf.pdf(ctx, interaction(a), mi.Vector3f(b)))[below] == 0)
    assert np.all(f_ab[:, ~below] > 0)
    # eval includes cos(theta_o): reciprocity holds for f = eval / cos_o.
    assert np.allclose(f_ab[:, ~below] / b[2, ~below], f_ba[:, ~below] / a[2, ~below], rtol=1e-4)


def test_ggx_alpha_convention_matches_mitsuba():
    """D is GGX with alpha = tau (not tau^2): compare with Mitsuba's GGX."""
    tau = 0.3
    bsdf = make_bsdf(albedo=0.0, roughness=tau, f0=1.0)
    theta = np.linspace(0.0, 80.0, 9)
    w = np.stack([direction(t) for t in theta], axis=1)
    # Co-located, F = 1 and G / (4 cos^2) = min(1/(4 cos^2), 1/2): isolate D.
    f = np.array(bsdf.eval(mi.BSDFContext(), interaction(w), mi.Vector3f(w)))[0] / w[2]
    g_over = np.minimum(1.0 / (4.0 * w[2] ** 2), 0.5)
    d_ref = np.array(mi.MicrofacetDistribution(mi.MicrofacetType.GGX, tau).eval(mi.Vector3f(w)))
    assert np.allclose(f / g_over, d_ref, rtol=1e-4)


def test_smooth_peak_is_accurate_in_float32():
    """Near the peak of a very smooth lobe, 1 - cos^2 cancels to rounding
    noise comparable to alpha^2; D must use sin^2 of the half-vector."""
    rng = np.random.default_rng(0)
    v = np.stack([rng.normal(size=512) * 1e-5, rng.normal(size=512) * 1e-5, np.ones(512)])
    v /= np.linalg.norm(v, axis=0)
    w = dr.normalize(mi.Vector3f(v.astype(np.float32)))
    for tau in (0.001, 0.005):
        bsdf = make_bsdf(albedo=0.0, roughness=tau)
        got = np.array(bsdf.eval(mi.BSDFContext(), interaction(v), w))[0]
        c = v[2]
        expected = paper_intensity(0.0, tau, c, 1.0, np.pi) / np.pi  # f_s cos
        assert np.allclose(got, expected, rtol=1e-4), tau


# --------------------------------------------------------------------- hard cases

def hard_directions():
    c = np.array([1e-7, 1e-4, 0.3, 1.0])
    dirs = [np.array([np.sqrt(1 - x * x), 0.0, x]) for x in c]
    dirs.append(np.array([0.0, 1.0, 0.0]))   # exactly tangent
    dirs.append(np.array([0.0, 0.6, -0.8]))  # below the surface
    return dirs


@pytest.mark.parametrize("roughness", [0.0, 1e-4, 0.05, 1.0])
def test_finite_everywhere(roughness):
    dirs = hard_directions()
    pairs = [(a, b) for a in dirs for b in dirs]
    wi = np.stack([p[0] for p in pairs], axis=1)
    wo = np.stack([p[1] for p in pairs], axis=1)
    n = wi.shape[1]
    albedo = mi.Color3f(0.5)
    rough = mi.Float(roughness)
    dr.enable_grad(albedo, rough)
    bsdf = make_bsdf(albedo=0.5, roughness=roughness)
    bsdf.albedo, bsdf.roughness = albedo, rough   # make the parameters differentiable
    ctx = mi.BSDFContext()
    si = interaction(wi)
    value, pdf = bsdf.eval_pdf(ctx, si, mi.Vector3f(wo))
    assert dr.all(dr.isfinite(value), axis=None) and dr.all(dr.isfinite(pdf))
    assert dr.all(value >= 0, axis=None) and dr.all(pdf >= 0)
    dr.backward(dr.sum(value, axis=None))
    assert dr.all(dr.isfinite(dr.grad(albedo)), axis=None)
    assert dr.all(dr.isfinite(dr.grad(rough)))
    rng = np.random.default_rng(5)
    for s in range(4):
        bs, weight = bsdf.sample(ctx, si, mi.Float(rng.random(n)), mi.Point2f(rng.random((2, n))))
        assert dr.all(dr.isfinite(weight), axis=None) and dr.all(dr.isfinite(bs.pdf))
        assert dr.all(dr.isfinite(bs.wo), axis=None)


@pytest.mark.parametrize("theta_i, theta_o, phi", [
    (0.0, 0.0, 0.0), (30.0, 40.0, 180.0), (60.0, 10.0, 90.0), (89.9, 89.9, 180.0)])
@pytest.mark.parametrize("roughness", [0.05, 0.3, 0.9])
def test_roughness_gradient_matches_finite_differences(theta_i, theta_o, phi, roughness):
    wi, wo = direction(theta_i), direction(theta_o, phi)
    ctx = mi.BSDFContext()

    def value(r):
        bsdf = make_bsdf(albedo=0.25, roughness=0.5)
        bsdf.roughness = r
        return bsdf.eval(ctx, interaction(wi), mi.Vector3f(wo)).x

    r = mi.Float(roughness)
    dr.enable_grad(r)
    v = value(r)
    dr.backward(v)
    grad = dr.grad(r)[0]
    h = 1e-3 * roughness
    fd = (value(mi.Float(roughness + h))[0] - value(mi.Float(roughness - h))[0]) / (2 * h)
    assert math.isfinite(grad)
    assert abs(grad - fd) <= 2e-2 * abs(fd) + 1e-5, (grad, fd)


# ------------------------------------------------------- integration with Mitsuba

def test_attributes_reachable_from_surface_interaction():
    scene = mi.load_dict({
        "type": "scene",
        "a": {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([-2, 0, 0]),
              "bsdf": {"type": "cooktorrance", "albedo": {"type": "rgb", "value": [0.1, 0.2, 0.3]},
                       "roughness": 0.3, "lidar_albedo": 0.7}},
        "b": {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([2, 0, 0]),
              "bsdf": {"type": "diffuse"}}})
    ray = mi.Ray3f(mi.Point3f([-2, 2], [0, 0], [1, 1]), mi.Vector3f(0, 0, -1))
    si = scene.ray_intersect(ray)
    bsdfs = si.bsdf()
    # Mitsuba dispatches these through its C++ BSDF interface to the Python overrides.
    assert np.array_equal(np.array(bsdfs.has_attribute("lidar_albedo")), [True, False])
    assert np.allclose(np.array(bsdfs.eval_attribute_1("lidar_albedo", si)), [0.7, 0.0])
    assert np.allclose(np.array(bsdfs.eval_attribute_1("roughness", si)), [0.3, 0.0])
    assert np.allclose(np.array(bsdfs.eval_attribute_3("albedo", si))[:, 0], [0.1, 0.2, 0.3])
    # The Python object itself (and its material()) is reachable per lane.
    albedo, rough, lidar = bsdfs[0].material(si)
    assert np.allclose(np.array(lidar), 0.7) and np.allclose(np.array(rough), 0.3)


def test_traverse_update_and_texture(scenes_dir):
    scene = mi.load_file(str(scenes_dir / "cooktorrance_sphere.xml"), spp=4, res=16)
    params = mi.traverse(scene)
    for key in ("albedo", "roughness", "lidar_albedo", "f0"):
        assert "sphere.bsdf." + key in params
    assert "ground.bsdf.albedo.color0.value" in params
    image = np.array(mi.render(scene))
    assert np.all(np.isfinite(image)) and image.mean() > 0
    params["sphere.bsdf.roughness"] = 0.9
    params.update()
    bsdf = [s for s in scene.shapes() if s.id() == "sphere"][0].bsdf()
    assert np.allclose(np.array(bsdf.material(dr.zeros(mi.SurfaceInteraction3f))[1]), 0.9)


def test_components_split_the_lobes():
    bsdf = make_bsdf(albedo=0.4, roughness=0.3)
    assert bsdf.flags() & mi.BSDFFlags.DiffuseReflection
    assert bsdf.flags() & mi.BSDFFlags.GlossyReflection
    assert not bsdf.flags() & (mi.BSDFFlags.DiffuseTransmission | mi.BSDFFlags.BackSide)
    si = interaction(direction(35.0), 64)
    wo = mi.Vector3f(mi.warp.square_to_uniform_hemisphere(mi.Point2f(
        np.random.default_rng(2).random((2, 64)))))
    total = bsdf.eval(mi.BSDFContext(), si, wo)
    parts = []
    for component in (0, 1):
        ctx = mi.BSDFContext()
        ctx.component = component
        parts.append(bsdf.eval(ctx, si, wo))
        bs, _ = bsdf.sample(ctx, si, mi.Float(0.5), mi.Point2f(0.3, 0.6))
        assert dr.all(bs.sampled_component == component)
    assert dr.allclose(parts[0] + parts[1], total)


def test_prb_gradients_through_the_material(scenes_dir):
    scene = mi.load_file(str(scenes_dir / "cooktorrance_sphere.xml"), spp=4, res=16)
    params = mi.traverse(scene)
    keys = ["sphere.bsdf.albedo", "sphere.bsdf.roughness", "sphere.bsdf.f0",
            "ground.bsdf.albedo.color0.value"]
    for key in keys:
        dr.enable_grad(params[key])
    params.update()
    image = mi.render(scene, params, integrator=mi.load_dict({"type": "prb", "max_depth": 3}))
    dr.backward(dr.mean(image, axis=None))
    for key in keys:
        grad = np.array(dr.grad(params[key]))
        assert np.all(np.isfinite(grad)) and np.any(grad != 0), key
    # A brighter albedo and a stronger Fresnel both brighten the image.
    assert np.all(np.array(dr.grad(params["sphere.bsdf.albedo"])) > 0)
    assert np.array(dr.grad(params["sphere.bsdf.f0"]))[0] > 0
