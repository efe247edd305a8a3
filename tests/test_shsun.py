"""Tests of the ``shsun`` emitter (SH sky + sun) and the SH helpers."""

import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_invrgbl.physics import sh as shm

# A fairly busy order-3 sky (kept positive by its large constant term), as a flat
# coefficient-major list; and the same with negative lobes that need clamping.
SKY3 = np.array([[3.0, 3.2, 3.6], [0.2, 0.1, -0.1], [1.2, 1.3, 1.6], [-0.3, 0.2, 0.1],
                 [0.2, -0.1, 0.1], [0.1, 0.2, 0.0], [0.4, 0.3, 0.5], [0.0, -0.2, 0.1],
                 [0.3, 0.1, -0.2], [0.1, 0.0, 0.1], [-0.1, 0.1, 0.0], [0.0, 0.1, 0.1],
                 [0.2, 0.2, 0.3], [0.1, -0.1, 0.0], [0.0, 0.1, -0.1], [0.1, 0.0, 0.1]])
SKY3_NEG = SKY3 * np.array([[0.2]] + [[3.0]] * 15)


def sh_string(coeffs):
    return " ".join("%.9g" % v for v in np.asarray(coeffs).ravel())


def shsun(**kw):
    d = {"type": "shsun"}
    d.update(kw)
    return d


def random_dirs(n, seed=0):
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def vec(d):
    return mi.Vector3f(np.asarray(d, np.float32).T)


def scene_dict(emitter, integrator="path", max_depth=3, bsdf=None):
    """A diffuse sphere on a ground square under ``emitter`` (tiny film)."""
    return {
        "type": "scene",
        "integrator": {"type": integrator, "max_depth": max_depth} if integrator != "direct"
        else {"type": "direct"},
        "sensor": {
            "type": "perspective", "fov": 50,
            "to_world": mi.ScalarTransform4f().look_at(origin=[0, -6, 2.5], target=[0, 0, 0.4],
                                                       up=[0, 0, 1]),
            "film": {"type": "hdrfilm", "width": 16, "height": 16, "pixel_format": "rgb"},
            "sampler": {"type": "independent"},
        },
        "sphere": {"type": "sphere", "center": [0, 0, 1], "radius": 1,
                   "bsdf": bsdf or {"type": "diffuse", "reflectance": {"type": "rgb",
                                                                     "value": [0.7, 0.5, 0.3]}}},
        "ground": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale([4, 4, 1]),
                   "bsdf": {"type": "diffuse", "reflectance": 0.5}},
        "light": emitter,
    }


def render_mean(emitter, spp, seed=0, **kw):
    scene = mi.load_dict(scene_dict(emitter, **kw))
    img = np.asarray(mi.render(scene, spp=spp, seed=seed), np.float64)
    assert np.all(np.isfinite(img))
    return img.mean(axis=(0, 1)), img


# ------------------------------------------------------------------ loading


def test_loads_as_environment(variant):
    scene = mi.load_dict(scene_dict(shsun(sun_irradiance=2.0)))
    env = scene.environment()
    assert env is not None and env.is_environment()
    assert mi.has_flag(env.flags(), mi.EmitterFlags.Infinite)
    assert not mi.has_flag(env.flags(), mi.EmitterFlags.Delta)
    assert env in scene.emitters()
    assert set(mi.traverse(env).keys()) >= {"sh", "sun_direction", "sun_irradiance"}


def test_default_is_uniform_grey_sky_of_radiance_one(variant):
    e = mi.load_dict(shsun())
    assert e.order == 0 and not e.has_sun()
    L = np.asarray(e.sky_radiance(vec(random_dirs(64))))
    assert np.allclose(L, 1.0, atol=1e-6)


def test_xml_parameters_and_accessors(variant):
    e = mi.load_string("""
        <emitter version="3.0.0" type="shsun">
            <string name="sh" value="1, 2, 3,  0.1 0.2 0.3,  0 0 0,  -0.1 0 0.1"/>
            <vector name="sun_direction" x="0" y="3" z="4"/>
            <rgb name="sun_irradiance" value="5, 6, 7"/>
            <float name="sun_radius" value="2"/>
        </emitter>""")
    assert e.order == 1 and e.has_sun()
    assert np.allclose(np.asarray(e.sun_direction_world()).ravel(), [0, 0.6, 0.8], atol=1e-6)
    assert np.allclose(np.asarray(e.sun_irradiance_value()).ravel(), [5, 6, 7])
    assert e.sun_radius() == 2.0
    assert np.allclose(e.sh_coefficients()[3], [-0.1, 0, 0.1])


