"""Light bounced between Gaussians (``invrgbl``'s ``bounces``) against Mitsuba.

The reference is Mitsuba's stock ``path`` integrator on the same corner (a
floor and a wall) built from ``cooktorrance`` meshes: ``max_depth`` 3 minus
``max_depth`` 2 is the light that arrives after exactly one bounce. The
Gaussian corner renders the same with ``bounces`` 1 minus ``bounces`` 0.
Gradients of the bounce are checked against central finite differences.
"""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from test_invrgbl import ALPHA, DEPTH, RGB, camera, layer, pixel_rays, sky

ALBEDO_FLOOR = (0.6, 0.55, 0.5)
ALBEDO_WALL = (0.8, 0.5, 0.3)
ROUGHNESS = 1.0
#: No Fresnel reflectance: the surfaces are Lambertian up to a grazing term,
#: as the bounce assumes (it passes on diffusely reflected light only).
F0 = 0.0
SUN = [0.2, -1.0, 0.8]    # the sun lights the wall's face and the floor in front of it


def wall_transform():
    # Layer (x, y, 0) with normal +z -> wall (x, 0.5, y + 1) with normal -y.
    return (mi.ScalarTransform4f().translate([0, 0.5, 1.0])
            @ mi.ScalarTransform4f().rotate([1, 0, 0], 90))


def gaussian_corner(bounces, wall_albedo=ALBEDO_WALL, samples=64):
    floor, _ = layer(extent=1.0, spacing=0.08, albedo=ALBEDO_FLOOR, roughness=ROUGHNESS)
    wall, _ = layer(extent=1.0, spacing=0.08, albedo=wall_albedo, roughness=ROUGHNESS,
                    shape_id="wall")
    wall["to_world"] = wall_transform()
    return {"type": "scene",
            "integrator": {"type": "invrgbl", "samples": samples, "bounces": bounces, "f0": F0},
            "floor": floor, "wall": wall, "sky": sky(sun_direction=SUN),
            "sensor": camera([0.3, -3.5, 1.6], [0, 0, 0.4], size=48)}


def mesh_corner(max_depth):
    ct = lambda a: {"type": "cooktorrance", "albedo": list(a), "roughness": ROUGHNESS, "f0": F0}  # noqa: E731
    return {"type": "scene", "integrator": {"type": "path", "max_depth": max_depth},
            "floor": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale(1.0),
                      "bsdf": ct(ALBEDO_FLOOR)},
            "wall": {"type": "rectangle", "to_world": wall_transform(), "bsdf": ct(ALBEDO_WALL)},
            "sky": sky(sun_direction=SUN),
            "sensor": camera([0.3, -3.5, 1.6], [0, 0, 0.4], size=48)}


def render(d, spp, seed=0):
    return np.array(mi.render(mi.load_dict(d), spp=spp, seed=seed))


def inside_pixels(mesh_scene, g0):
    """Pixels well inside both surfaces (opaque Gaussians, mesh hit), where
    the layers' fading borders do not matter."""
    mesh = mi.load_dict(mesh_scene)
    o, d = pixel_rays(mesh)
    si = mesh.ray_intersect(mi.Ray3f(mi.Point3f(o.reshape(-1, 3).T), mi.Vector3f(d.reshape(-1, 3).T)))
    p = np.array(si.p).T.reshape(o.shape)
    # The mesh point lies inside both surfaces' borders (the layers fade
    # over their outer 3 sigma) and the Gaussians' depth agrees with it.
    inside = np.array(si.is_valid()).reshape(o.shape[:2]) & (np.abs(p[..., 0]) < 0.8)
    inside &= (p[..., 1] < 0.45) | (p[..., 2] > 0.05)   # on the floor in front, or on the wall
    inside &= (p[..., 1] > -0.8) & (p[..., 2] < 1.8)
    inside &= (g0[..., ALPHA] > 0.999) & (np.abs(g0[..., DEPTH] - np.array(si.t).reshape(o.shape[:2])) < 0.05)
    assert inside.mean() > 0.3
    return inside


