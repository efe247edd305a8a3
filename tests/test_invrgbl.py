"""Tests of the ``invrgbl`` camera integrator against independent references.

References used here never go through the integrator's own shading code:

* Mitsuba's stock ``path`` integrator (max_depth 2 = direct light only) on the
  same surface built as a mesh with the ``cooktorrance`` BSDF, or with stock
  BSDFs, under the same ``shsun`` sky and sun;
* closed forms (a point light over a Gaussian; the Cook-Torrance equation
  re-implemented below in numpy);
* renders of the same scene with one light switched off (shadows);
* central finite differences of the primal render (gradients).

Film layout of an ``hdrfilm`` with ``pixel_format=rgb``: channels 0-2 the
colour, then the AOVs in this order: albedo R G B (3-5), normal X Y Z (6-8),
roughness (9), lidar_albedo (10), depth (11), alpha (12).
"""

import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

RGB = slice(0, 3)
ALBEDO, NORMAL = slice(3, 6), slice(6, 9)
ROUGH, LIDAR, DEPTH, ALPHA = 9, 10, 11, 12

SUN_DIR = [0.3, 0.2, 1.0]
# Order-1 sky: brighter overhead (c2 is the z term) plus a tilt in x (c3).
SKY_SH = "1.0 1.1 1.3,  0 0 0,  0.3 0.3 0.4,  -0.1 -0.1 -0.05"


# ---------------------------------------------------------------- helpers
def sky(sun_irradiance=(2.0, 2.0, 1.8), sun_direction=SUN_DIR, sh=SKY_SH):
    d = {"type": "shsun", "sh": sh, "sun_direction": list(sun_direction)}
    if sun_irradiance is not None:
        d["sun_irradiance"] = list(sun_irradiance)
    return d


def camera(origin, target, up=(0, 0, 1), fov=40.0, size=32):
    return {"type": "perspective", "fov": fov,
            "to_world": mi.ScalarTransform4f().look_at(origin, target, up),
            "film": {"type": "hdrfilm", "width": size, "height": size,
                     "pixel_format": "rgb", "rfilter": {"type": "box"}}}


def layer(extent=2.0, spacing=0.1, albedo=(0.6, 0.4, 0.3), roughness=0.4, opacity=1.0,
          lidar_albedo=0.35, z=0.0, sun_visibility=None, shape_id="ground", jitter=0.02):
    """A flat layer of thin disc-shaped Gaussians with normal +z: an opaque
    surface when neighbours overlap (sigma = 1.1 x spacing).

    The grid is jittered and sigma is not a multiple of the spacing: on an
    exact grid, neighbours' 3-sigma supports end exactly on a centre (a shadow
    ray from that centre then clips them) and symmetric neighbours enter a ray
    at the same distance (the traversal then records only one of them)."""
    xs = np.arange(-extent, extent + 1e-6, spacing, dtype=np.float32)
    X, Y = np.meshgrid(xs, xs)
    c = np.stack([X.ravel(), Y.ravel(), np.full(X.size, z)], 1)
    c[:, :2] += np.random.default_rng(1).uniform(-jitter, jitter, (c.shape[0], 2))
    c = c.astype(np.float32)
    n = c.shape[0]
    sigma = 1.1 * spacing
    d = {"type": "gaussians", "id": shape_id,
         "centers": mi.TensorXf(c),
         "scales": mi.TensorXf(np.tile([[sigma, sigma, 1e-3]], (n, 1)).astype(np.float32)),
         "opacities": mi.TensorXf(np.full(n, opacity, np.float32)),
         "normals": mi.TensorXf(np.tile([[0, 0, 1]], (n, 1)).astype(np.float32)),
         "albedo": mi.TensorXf(np.tile([albedo], (n, 1)).astype(np.float32)),
         "roughness": mi.TensorXf(np.full(n, roughness, np.float32)),
         "lidar_albedo": mi.TensorXf(np.full(n, lidar_albedo, np.float32))}
    if sun_visibility is not None:
        d["sun_visibility"] = mi.TensorXf(sun_visibility(c).astype(np.float32))
    return d, c


def single_gaussian(center, scale, albedo=(0.5, 0.5, 0.5), roughness=0.5, opacity=1.0,
                    normal=(0, 0, 1), shape_id="blob"):
    f = lambda v: mi.TensorXf(np.array([v], np.float32))  # noqa: E731
    return {"type": "gaussians", "id": shape_id, "centers": f(center), "scales": f(scale),
            "opacities": mi.TensorXf(np.array([opacity], np.float32)), "normals": f(normal),
            "albedo": f(albedo), "roughness": mi.TensorXf(np.array([roughness], np.float32))}