def test_example_scene_renders(variant, scenes_dir):
    scene = mi.load_file(str(scenes_dir / "shsun_sky.xml"), resx=16, resy=12, spp=4)
    img = np.asarray(mi.render(scene))
    assert img.shape[:2] == (12, 16) and np.all(np.isfinite(img)) and img.mean() > 0
    assert scene.environment().has_sun()


# --------------------------------------------------- 1. order 0 == constant


@pytest.mark.parametrize("integrator", ["path", "direct"])
def test_order0_matches_constant(variant, integrator):
    rgb = np.array([0.5, 1.0, 2.0])
    ours, _ = render_mean(shsun(sh=sh_string(rgb / shm.Y0)), spp=256, integrator=integrator)
    ref, _ = render_mean({"type": "constant", "radiance": {"type": "rgb", "value": rgb.tolist()}},
                         spp=256, integrator=integrator)
    rel = np.abs(ours / ref - 1)
    print("order 0 vs constant (%s): relative differences %s" % (integrator, rel))
    assert np.all(rel < 0.01)


# ---------------------------------------------- 2. sun only == directional


@pytest.mark.parametrize("bsdf", ["diffuse", "roughplastic"])
def test_sun_only_matches_directional(variant, bsdf):
    sun = np.array([0.4, -0.5, 0.75])
    E = [3.0, 2.5, 2.0]
    b = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.7, 0.5, 0.3]}} \
        if bsdf == "diffuse" else {"type": "roughplastic", "alpha": 0.2,
                                   "diffuse_reflectance": {"type": "rgb", "value": [0.7, 0.5, 0.3]}}
    ours, img_o = render_mean(shsun(sh="0 0 0", sun_direction=sun.tolist(),
                                    sun_irradiance={"type": "rgb", "value": E}),
                              spp=64, max_depth=3, bsdf=b)
    ref, img_r = render_mean({"type": "directional", "direction": (-sun).tolist(),
                              "irradiance": {"type": "rgb", "value": E}},
                             spp=64, max_depth=3, bsdf=b)
    rel = np.abs(ours / ref - 1)
    print("sun vs directional (%s): relative differences %s" % (bsdf, rel))
    assert np.all(rel < 0.01)
    # Shadows too: the per-pixel images agree, not only their means.
    assert np.abs(img_o - img_r).mean() < 0.02 * img_r.mean()


# ------------------------------------------------------------- 3. chi²


@pytest.mark.parametrize("case", ["sky", "sky+sun", "clamped sky+sun"])
def test_chi2_sample_direction(variant, case):
    # The chi² grid (101 x 202 bins, ~1.8 degrees) cannot resolve the real 0.27
    # degree sun; a 5 degree sun exercises the same code with bins inside the disk.
    # Its reference integrates the pdf over each bin with ires² points: the default
    # 4² mis-integrates the disk's sharp rim (PDF sum 0.974), 16² gets it right.
    coeffs = SKY3_NEG if case.startswith("clamped") else SKY3
    kw = dict(sh=sh_string(coeffs))
    if "sun" in case:
        kw.update(sun_direction=[0.5, -0.3, 0.6], sun_irradiance=20.0, sun_radius=5.0)
    sample_func, pdf_func = mi.chi2.EmitterAdapter("shsun", shsun(**kw))
    chi2 = mi.chi2.ChiSquareTest(domain=mi.chi2.SphericalDomain(), sample_func=sample_func,
                                 pdf_func=pdf_func, sample_dim=2, sample_count=1000000,
                                 ires=16 if "sun" in case else 4)
    assert chi2.run(), chi2.messages