def test_one_bounce_between_gaussians_matches_path_tracing():
    g0, g1 = render(gaussian_corner(0), 4), render(gaussian_corner(1), 4)
    m2, m3 = render(mesh_corner(2), 2048), render(mesh_corner(3), 2048, seed=1)
    inside = inside_pixels(mesh_corner(2), g0)
    bounce_g = (g1 - g0)[inside][:, RGB]
    bounce_m = (m3 - m2)[inside][:, RGB]
    direct_m = m2[inside][:, RGB]
    share = bounce_m.mean(0) / direct_m.mean(0)
    rel = bounce_g.mean(0) / bounce_m.mean(0) - 1
    # Where the bounce is strongest (the floor next to the wall, the wall
    # above the sunlit floor): the upper quarter of the reference's bounce.
    strong = bounce_m.sum(-1) > np.percentile(bounce_m.sum(-1), 75)
    rel_strong = bounce_g[strong].mean(0) / bounce_m[strong].mean(0) - 1
    print("bounce share of direct %s; rel err all %s, strongest quarter %s"
          % (share, rel, rel_strong))
    # The corner's bounce is a real part of the light (else the test proves nothing).
    assert np.all(share > 0.05)
    # Without bounce the Gaussians miss it entirely: g0 alone would be -100 %.
    # Measured: 2-4 % over all pixels, 5-8 % low in the strongest quarter
    # (each Gaussian's light is taken at its centre, so the steep rise of
    # the bounce into the corner is smoothed over one Gaussian's size).
    assert np.all(np.abs(rel) < 0.08)
    assert np.all(np.abs(rel_strong) < 0.12)
    # And the total image agrees as well as the direct light does.
    total = g1[inside][:, RGB].mean(0) / m3[inside][:, RGB].mean(0) - 1
    assert np.all(np.abs(total) < 0.03)


@pytest.mark.parametrize("coated,key", [(False, "wall.albedo"), (True, "wall.albedo"),
                                        (True, "wall.roughness")])
def test_bounce_gradient_matches_finite_differences(coated, key):
    """The floor's colour depends on the wall's albedo only through the
    bounce; under a coat, on the wall's roughness too (its coat lets the
    bounce out), besides the wall's own glossy reflection, which the floor's
    pixels do not show."""
    scene = mi.load_dict((coated_corner_gaussians if coated else gaussian_corner)(1, samples=16))
    params = mi.traverse(scene)
    assert key in params, sorted(params.keys())
    base = mi.Float(params[key])
    # Floor pixels only: below the wall's lowest point in the image.
    img0 = np.array(mi.render(scene, params, spp=1))
    floor = (img0[..., ALPHA] > 0.999) & (img0[..., DEPTH] > 0) & (np.arange(48)[:, None] > 34)
    assert floor.sum() > 40
    mask = mi.TensorXf(np.repeat(floor[..., None], img0.shape[-1], -1).astype(np.float32)
                       * (np.arange(img0.shape[-1]) < 3))

    def objective():
        return dr.sum((mi.render(scene, params, spp=1) * mask).array)

    dr.enable_grad(params[key])
    params.update()
    f = objective()
    dr.backward(f)
    grad = np.array(dr.grad(params[key]))
    # Along all wall Gaussians' red channel (or roughness) at once (one
    # direction, two renders).
    direction = np.zeros(dr.width(base), np.float32)
    direction[0::3 if key.endswith("albedo") else 1] = 1.0
    ad = float(grad @ direction)
    eps = 0.05
    vals = []
    for s in (+1, -1):
        params[key] = base + mi.Float(s * eps * direction)
        params.update()
        with dr.suspend_grad():
            vals.append(float(objective()[0]))
    params[key] = base
    params.update()
    fd = (vals[0] - vals[1]) / (2 * eps)
    print("d(floor red)/d(%s): AD %.5g, FD %.5g" % (key, ad, fd))
    if key.endswith("albedo"):
        assert fd > 0                  # more red on the wall, more red bounced on the floor
    else:
        assert fd < 0                  # a rougher coat lets less of the wall's light out
    # 3 %, as for the integrator's other material gradients (test_invrgbl_gradients).
    assert abs(ad - fd) <= 0.03 * abs(fd)


@pytest.mark.parametrize("bounces", [-1, 9])
def test_bounces_out_of_range_are_refused(bounces):
    with pytest.raises(Exception, match="bounces"):
        mi.load_dict({"type": "invrgbl", "bounces": bounces})


def test_nothing_to_bounce_off_renders_as_direct_light():
    """A single Gaussian: its sky rays meet nothing, the bounce matrix is
    empty, and the image equals the direct-light one."""
    from test_invrgbl import single_gaussian
    imgs = [render({"type": "scene", "integrator": {"type": "invrgbl", "samples": 16, "bounces": b},
                    "blob": single_gaussian([0, 0, 0], [0.5, 0.5, 0.05]), "sky": sky(sun_direction=SUN),
                    "sensor": camera([0, -2, 2], [0, 0, 0], size=16)}, 2) for b in (0, 1)]
    assert imgs[0][..., ALPHA].max() > 0.5
    assert np.allclose(imgs[0], imgs[1], rtol=1e-6, atol=1e-7)


COAT_ROUGHNESS = 0.9


def coated_corner_gaussians(bounces, samples=64):
    d = gaussian_corner(bounces, samples=samples)
    for name in ("floor", "wall"):
        n = d[name]["roughness"].shape[0]
        d[name]["roughness"] = mi.TensorXf(np.full(n, COAT_ROUGHNESS, np.float32))
    d["integrator"] = dict(d["integrator"], diffuse_fresnel=True, f0=0.04, shadowing="smith")
    return d