def render(scene_dict, spp=4, seed=0):
    scene = mi.load_dict(dict({"type": "scene"}, **scene_dict))
    return np.array(mi.render(scene, spp=spp, seed=seed)), scene


def pixel_rays(scene):
    """Per-pixel centre ray origins and directions (H, W, 3) of the scene's sensor."""
    sensor = scene.sensors()[0]
    w, h = sensor.film().crop_size()
    j, i = np.meshgrid(np.arange(w), np.arange(h))
    pos = mi.Point2f(mi.Float(((j + 0.5) / w).ravel()), mi.Float(((i + 0.5) / h).ravel()))
    rays, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5))
    o = np.array(rays.o).T.reshape(h, w, 3)
    d = np.array(rays.d).T.reshape(h, w, 3)
    return o, d


def ground_hits(scene, z=0.0):
    """World point and distance where each pixel's centre ray meets the plane z."""
    o, d = pixel_rays(scene)
    t = (z - o[..., 2]) / np.where(np.abs(d[..., 2]) > 1e-9, d[..., 2], 1e-9)
    return o + t[..., None] * d, t


# ---------------------------------------------------------- Cook-Torrance
def ct_brdf_np(albedo, tau, wi, wo, n=(0, 0, 1), f0=0.04):
    """The paper's BRDF, written again from its equation (numpy, float64):
    rho/pi + F D G / (4 cos_i cos_o), GGX alpha = tau, V-cavity G, Schlick F."""
    n, wi, wo = (np.asarray(v, np.float64) / np.linalg.norm(v) for v in (n, wi, wo))
    h = (wi + wo) / np.linalg.norm(wi + wo)
    ci, co, ch, oh = n @ wi, n @ wo, n @ h, wo @ h
    a2 = tau ** 2
    D = a2 / (math.pi * (ch ** 2 * (a2 - 1) + 1) ** 2)
    G = min(1.0, 2 * ch * co / oh, 2 * ch * ci / oh)
    F = f0 + (1 - f0) * (1 - wi @ h) ** 5
    return np.asarray(albedo, np.float64) / math.pi + F * D * G / (4 * ci * co)


# ==================================================================
# 1. Opaque flat Gaussians == the same surface as a cooktorrance mesh
# ==================================================================
@pytest.mark.parametrize("roughness", [0.2, 0.8])
def test_opaque_gaussian_layer_matches_cooktorrance_mesh_under_path(roughness):
    albedo = (0.6, 0.4, 0.3)
    cam = camera([0, -3, 3], [0, 0, 0])
    g, _ = layer(albedo=albedo, roughness=roughness)
    img_g, scene_g = render({"integrator": {"type": "invrgbl", "samples": 64},
                             "ground": g, "sky": sky(), "sensor": cam}, spp=4)
    mesh = {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale(2.05),
            "bsdf": {"type": "cooktorrance", "albedo": list(albedo), "roughness": roughness}}
    img_m, _ = render({"integrator": {"type": "path", "max_depth": 2},
                       "m": mesh, "sky": sky(), "sensor": cam}, spp=4096)

    # Covered region: pixels whose centre ray meets the layer well inside its
    # border (the layer's edge fades over ~3 sigma).
    p, _ = ground_hits(scene_g)
    mask = (np.abs(p[..., 0]) < 1.7) & (np.abs(p[..., 1]) < 1.7)
    assert mask.sum() > 300
    # A few pixels may show a hole (see test_opaque_layer_has_no_holes).
    assert np.mean(img_g[mask, ALPHA] > 0.99) > 0.98
    a, b = img_g[mask][:, RGB], img_m[mask][:, RGB]
    mean_rel = np.abs(a.mean(0) / b.mean(0) - 1)
    rel = np.abs(a / b - 1)
    p95 = np.percentile(rel, 95)
    print("tau=%.1f mean rel err %s, per-pixel p95 %.4f" % (roughness, mean_rel, p95))
    # Measured: mean 0.1-0.2 %, per-pixel p95 0.013 for both roughness values
    # (the reference's own MC noise at 4096 spp is ~0.5 %, plus the M = 64 sky
    # quadrature of the glossy lobe). 0.03 leaves a 2x margin and still
    # catches a wrong lobe, a missing cosine or a missing sun (tens of %).
    assert np.all(mean_rel < 0.02)
    assert p95 < 0.03