def test_sample_weight_is_radiance_over_pdf(variant):
    e = mi.load_dict(shsun(sh=sh_string(SKY3_NEG), sun_direction=[0, 0.6, 0.8],
                           sun_irradiance=10.0, sun_radius=1.0))
    n = 4096
    rng = np.random.default_rng(3)
    u = mi.Point2f(rng.random((2, n)).astype(np.float32))
    it = dr.zeros(mi.Interaction3f, n)
    ds, w = e.sample_direction(it, u)
    pdf = e.pdf_direction(it, ds)
    L = e.eval_direction(it, ds)
    assert np.allclose(np.asarray(ds.pdf), np.asarray(pdf), rtol=1e-5)
    ok = np.asarray(pdf) > 0
    assert ok.mean() > 0.999
    assert np.allclose(np.asarray(w)[:, ok], (np.asarray(L) / np.asarray(pdf))[:, ok], rtol=1e-4)
    # The estimator of the emitted power ∫ L dω is unbiased: sky by projection, sun
    # disk E / (π sin² r) · 2π (1 - cos r).
    r = math.radians(1.0)
    dirs, wq = shm.sphere_quadrature(64)
    sky = (np.maximum(0, shm.eval_sh_numpy(SKY3_NEG, dirs)) * wq[:, None]).sum(0)
    sun = 10.0 / (math.pi * math.sin(r) ** 2) * 2 * math.pi * (1 - math.cos(r))
    exact = sky + sun
    est = np.asarray(w, np.float64).mean(axis=1)
    assert np.allclose(est, exact, rtol=0.03), (est, exact)


# -------------------------------------------------------- 4. SH projection


def test_numpy_basis_matches_drjit(variant):
    d = random_dirs(200, seed=1)
    ours = shm.sh_basis_numpy(d, 3)
    ref = np.stack([np.broadcast_to(np.asarray(y, np.float64), (200,))
                    for y in dr.sh_eval(vec(d), 3)], axis=1)
    assert np.abs(ours - ref).max() < 1e-5
    # Orthonormal under the quadrature.
    dirs, w = shm.sphere_quadrature(16)
    B = shm.sh_basis_numpy(dirs, 3)
    assert np.allclose(B.T @ (B * w[:, None]), np.eye(16), atol=1e-10)


def test_emitter_sky_matches_numpy(variant):
    e = mi.load_dict(shsun(sh=sh_string(SKY3_NEG)))
    d = random_dirs(500, seed=2)
    ours = np.asarray(e.sky_radiance(vec(d))).T
    ref = np.maximum(0, shm.eval_sh_numpy(SKY3_NEG, d))
    assert np.abs(ours - ref).max() < 1e-4
    assert ours.min() >= 0 and (ref == 0).any()  # the clamp is exercised


def test_projection_reproduces_order2_sky():
    a, b, c = np.array([1.0, 2.0, 3.0]), np.array([0.5, -0.2, 0.1]), np.array([0.3, 0.4, -0.2])

    def sky(d):
        z = d[:, 2:3]
        return a + b * z + c * (3 * z * z - 1)

    for order in (2, 3):
        coeffs = shm.project_sh(sky, order)
        d = random_dirs(1000, seed=4)
        err = np.abs(shm.eval_sh_numpy(coeffs, d) - sky(d)).max()
        assert err < 1e-3, (order, err)
    assert np.allclose(coeffs[0], a * math.sqrt(4 * math.pi), atol=1e-9)
    # Order 1 cannot hold the z² term: a clear residual remains.
    assert np.abs(shm.eval_sh_numpy(shm.project_sh(sky, 1), d) - sky(d)).max() > 0.1


def test_projection_error_decreases_with_order():
    s = np.array([0.3, 0.2, 0.93])
    s /= np.linalg.norm(s)

    def sky(d):  # smooth, not band-limited: a bright lobe plus a horizon gradient
        return np.exp(2.0 * (d @ s))[:, None] * np.array([1.0, 0.9, 0.8]) + \
            np.exp(-4 * d[:, 2:3] ** 2) * np.array([0.2, 0.3, 0.5])

    dirs, w = shm.sphere_quadrature(48)
    errors = []
    for order in range(4):
        coeffs = shm.project_sh(sky, order)
        diff = shm.eval_sh_numpy(coeffs, dirs) - sky(dirs)
        errors.append(math.sqrt((diff ** 2 * w[:, None]).sum() / (4 * math.pi)))
    print("RMS projection error by order 0..3:", errors)
    assert all(e1 < 0.8 * e0 for e0, e1 in zip(errors, errors[1:])), errors


def test_to_world_rotates_the_sky(variant):
    rot = mi.ScalarTransform4f().rotate([1, 0, 0], 90)
    plain = mi.load_dict(shsun(sh=sh_string(SKY3)))
    turned = mi.load_dict(shsun(sh=sh_string(SKY3), to_world=rot))
    d_local = random_dirs(100, seed=5)
    d_world = d_local @ np.array(rot.matrix, np.float64)[:3, :3].T
    a = np.asarray(turned.sky_radiance(vec(d_world)))
    b = np.asarray(plain.sky_radiance(vec(d_local)))
    assert np.allclose(a, b, atol=1e-4)


