"""Gradients of the ``invrgbl`` integrator: finite everywhere, equal to finite differences."""

import numpy as np
import pytest
import drjit as dr
import mitsuba as mi

SKY = {"type": "shsun", "id": "sky", "sh": "0.9 1.0 1.2  0 0 0  0.3 0.3 0.4  0 0 0",
       "sun_direction": [0.3, 0.2, 1.0], "sun_irradiance": [2.0, 1.9, 1.7]}


def layer(opacity=0.6, roughness=0.4, n=12, spacing=0.25):
    rng = np.random.default_rng(3)
    xs = (np.arange(n) - (n - 1) / 2) * spacing
    x, y = np.meshgrid(xs, xs)
    c = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1)
    c[:, :2] += rng.uniform(-0.03, 0.03, (c.shape[0], 2))
    m = c.shape[0]
    t = lambda a: mi.TensorXf(np.asarray(a, np.float32))  # noqa: E731
    return {"type": "gaussians", "id": "g", "centers": t(c),
            "scales": t(np.tile([spacing * 0.8, spacing * 0.8, spacing * 0.08], (m, 1))),
            "opacities": t(np.full(m, opacity)), "normals": t(np.tile([0, 0, 1.0], (m, 1))),
            "albedo": t(np.tile([0.6, 0.4, 0.3], (m, 1))), "roughness": t(np.full(m, roughness))}


def scene(ground=False, **kw):
    """Gaussian layer under the sky; ``ground`` adds a mesh below it.

    Finite differences use the layer alone: its shading is deterministic,
    while a mesh is shaded by Monte Carlo whose samples move when the sky's
    sampling table is rebuilt for a perturbed parameter (FD noise, not AD error).
    """
    extra = {}
    if ground:
        extra["ground"] = {"type": "rectangle",
                           "to_world": mi.ScalarTransform4f().translate([0, 0, -0.3]).scale(3),
                           "bsdf": {"type": "cooktorrance", "albedo": 0.3, "roughness": 0.6}}
    return mi.load_dict({
        "type": "scene", "integrator": {"type": "invrgbl", "samples": 8},
        "g": layer(**kw), "sky": SKY, **extra,
        "sensor": {"type": "perspective", "fov": 45,
                   "to_world": mi.ScalarTransform4f().look_at([0.3, -2.0, 2.5], [0, 0, 0], [0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": 12, "height": 12, "rfilter": {"type": "box"}}}})


def loss(img):
    return dr.sum(img[..., :3].array)


def ad_and_fd(sc, key, direction, h):
    """Directional derivative of the image sum along ``direction`` by AD and by central FD."""
    params = mi.traverse(sc)
    base = np.array(params[key], np.float64).ravel()
    direction = np.asarray(direction, np.float64).ravel()
    kind = type(params[key])

    def set_value(v):
        if isinstance(params[key], mi.Float):
            params[key] = mi.Float(v.astype(np.float32))
        else:  # 3-vectors and colours
            params[key] = kind(*[float(x) for x in v])
        params.update()

    set_value(base)
    dr.enable_grad(params[key])
    params.update()
    img = mi.render(sc, params, spp=1, seed=1)
    dr.backward(loss(img))
    grad = np.array(dr.grad(params[key]), np.float64).ravel()
    assert np.all(np.isfinite(grad)), key
    ad = float(grad @ direction)
    values = []
    for sign in (+1, -1):
        set_value(base + sign * h * direction)
        values.append(float(loss(mi.render(sc, spp=1, seed=1))[0]))
    set_value(base)
    return ad, (values[0] - values[1]) / (2 * h)


# Opacity: the ellipsoids' support (adaptive extent clamping) shrinks with the
# opacity, which moves the layer's edges; finite differences see that boundary
# term, the interior AD derivative does not (measured 7 % apart), hence 10 %.
@pytest.mark.parametrize("key,h,rel", [("g.albedo", 1e-2, 0.03), ("g.roughness", 2e-2, 0.03),
                                       ("g.opacities", 1e-2, 0.10)])
def test_gaussian_material_gradients_match_finite_differences(key, h, rel):
    sc = scene()
    size = dr.width(mi.traverse(sc)[key])
    ad, fd = ad_and_fd(sc, key, np.ones(size), h)
    assert abs(fd) > 1e-4                     # the parameter does change the image
    assert ad == pytest.approx(fd, rel=rel)


def test_sky_and_sun_gradients_match_finite_differences():
    sc = scene()
    params = mi.traverse(sc)
    n_sh = dr.width(params["sky.sh"])
    e0 = np.zeros(n_sh)
    e0[0] = 1.0                               # the constant (order-0) red coefficient
    ad, fd = ad_and_fd(sc, "sky.sh", e0, 2e-2)
    assert ad == pytest.approx(fd, rel=0.03)
    ad, fd = ad_and_fd(sc, "sky.sun_irradiance", np.ones(3), 5e-2)
    assert abs(fd) > 1e-3
    assert ad == pytest.approx(fd, rel=0.03)


def test_geometry_gradients_are_finite_and_match_for_centre_height():
    sc = scene(opacity=0.9)
    params = mi.traverse(sc)
    n = dr.width(params["g.opacities"])
    direction = np.zeros((n, 10))
    direction[:, 2] = 1.0                     # every centre's z
    ad, fd = ad_and_fd(sc, "g.data", direction, 1e-2)
    assert np.isfinite(ad)
    # Visibility (the Gaussians' shadows on each other) is traced without
    # derivatives and re-traced for each finite-difference render, so AD sees
    # the moved shading points and blending but not the moved shadows
    # (measured: 26.6 vs 34.5). Same sign and magnitude is what can be asked.
    assert np.sign(ad) == np.sign(fd)
    assert 0.5 < ad / fd < 1.5


@pytest.mark.parametrize("roughness", [0.0, 1.0])
def test_gradients_finite_at_roughness_limits_and_grazing_view(roughness):
    sc = scene(ground=True, roughness=roughness)
    params = mi.traverse(sc)
    keys = ["g.albedo", "g.roughness", "g.opacities", "g.data", "sky.sh", "sky.sun_irradiance"]
    for k in keys:
        dr.enable_grad(params[k])
    params.update()
    sensor = mi.load_dict({"type": "perspective", "fov": 30,
                           "to_world": mi.ScalarTransform4f().look_at([0, -4, 0.05], [0, 0, 0], [0, 0, 1]),
                           "film": {"type": "hdrfilm", "width": 8, "height": 8}})
    for s in (sc.sensors()[0], sensor):
        img = mi.render(sc, params, sensor=s, spp=1)
        assert np.all(np.isfinite(np.array(img)))
        dr.backward(loss(img))
        for k in keys:
            assert np.all(np.isfinite(np.array(dr.grad(params[k])))), k