# ==================================================================
# 2. Meshes alone: direct lighting == stock path with max_depth 2
# ==================================================================
def test_mesh_scene_matches_stock_path_direct_lighting():
    shapes = {
        "ball": {"type": "sphere", "center": [-0.6, 0, 0.5], "radius": 0.5,
                 "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.7, 0.45, 0.3]}}},
        "gloss": {"type": "sphere", "center": [0.6, 0.2, 0.4], "radius": 0.4,
                  "bsdf": {"type": "roughplastic", "alpha": 0.2,
                           "diffuse_reflectance": {"type": "rgb", "value": [0.2, 0.35, 0.6]}}},
        "floor": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale(3),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.4, 0.4, 0.38]}}},
    }
    cam = camera([0, -4, 2.5], [0, 0, 0.3])
    img_i, _ = render(dict(shapes, integrator={"type": "invrgbl"}, sky=sky(), sensor=cam), spp=256)
    # Another seed: an honest MC comparison, not the same sample sequence.
    img_p, _ = render(dict(shapes, integrator={"type": "path", "max_depth": 2}, sky=sky(),
                           sensor=cam), spp=256, seed=1)
    covered = img_i[..., ALPHA] > 0.5
    assert covered.mean() > 0.6
    mean_rel = np.abs(img_i[covered][:, RGB].mean(0) / img_p[covered][:, RGB].mean(0) - 1)
    print("mesh scene mean rel err", mean_rel)
    # Measured ~0.3 %; 2 % is the MC-noise bound asked of the integrator.
    assert np.all(mean_rel < 0.02)


# ==================================================================
# 3. Sun shadows: traced from each Gaussian, or read from its field
# ==================================================================
SHADOW_SUN = [1.0, 0.0, 1.0]  # 45 degrees: the blob at (1, 0, 1) shadows the origin
SHADOW_E = (3.0, 3.0, 3.0)


def shadow_scene(sun, mode="trace", blob=True, half_shadowed=False):
    field = (lambda c: (c[:, 1] >= 0).astype(np.float32)) if half_shadowed else None
    g, _ = layer(extent=2.5, albedo=(0.5, 0.5, 0.5), roughness=0.5, sun_visibility=field)
    d = {"integrator": {"type": "invrgbl", "samples": 16, "sun_visibility": mode},
         "ground": g, "sky": sky(sun_irradiance=SHADOW_E if sun else None, sun_direction=SHADOW_SUN),
         "sensor": camera([0, 0, 5], [0, 0, 0], up=(0, 1, 0), fov=50, size=32)}
    if blob:
        d["blob"] = single_gaussian([1, 0, 1], [0.3, 0.3, 0.3])
    return d


def sun_term_closed_form(p, cam_origin=(0, 0, 5)):
    """E cos(theta_sun) f_r(sun, view) on the ground point p (albedo 0.5, tau 0.5)."""
    s = np.array(SHADOW_SUN) / np.linalg.norm(SHADOW_SUN)
    wo = np.asarray(cam_origin, np.float64) - p
    return SHADOW_E[0] * s[2] * ct_brdf_np(0.5, 0.5, s, wo)[()]


def test_blob_casts_sun_shadow_on_gaussian_ground():
    with_sun, scene = render(shadow_scene(True), spp=4)
    no_sun, _ = render(shadow_scene(False), spp=4)
    sun_term = (with_sun - no_sun)[..., 1]
    p, _ = ground_hits(scene)
    r = np.linalg.norm(p[..., :2], axis=-1)
    core = r < 0.15
    # Lit: far from the shadow and not looking through the blob (its image
    # falls around ground x = 1.25).
    lit = ((np.abs(p[..., 1]) > 1.3) & (np.abs(p[..., 1]) < 1.8) & (np.abs(p[..., 0]) < 1.5)
           & (np.linalg.norm(p[..., :2] - [1.25, 0], axis=-1) > 1.3))
    assert core.sum() >= 2 and lit.sum() > 50
    expected = np.array([sun_term_closed_form(q) for q in p[lit]])
    lit_err = np.abs(sun_term[lit] / expected - 1)
    core_ratio = sun_term[core].mean() / sun_term_closed_form(np.zeros(3))
    print("lit sun term err max %.4f, shadow core keeps %.4f of the sun" % (lit_err.max(), core_ratio))
    # Lit ground: the sun term is the closed form (measured median 5e-4). A
    # pixel or two that the traversal renders wrongly (Gaussians skipped at
    # near-equal entry distances, see the layer test) are tolerated by the 90th percentile.
    assert np.percentile(lit_err, 90) < 0.01
    # Core: the blob's centre has opacity 0.99, and each pixel blends ground
    # Gaussians up to ~0.3 away whose shadow rays pass off-centre: measured ~0.05.
    assert core_ratio < 0.15