# ------------------------------------------------------------ 5. hard cases


@pytest.mark.parametrize("kw,match", [
    (dict(sh="1 2 3 4"), "'sh'"),
    (dict(sh="1 2 3 4 5 6"), "'sh'"),
    (dict(sh="1 2 3", order=1), "'order'"),
    (dict(sh="nan 1 1"), "'sh'"),
    (dict(sh="1 x 1"), "'sh'"),
    (dict(order=4), "'order'"),
    (dict(sun_irradiance=-1.0), "'sun_irradiance'"),
    (dict(sun_irradiance={"type": "rgb", "value": [1, float("nan"), 1]}), "'sun_irradiance'"),
    (dict(sun_radius=0.0), "'sun_radius'"),
    (dict(sun_radius=90.0), "'sun_radius'"),
    (dict(sun_radius=-2.0), "'sun_radius'"),
    (dict(sun_direction=[0, 0, 0]), "'sun_direction'"),
    (dict(to_world=mi.ScalarTransform4f().scale(2)), "'to_world'"),
])
def test_bad_input_refused(variant, kw, match):
    with pytest.raises(Exception, match=match) as info:
        mi.load_dict(shsun(**kw))
    assert "ValueError" in str(info.value) or isinstance(info.value, ValueError)


def test_nan_update_refused(variant):
    e = mi.load_dict(shsun(sh=sh_string(SKY3)))
    params = mi.traverse(e)
    values = np.asarray(params["sh"]).copy()
    values[5] = np.nan
    params["sh"] = mi.Float(values)
    with pytest.raises(ValueError, match="'sh'"):
        params.update()


def test_radiance_never_negative(variant):
    e = mi.load_dict(shsun(sh=sh_string(SKY3_NEG), sun_irradiance=1.0))
    n = 20000
    d = vec(random_dirs(n, seed=6))
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = -d
    L = np.asarray(e.eval(si))
    assert np.all(np.isfinite(L)) and L.min() >= 0
    mean, img = render_mean(shsun(sh=sh_string(SKY3_NEG), sun_irradiance=1.0), spp=4)
    assert img.min() >= 0


def test_sun_below_horizon_adds_nothing_to_the_ground(variant):
    sky = shsun(sh=sh_string(SKY3))
    below = shsun(sh=sh_string(SKY3), sun_direction=[1, 0, -0.3], sun_irradiance=50.0)
    horizon = shsun(sh=sh_string(SKY3), sun_direction=[1, 0, 0], sun_irradiance=50.0)
    # Only the ground's top face is seen: the sphere is out of this scene.
    def ground_only(em):
        d = scene_dict(em, max_depth=2)
        del d["sphere"]
        d["sensor"]["to_world"] = mi.ScalarTransform4f().look_at(origin=[0, 0, 3],
                                                                 target=[0, 0, 0], up=[0, 1, 0])
        return np.asarray(mi.render(mi.load_dict(d), spp=64, seed=1), np.float64)
    ref, low, flat = ground_only(sky), ground_only(below), ground_only(horizon)
    for img in (ref, low, flat):
        assert np.all(np.isfinite(img))
    # Below the horizon the sun only costs samples: the estimate stays unbiased.
    assert np.all(np.abs(low.mean((0, 1)) / ref.mean((0, 1)) - 1) < 0.02)
    # At the horizon half the disk is up, grazing: cos ≤ sin(0.265°), E·cos < 0.25.
    extra = flat.mean((0, 1)) - ref.mean((0, 1))
    assert np.all(extra > -0.02 * ref.mean((0, 1))) and np.all(extra < 0.25 * 0.5 / math.pi + 0.02)


def test_huge_irradiance_is_linear_and_finite(variant):
    sun = dict(sh="0 0 0", sun_direction=[0.4, -0.5, 0.75])
    small, _ = render_mean(shsun(sun_irradiance=1.0, **sun), spp=8, seed=3)
    huge, img = render_mean(shsun(sun_irradiance=1e8, **sun), spp=8, seed=3)
    assert np.all(np.isfinite(img))
    assert np.allclose(huge / 1e8, small, rtol=1e-4)