def coated_corner_meshes(max_depth):
    d = mesh_corner(max_depth)
    for name, albedo in (("floor", ALBEDO_FLOOR), ("wall", ALBEDO_WALL)):
        d[name]["bsdf"] = {"type": "roughplastic", "distribution": "ggx", "alpha": COAT_ROUGHNESS,
                           "int_ior": 1.5, "ext_ior": 1.0,
                           "diffuse_reflectance": {"type": "rgb", "value": list(albedo)}}
    return d


def test_coated_bounce_leaves_its_source_through_the_coat():
    """Under a coat (``diffuse_fresnel``) the light a Gaussian passes on
    leaves it through its coat, as its light towards the camera does, and
    enters the receiver through its coat, as direct light does, and the
    receiver's specular lobe reflects it too. The reference is the
    ``roughplastic`` corner. What the bounce leaves out, the blockers' own
    specular light passed on, keeps it low. Measured: 8-15 % low (18-29 %
    with the lobe blind to the blockers; 3.8x high before the coat was
    applied to the bounce)."""
    g0, g1 = render(coated_corner_gaussians(0), 4), render(coated_corner_gaussians(1), 4)
    m2, m3 = render(coated_corner_meshes(2), 2048), render(coated_corner_meshes(3), 2048, seed=1)
    inside = inside_pixels(coated_corner_meshes(2), g0)
    bounce_g = (g1 - g0)[inside][:, RGB].mean(0)
    bounce_m = (m3 - m2)[inside][:, RGB].mean(0)
    share = bounce_m / m2[inside][:, RGB].mean(0)
    rel = bounce_g / bounce_m - 1
    print("coated bounce share of direct %s; rel err %s" % (share, rel))
    assert np.all(share > 0.02)
    assert np.all(np.abs(rel) < 0.2)


GLOSSY_FLOOR = dict(albedo=(0.05, 0.05, 0.05), roughness=0.1)
BRIGHT_WALL = dict(albedo=(0.8, 0.8, 0.8), roughness=1.0)


def glossy_corner_gaussians(bounces, samples=64):
    floor, _ = layer(extent=1.0, spacing=0.08, **GLOSSY_FLOOR)
    wall, _ = layer(extent=1.0, spacing=0.08, shape_id="wall", **BRIGHT_WALL)
    wall["to_world"] = wall_transform()
    return {"type": "scene",
            "integrator": {"type": "invrgbl", "samples": samples, "bounces": bounces, "f0": 0.04},
            "floor": floor, "wall": wall, "sky": sky(sun_direction=SUN),
            "sensor": camera([0.3, -3.5, 1.6], [0, 0, 0.4], size=48)}


def glossy_corner_meshes(max_depth):
    ct = lambda m: {"type": "cooktorrance", "albedo": list(m["albedo"]),  # noqa: E731
                    "roughness": m["roughness"], "f0": 0.04}
    d = mesh_corner(max_depth)
    d["floor"]["bsdf"], d["wall"]["bsdf"] = ct(GLOSSY_FLOOR), ct(BRIGHT_WALL)
    return d


def test_a_glossy_floor_mirrors_the_wall_beside_it():
    """A dark glossy floor (glass-like: albedo 0.05, roughness 0.1, f0 0.04)
    beside a bright sunlit wall: most of the light the floor sends the
    camera after one bounce is the wall's image in its specular lobe, which
    the bounce brings to the lobe sample by sample. Reference: the
    ``cooktorrance`` corner, ``path`` max_depth 3 minus 2, floor pixels.
    The wall's own specular light, which the bounce leaves out, is small
    here (f0 0.04, roughness 1). Measured: 5 % low in each channel; with
    the lobe reading the sky alone (blockers black to it) 87 % low."""
    g0, g1 = render(glossy_corner_gaussians(0), 4), render(glossy_corner_gaussians(1), 4)
    m2, m3 = render(glossy_corner_meshes(2), 2048), render(glossy_corner_meshes(3), 2048, seed=1)
    mesh = glossy_corner_meshes(2)
    inside = inside_pixels(mesh, g0)
    o, d = pixel_rays(mi.load_dict(mesh))
    # The floor's pixels: their rays meet z = 0 before the wall's plane.
    t = -o[..., 2] / np.where(d[..., 2] < -1e-6, d[..., 2], -1e-6)
    y = o[..., 1] + t * d[..., 1]
    floor = inside & (d[..., 2] < 0) & (y < 0.45)
    assert floor.sum() > 100
    bounce_g = (g1 - g0)[floor][:, RGB].mean(0)
    bounce_m = (m3 - m2)[floor][:, RGB].mean(0)
    rel = bounce_g / bounce_m - 1
    print("glossy floor: bounce %s against %s (rel %s); share of direct %s"
          % (bounce_g, bounce_m, rel, bounce_m / m2[floor][:, RGB].mean(0)))
    assert np.all(bounce_m / m2[floor][:, RGB].mean(0) > 0.2)
    assert np.all(np.abs(rel) < 0.12)