def test_sun_visibility_attribute_replaces_traced_shadows():
    with_sun, scene = render(shadow_scene(True, "attribute", half_shadowed=True), spp=4)
    no_sun, _ = render(shadow_scene(False, "attribute", half_shadowed=True), spp=4)
    sun_term = (with_sun - no_sun)[..., 1]
    p, _ = ground_hits(scene)
    away_from_blob = np.linalg.norm(p[..., :2] - [1.25, 0], axis=-1) > 1.3
    shadowed = (p[..., 1] < -0.6) & (np.abs(p[..., 0]) < 1.5) & away_from_blob
    lit = (p[..., 1] > 0.6) & (np.abs(p[..., 0]) < 1.5) & (p[..., 1] < 1.8) & away_from_blob
    expected = np.array([sun_term_closed_form(q) for q in p[lit]])
    # The field is 0 for y < 0: no sun there at all.
    assert np.percentile(np.abs(sun_term[shadowed]), 90) < 1e-4 * expected.mean()
    # y > 0: fully lit, also where the traced blob shadow would fall (x ~ 0).
    assert np.percentile(np.abs(sun_term[lit] / expected - 1), 90) < 0.01

    # Editing the field through mi.traverse must take effect on the next render.
    params = mi.traverse(scene)
    params["ground.sun_visibility"] = dr.ones(type(params["ground.sun_visibility"]),
                                              dr.width(params["ground.sun_visibility"]))
    params.update()
    edited = np.array(mi.render(scene, spp=4))
    assert np.all((edited - no_sun)[shadowed, 1] > 0.5 * sun_term[lit].mean())


def test_moving_shapes_cast_their_shadow_over_the_learned_field():
    # A fitted scene's field holds the static scene's shadows (here: none,
    # the field is 1); the blob, named as moving, casts its own shadow on
    # top, where it stands at each render.
    def scene_dict(moving):
        d = shadow_scene(True, "attribute")
        d["integrator"]["moving"] = moving
        return d
    no_sun, _ = render(shadow_scene(False, "attribute"), spp=4)
    traced, _ = render(shadow_scene(True, "trace"), spp=4)
    static, _ = render(scene_dict(""), spp=4)
    moving, scene = render(scene_dict("blob"), spp=4)
    p, _ = ground_hits(scene)
    core = np.linalg.norm(p[..., :2], axis=-1) < 0.15
    full = sun_term_closed_form(np.zeros(3))
    # Without it the field lights the core; with it the core is in the
    # blob's shadow, as a traced render has it.
    assert (static - no_sun)[core, 1].mean() > 0.8 * full
    assert (moving - no_sun)[core, 1].mean() < 0.15 * full
    np.testing.assert_allclose(moving[core], traced[core], atol=0.02 * full)

    # Moved through mi.traverse, the blob takes its shadow along.
    params = mi.traverse(scene)
    data = np.array(params["blob.data"])
    data[1] += 1.0
    params["blob.data"] = type(params["blob.data"])(data)
    params.update()
    moved = np.array(mi.render(scene, spp=4))
    core_y1 = np.linalg.norm(p[..., :2] - [0.0, 1.0], axis=-1) < 0.15
    assert (moved - no_sun)[core, 1].mean() > 0.8 * full
    assert (moved - no_sun)[core_y1, 1].mean() < 0.15 * full

    # A name that is no Gaussian shape is refused by name (mi.render hands
    # the integrator's error on as the cause of its own).
    with pytest.raises(RuntimeError) as refused:
        render(scene_dict("car"), spp=1)
    assert "moving names no Gaussian shape of the scene: car" in str(refused.value.__cause__)