def test_eval_gradients_match_finite_differences(variant):
    e = mi.load_dict(shsun(sh=sh_string(SKY3), sun_direction=[0, 0.6, 0.8],
                           sun_irradiance={"type": "rgb", "value": [2.0, 3.0, 4.0]}))
    params = mi.traverse(e)
    sky_dirs = np.array([[0.3, -0.2, 0.93], [-0.7, 0.1, 0.2], [0.1, 0.5, -0.8]])
    # The sun's radiance (~1.5e4 per unit irradiance) would swamp the sky's
    # finite differences in float32: check each parameter where it matters.
    cases = (("sh", sky_dirs, 1e-2), ("sun_irradiance", np.array([[0, 0.6, 0.8]]), 1e-2))

    for key, dirs, h in cases:
        dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)

        def total():
            si = dr.zeros(mi.SurfaceInteraction3f, len(dirs))
            si.wi = -vec(dirs)
            return dr.sum(dr.sum(e.eval(si)))

        dr.enable_grad(params[key])
        params.update()
        dr.backward(total())
        grad = np.asarray(dr.grad(params[key]), np.float64).ravel()
        dr.disable_grad(params[key])
        base = np.array(np.asarray(params[key]), np.float64).ravel()
        assert np.all(np.isfinite(grad))

        def set_value(v):
            params[key] = mi.Float(v.astype(np.float32)) if key == "sh" \
                else mi.Color3f(*map(float, v))
            params.update()

        fd = []
        for i in range(base.size):
            vals = []
            for step in (h, -h):
                v = base.copy()
                v[i] += step
                set_value(v)
                vals.append(float(total()[0]))
            fd.append((vals[0] - vals[1]) / (2 * h))
        set_value(base)
        fd = np.array(fd)
        print(key, "max |AD - FD| =", np.abs(grad - fd).max(), "of max |FD|", np.abs(fd).max())
        assert np.allclose(grad, fd, rtol=1e-3, atol=2e-3), (key, grad, fd)
    # The sun disk's radiance per unit irradiance: 1 / (π sin² r).
    assert grad[0] == pytest.approx(1 / (math.pi * math.sin(math.radians(0.265)) ** 2), rel=1e-3)


def _prb_scene(**em):
    return mi.load_dict(scene_dict(shsun(**em), integrator="prb", max_depth=3))


def _ad_gradients(scene, keys, spp=8, seed=7):
    params = mi.traverse(scene)
    for key in keys:
        dr.enable_grad(params[key])
    params.update()
    # The adjoint pass traces with seed_grad: the very paths of a primal render with
    # seed=seed_grad, so finite differences of such renders compare path by path.
    img = mi.render(scene, params, spp=spp, seed=seed + 1, seed_grad=seed)
    dr.backward(dr.mean(img, axis=None))
    grads = {k: np.asarray(dr.grad(params[k]), np.float64).ravel() for k in keys}
    for key in keys:
        dr.disable_grad(params[key])
    params.update()
    return grads, _render_mean(scene, spp=spp, seed=seed)


def _render_mean(scene, spp=8, seed=7):
    return float(np.asarray(mi.render(scene, spp=spp, seed=seed), np.float64).mean())


def test_render_gradients_euler_identity(variant):
    """The render is positively homogeneous of degree 1 in (sh, sun_irradiance),
    and scaling both leaves the sampling unchanged; so, path by path,
    Σ x · ∂mean/∂x = mean (Euler), which checks every AD path of the emitter in prb."""
    scene = _prb_scene(sh=sh_string(SKY3), sun_direction=[0.4, -0.5, 0.75],
                       sun_irradiance={"type": "rgb", "value": [2.0, 2.5, 3.0]})
    keys = ["light.sh", "light.sun_irradiance"]
    grads, mean = _ad_gradients(scene, keys)
    params = mi.traverse(scene)
    dot = sum(float(np.dot(grads[k], np.asarray(params[k], np.float64).ravel())) for k in keys)
    print("Euler: Σ x·grad = %.6f, mean = %.6f" % (dot, mean))
    assert np.all(np.isfinite(grads[keys[0]])) and np.all(np.isfinite(grads[keys[1]]))
    assert dot == pytest.approx(mean, rel=1e-3)
    # Same identity by finite differences of a global scale.
    base = {k: np.asarray(params[k], np.float64).ravel().copy() for k in keys}
    for k in keys:
        params[k] = type(params[k])(*map(float, 1.05 * base[k])) if k.endswith("irradiance") \
            else mi.Float((1.05 * base[k]).astype(np.float32))
    params.update()
    assert _render_mean(scene) == pytest.approx(1.05 * mean, rel=1e-4)


