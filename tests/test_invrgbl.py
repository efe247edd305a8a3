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