def test_a_low_sun_does_not_shadow_a_surface_with_its_own_gaussians():
    # Fitted surfaces are Gaussians a few centimetres thick and tenths of a
    # metre wide (the street's: smallest scale 0.02-0.04 m, largest 0.2-0.5 m).
    # A shadow ray traced from a centre towards a sun 15 degrees up passes
    # through its neighbours' peaks and the open surface loses part of its
    # sun (a quarter here); traced from SHADOW_OFFSET above the centre (as
    # the fit's sun search and stage 2's start trace) it loses none. With
    # nothing to block the sun, traced visibility must render as the field
    # at 1 does.
    sun = [math.cos(math.radians(15)), 0.0, math.sin(math.radians(15))]

    def ground(mode):
        g, c = layer(extent=1.5, albedo=(0.5, 0.5, 0.5), roughness=0.5,
                     sun_visibility=lambda c: np.ones(len(c)))
        g["scales"] = mi.TensorXf(np.tile([[0.25, 0.25, 0.03]], (len(c), 1)).astype(np.float32))
        # and their centres scatter a few centimetres about the surface.
        c[:, 2] += np.random.default_rng(4).uniform(-0.03, 0.03, len(c)).astype(np.float32)
        g["centers"] = mi.TensorXf(c)
        return {"integrator": {"type": "invrgbl", "samples": 16, "sun_visibility": mode},
                "ground": g, "sky": sky(sun_irradiance=SHADOW_E, sun_direction=sun),
                "sensor": camera([0, 0, 4], [0, 0, 0], up=(0, 1, 0), fov=30, size=24)}

    traced, _ = render(ground("trace"))
    field, _ = render(ground("attribute"))
    ratio = traced[..., 1] / field[..., 1]
    print("traced / field under a 15-degree sun: median %.4f, 5th percentile %.4f"
          % (np.median(ratio), np.percentile(ratio, 5)))
    assert np.percentile(ratio, 5) > 0.98
    # The same surface traced from its centres: self-shadowed, the failure
    # the offset prevents.
    from mi_invrgbl.physics.lighting import GaussianTable, shadow_origins, transmittance
    scene = mi.load_dict(dict({"type": "scene"}, **ground("trace")))
    from mi_invrgbl.physics import hits as hitlib
    nodes = hitlib.gaussian_nodes(scene)
    table = GaussianTable.build(nodes).load_geometry()
    d = dr.zeros(mi.Vector3f, table.total) + mi.Vector3f(sun)
    inner = np.array(np.linalg.norm(np.array(table.center)[:2].T, axis=1) < 1.0)
    from_centre = np.array(transmittance(scene, dr.detach(table.center), d, mi.Float(dr.inf), nodes))
    offset = np.array(transmittance(scene, shadow_origins(table, d), d, mi.Float(dr.inf), nodes))
    print("visibility from the centres %.3f, from the offset origins %.3f"
          % (from_centre[inner].mean(), offset[inner].mean()))
    # Measured: 0.75 from the centres (a quarter of the sun lost on open
    # ground), 1.000 from the offset origins.
    assert from_centre[inner].mean() < 0.85 and offset[inner].min() > 0.98


def test_a_point_light_nearer_than_the_shadow_offset_still_lights_and_stays_finite():
    # Shadow rays to a light at a finite distance stop SHADOW_OFFSET short of
    # it; a light closer than that to a Gaussian gives a ray of length 0,
    # which must read as unblocked, not as NaN or shadow. (Mitsuba also
    # reads a negative length as no hit, so this checks the outcome, not the
    # clamp that keeps the length at 0.)
    from mi_invrgbl.physics.lighting import SHADOW_OFFSET
    light = {"type": "point", "position": [0.0, 0.0, 0.5 * SHADOW_OFFSET],
             "intensity": {"type": "rgb", "value": 0.01}}

    g, _ = layer(extent=0.6, albedo=(0.5, 0.5, 0.5), roughness=0.5)
    img, _ = render({"integrator": {"type": "invrgbl", "samples": 4}, "ground": g, "light": light,
                     "sensor": camera([0, 0, 2], [0, 0, 0], up=(0, 1, 0), fov=20, size=16)})
    assert np.all(np.isfinite(img))
    # Lit where the light is nearest, and brighter there than at the edge
    # (a ray read as blocked would leave the middle black).
    middle, edge = img[7:9, 7:9, 1], img[0, :, 1]
    print("under the light %.4g, at the edge %.4g" % (middle.min(), edge.max()))
    assert middle.min() > 3 * edge.max() > 0