def test_render_gradient_sun_irradiance_matches_fd(variant):
    # No sky: all samples go to the sun whatever its irradiance, so a render with
    # the same seed is exactly linear and central differences are exact.
    scene = _prb_scene(sh="0 0 0", sun_direction=[0.4, -0.5, 0.75],
                       sun_irradiance={"type": "rgb", "value": [2.0, 2.5, 3.0]})
    grads, _ = _ad_gradients(scene, ["light.sun_irradiance"])
    params = mi.traverse(scene)
    base = np.asarray(params["light.sun_irradiance"], np.float64).ravel()
    for i in range(3):
        vals = []
        for h in (0.1, -0.1):
            v = base.copy()
            v[i] += h
            params["light.sun_irradiance"] = mi.Color3f(*map(float, v))
            params.update()
            vals.append(_render_mean(scene))
        fd = (vals[0] - vals[1]) / 0.2
        g = grads["light.sun_irradiance"][i]
        print("d mean / d E[%d]: AD %.6f  FD %.6f" % (i, g, fd))
        assert g == pytest.approx(fd, rel=1e-3)


def test_render_gradient_sky_constant_matches_fd(variant):
    # Order 0: the sampling table is uniform whatever c0, so again exact FD.
    scene = _prb_scene(sh="3 3.5 4")
    grads, _ = _ad_gradients(scene, ["light.sh"])
    params = mi.traverse(scene)
    base = np.asarray(params["light.sh"], np.float64).ravel()
    for i in range(3):
        vals = []
        for h in (0.1, -0.1):
            v = base.copy()
            v[i] += h
            params["light.sh"] = mi.Float(v.astype(np.float32))
            params.update()
            vals.append(_render_mean(scene))
        fd = (vals[0] - vals[1]) / 0.2
        g = grads["light.sh"][i]
        print("d mean / d c0[%d]: AD %.6f  FD %.6f" % (i, g, fd))
        assert g == pytest.approx(fd, rel=1e-3)


def test_sample_ray_and_wavelengths(variant):
    scene = mi.load_dict(scene_dict(shsun(sh=sh_string(SKY3), sun_direction=[0, 0.6, 0.8],
                                          sun_irradiance=10.0, sun_radius=1.0)))
    e = scene.environment()
    e.set_scene(scene)  # Mitsuba does not forward it to Python emitters
    sphere = scene.bbox().bounding_sphere()
    n = 1 << 16
    rng = np.random.default_rng(8)
    u = [mi.Point2f(rng.random((2, n)).astype(np.float32)) for _ in range(2)]
    ray, w = e.sample_ray(0.0, mi.Float(0.5), u[0], u[1])
    o = np.asarray(ray.o, np.float64).T - np.asarray(sphere.center, np.float64).ravel()
    d = np.asarray(ray.d, np.float64).T
    # Rays start on a disk tangent to the bounding sphere and head into it.
    assert np.allclose(-(o * d).sum(1), sphere.radius, rtol=1e-4)
    assert np.all(np.linalg.norm(o - (o * d).sum(1, keepdims=True) * d, axis=1)
                  <= sphere.radius * (1 + 1e-4))
    # Unbiased power: E[weight] = π R² ∫ L dω.
    r = math.radians(1.0)
    dirs, wq = shm.sphere_quadrature(64)
    power = (np.maximum(0, shm.eval_sh_numpy(SKY3, dirs)) * wq[:, None]).sum(0) + \
        10.0 / (math.pi * math.sin(r) ** 2) * 2 * math.pi * (1 - math.cos(r))
    est = np.asarray(w, np.float64).mean(1) / (math.pi * sphere.radius ** 2)
    assert np.allclose(est, power, rtol=0.03), (est, power)
    si = dr.zeros(mi.SurfaceInteraction3f, 2)
    si.wi = -vec([[0, 0.6, 0.8], [0, 0, -1]])
    _, spec = e.sample_wavelengths(si, mi.Float([0.3, 0.7]))
    assert np.allclose(np.asarray(spec), np.asarray(e.eval(si)))