# ==================================================================
# 4. Point and spot lights (night scenes): closed form
# ==================================================================
@pytest.mark.parametrize("case", ["point_above", "point_oblique", "spot_above"])
def test_point_and_spot_light_on_gaussian_match_closed_form(case):
    I, albedo, tau = 10.0, 0.5, 0.5
    light_pos = np.array([0.0, 0.0, 2.0])
    centre = np.array([1.5, 0.0, 0.0]) if case == "point_oblique" else np.zeros(3)
    if case == "spot_above":
        light = {"type": "spot", "intensity": {"type": "rgb", "value": I},
                 "cutoff_angle": 30.0, "beam_width": 20.0,
                 "to_world": mi.ScalarTransform4f().look_at(light_pos, [0, 0, 0], [0, 1, 0])}
    else:
        light = {"type": "point", "position": light_pos.tolist(),
                 "intensity": {"type": "rgb", "value": I}}
    # Camera straight above the Gaussian; odd size so the middle pixel's centre
    # looks exactly at it. No environment: the light is the only source.
    cam_pos = centre + [0, 0, 1]
    img, _ = render({"integrator": {"type": "invrgbl", "samples": 16},
                     # 50:1 disc: much flatter ones (500:1) are missed by the
                     # ellipsoid intersector at normal incidence.
                     "g": single_gaussian(centre.tolist(), [0.5, 0.5, 1e-2], albedo=(albedo,) * 3,
                                          roughness=tau),
                     "light": light,
                     "sensor": camera(cam_pos.tolist(), centre.tolist(), up=(0, 1, 0), fov=5, size=15)},
                    spp=4)
    px = img[7, 7]
    to_light = light_pos - centre
    d2 = to_light @ to_light
    cos = to_light[2] / math.sqrt(d2)
    expected = I * cos / d2 * ct_brdf_np(albedo, tau, to_light, [0, 0, 1])
    got = px[RGB] / px[ALPHA]  # the Gaussian's colour (its opacity is 0.99 there)
    print(case, got, expected)
    assert px[ALPHA] > 0.98
    assert np.allclose(got, expected, rtol=0.01)


# ==================================================================
# 5. AOVs
# ==================================================================
def test_aovs_of_opaque_gaussian_layer():
    g, _ = layer(albedo=(0.6, 0.4, 0.3), roughness=0.3, lidar_albedo=0.35)
    # An emitting plane below the layer: the only light, and Gaussians are not
    # lit by area lights, so the colour is exactly the residual transmittance.
    backlight = {"type": "rectangle",
                 "to_world": mi.ScalarTransform4f().translate([0, 0, -0.5]).scale(4),
                 "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}}
    # min_transmittance below the layer's residual so the ray reaches the plane.
    img, scene = render({"integrator": {"type": "invrgbl", "samples": 4, "min_transmittance": 1e-7},
                         "ground": g,
                         "back": backlight,
                         "sensor": camera([0, 0, 3], [0, 0, 0], up=(0, 1, 0), fov=40, size=16)}, spp=4)
    p, t = ground_hits(scene)
    m = (np.abs(p[..., 0]) < 1.6) & (np.abs(p[..., 1]) < 1.6)
    px = img[m]
    a = px[:, ALPHA]
    assert np.all(a > 0.98)
    # alpha == 1 - residual transmittance (seen as the backlight's radiance).
    print("alpha + backlight - 1: max abs %.2e" % np.abs(a + px[:, 1] - 1).max())
    # The opaque backlight makes the alpha AOV 1, so this is the layer's
    # residual transmittance. For Gaussians this flat (1e-3 thick, 0.11 wide)
    # Mitsuba's intersector misplaces entries: measured over 2000 rays, the
    # traced transmittance is off from the exact product over every Gaussian
    # by a factor ~3 at the median (exact median 4.6e-6), its 90th percentile
    # 2.4e-4 on LLVM and CUDA alike. Asserted: 90 % of pixels below 5e-4.
    assert np.percentile(np.abs(a + px[:, 1] - 1), 90) < 5e-4
    # Material AOVs are alpha-weighted; the mesh behind adds (1 - alpha) * its own.
    def p90(x, want):
        return np.percentile(np.abs(x - np.asarray(want)), 90)
    assert p90(px[:, ALBEDO] / a[:, None], [0.6, 0.4, 0.3]) < 2e-3
    assert p90(px[:, NORMAL] / a[:, None], [0, 0, 1]) < 2e-3
    assert p90(px[:, ROUGH] / a, 0.3) < 2e-3
    assert p90(px[:, LIDAR] / a, 0.35) < 2e-3
    # Depth: distance along the ray to the layer (pixel-centre rays, box filter
    # over a pixel: < 0.5 % spread at this resolution).
    ok = np.isfinite(px[:, DEPTH])
    assert ok.all()
    assert np.percentile(np.abs(px[ok, DEPTH] / t[m][ok] - 1), 90) < 0.01


def test_depth_aov_is_finite_behind_opaque_layer():
    # Regression: rays stopped by the layer carry si.t = inf for the mesh behind;
    # weighting it by a zero transmittance gave 0 * inf = NaN.
    g, _ = layer()
    backlight = {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([0, 0, -0.5]).scale(4),
                 "bsdf": {"type": "diffuse"}}
    img, _ = render({"integrator": {"type": "invrgbl", "samples": 4, "min_transmittance": 1e-7},
                     "ground": g, "back": backlight,
                     "sensor": camera([0, 0, 3], [0, 0, 0], up=(0, 1, 0), fov=40, size=16)}, spp=4)
    assert np.all(np.isfinite(img))


@pytest.mark.parametrize("bsdf", ["cooktorrance", "diffuse"])
def test_aovs_of_mesh(bsdf):
    if bsdf == "cooktorrance":
        b = {"type": "cooktorrance", "albedo": [0.2, 0.5, 0.7], "roughness": 0.3, "lidar_albedo": 0.45}
        want_albedo, want_tau, want_lidar = [0.2, 0.5, 0.7], 0.3, 0.45
    else:
        b = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.2, 0.5, 0.7]}}
        # Any other BSDF: diffuse reflectance, roughness 1, LiDAR albedo = luminance.
        want_albedo, want_tau = [0.2, 0.5, 0.7], 1.0
        want_lidar = 0.2126 * 0.2 + 0.7152 * 0.5 + 0.0722 * 0.7
    img, scene = render({"integrator": {"type": "invrgbl"}, "sky": sky(),
                         "m": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale(5), "bsdf": b},
                         "sensor": camera([0, 0, 3], [0, 0, 0], up=(0, 1, 0), fov=40, size=16)}, spp=4)
    _, t = ground_hits(scene)
    assert np.allclose(img[..., ALPHA], 1.0)
    assert np.allclose(img[..., ALBEDO], want_albedo, atol=1e-5)
    assert np.allclose(img[..., NORMAL], [0, 0, 1], atol=1e-5)
    assert np.allclose(img[..., ROUGH], want_tau, atol=1e-5)
    assert np.allclose(img[..., LIDAR], want_lidar, atol=1e-4)
    assert np.allclose(img[..., DEPTH], t, rtol=0.01)


# ==================================================================
# 6. Stability
# ==================================================================
def test_zero_opacity_gaussians_render_the_background():
    g, _ = layer(extent=1.0, opacity=0.0)
    cam = camera([0, -3, 3], [0, 0, 0], size=16)
    img, _ = render({"integrator": {"type": "invrgbl", "samples": 8}, "ground": g, "sky": sky(),
                     "sensor": cam}, spp=2)
    bg, _ = render({"integrator": {"type": "invrgbl", "samples": 8}, "sky": sky(), "sensor": cam}, spp=2)
    assert np.allclose(img[..., RGB], bg[..., RGB], rtol=1e-5, atol=1e-6)
    assert np.all(img[..., ALPHA] == 0)


@pytest.mark.parametrize("bounces,coat", [(0, False), (1, False), (1, True)])
@pytest.mark.parametrize("case", ["zero_size", "huge", "tau_zero", "tau_one", "grazing"])
def test_degenerate_inputs_give_finite_output(case, bounces, coat):
    scale, tau = 0.1, 0.4
    origin, target = [0, -3, 3], [0, 0, 0]
    if case == "zero_size":
        scale = 0.0
    elif case == "huge":
        scale = 1e3
    elif case == "tau_zero":
        tau = 0.0
    elif case == "tau_one":
        tau = 1.0
    elif case == "grazing":
        origin, target = [0, -3, 0.002], [0, 0, 0]
    g, c = layer(extent=1.0, roughness=tau)
    n = c.shape[0]
    g["scales"] = mi.TensorXf(np.tile([[scale, scale, scale * 1e-2]], (n, 1)).astype(np.float32))
    img, _ = render({"integrator": {"type": "invrgbl", "samples": 8, "bounces": bounces,
                                    "diffuse_fresnel": coat},
                     "ground": g, "sky": sky(), "blob": single_gaussian([0, 0, 0.5], [0.2, 0.2, 0.2]),
                     "sensor": camera(origin, target, size=16)}, spp=2)
    assert np.all(np.isfinite(img))
    assert np.all(img[..., RGB] >= 0)


def test_nan_parameters_are_refused_with_a_clear_message(tmp_path):
    g, c = layer(extent=0.3)
    bad = c.copy()
    bad[3, 1] = np.nan
    g["centers"] = mi.TensorXf(bad)
    with pytest.raises(Exception, match=r"centers.*NaN.*index 3"):
        mi.load_dict(g)

    from mi_invrgbl.physics.gaussian_ply import GaussianCloud, write_ply
    n = 4
    cloud = GaussianCloud(centers=np.zeros((n, 3), np.float32), scales=np.full((n, 3), 0.1, np.float32),
                          quaternions=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                          opacities=np.full(n, 0.5, np.float32),
                          albedo=np.array([[0.5, np.nan, 0.5]] + [[0.5] * 3] * 3, np.float32))
    path = str(tmp_path / "nan.ply")
    write_ply(path, cloud)
    with pytest.raises(Exception, match=r"nan\.ply.*albedo.*NaN"):
        mi.load_dict({"type": "gaussians", "filename": path})


# ==================================================================
# Diffuse light through a dielectric coat (diffuse_fresnel)
# ==================================================================
def test_diffuse_through_a_coat_is_dimmed_in_and_out():
    """An opaque Gaussian layer under a uniform sky (order-0 SH, no sun),
    seen at oblique angles: the diffuse radiance with ``diffuse_fresnel`` is
    the plain one times the coat's way out at the viewer's angle
    (:func:`coat.way_out`, the layer's roughness) and times the
    cosine-weighted mean of its transmittance over the sky (2 int T(mu) mu
    dmu, integrated here over the table). The coat's tables are checked
    against Mitsuba's ``roughplastic`` in ``tests/test_coat.py``; this checks
    that the integrator applies them on both ways. The specular part (a
    render with albedo 0) does not change with the flag."""
    g0, _ = layer(albedo=(0.0, 0.0, 0.0), roughness=0.6)
    g1, _ = layer(albedo=(0.6, 0.4, 0.3), roughness=0.6)
    uniform = "2.0 2.0 2.0"      # radiance 2 * Y_0 = 0.56 everywhere

    def shot(ground, coat):
        img, scene = render({"integrator": {"type": "invrgbl", "samples": 256,
                                            "diffuse_fresnel": coat},
                             "ground": ground, "sky": sky(sun_irradiance=None, sh=uniform),
                             "sensor": camera([0, -3.0, 1.2], [0, 0, 0], fov=50, size=24)},
                            spp=8)
        return img, scene

    coat, scene = shot(g1, True)
    plain, _ = shot(g1, False)
    spec_plain, _ = shot(g0, False)
    spec_coat, _ = shot(g0, True)
    p, _ = ground_hits(scene)
    _, d = pixel_rays(scene)
    m = (np.abs(p[..., 0]) < 1.2) & (np.abs(p[..., 1]) < 1.2) & (coat[..., ALPHA] > 0.99)
    assert m.sum() > 100
    np.testing.assert_allclose(spec_coat[m][:, RGB], spec_plain[m][:, RGB], rtol=1e-5, atol=1e-7)
    from mi_invrgbl.physics import coat as coat_model
    mu = (np.arange(20000) + 0.5) / 20000
    t_in = 2.0 * np.mean(np.array(coat_model.transmission(mi.Float(mu), mi.Float(0.6), 0.04)) * mu)
    t_out = np.array(coat_model.way_out(mi.Float(-d[..., 2][m]), mi.Float(0.6), 0.04))
    ratio = (coat[m][:, RGB] - spec_plain[m][:, RGB]) / (plain[m][:, RGB] - spec_plain[m][:, RGB])
    want = (t_in * t_out)[:, None]
    cos_o = -d[..., 2][m]
    print("view angles %.0f-%.0f deg, ratio/want: median %.4f, 90th pct |err| %.4f" % (
        np.degrees(np.arccos(cos_o.max())), np.degrees(np.arccos(cos_o.min())),
        np.median(ratio / want), np.percentile(np.abs(ratio / want - 1), 90)))
    assert np.percentile(np.abs(ratio / want - 1), 90) < 0.01
