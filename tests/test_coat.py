"""The rough dielectric coat of the diffuse term (``mi_invrgbl.physics.coat``)
against independent references: Mitsuba's own ``roughplastic`` BSDF (whose
diffuse lobe is the coat's), the Fresnel equations in numpy for a smooth
coat, and central finite differences for the gradients."""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_invrgbl.physics import coat


def fresnel_np(cos, eta=1.5):
    """Unpolarised Fresnel reflectance of a smooth dielectric, from the
    textbook s/p amplitudes (numpy, float64)."""
    c = np.clip(np.asarray(cos, np.float64), 0.0, 1.0)
    ct = np.sqrt(np.maximum(1.0 - (1.0 - c * c) / eta ** 2, 0.0))
    rs = (c - eta * ct) / (c + eta * ct)
    rp = (eta * c - ct) / (eta * c + ct)
    return 0.5 * (rs * rs + rp * rp)


def roughplastic_diffuse(alpha, cos_i, cos_o):
    """Mitsuba's ``roughplastic`` (GGX, IOR 1.5, linear) diffuse lobe over
    the Lambertian ``1 / pi``: its value with diffuse reflectance 1 minus its
    value with 0, light and viewer 90 degrees apart in azimuth."""
    out = []
    for rho in (1.0, 0.0):
        bsdf = mi.load_dict({"type": "roughplastic", "distribution": "ggx", "alpha": alpha,
                             "int_ior": 1.5, "ext_ior": 1.0,
                             "diffuse_reflectance": {"type": "rgb", "value": [rho] * 3}})
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.n = mi.Normal3f(0, 0, 1)
        si.sh_frame = mi.Frame3f(si.n)
        si.wi = mi.Vector3f(float(np.sqrt(1 - cos_o ** 2)), 0.0, float(cos_o))
        wo = mi.Vector3f(0.0, float(np.sqrt(1 - cos_i ** 2)), float(cos_i))
        out.append(float(np.array(bsdf.eval(mi.BSDFContext(), si, wo)).ravel()[0]))
    return (out[0] - out[1]) * np.pi / cos_i


def test_a_smooth_coat_passes_one_minus_fresnel():
    cos = np.array([0.0, 0.01, 0.05, 0.2, 0.5, 0.8, 1.0])
    t = np.array(coat.transmission(mi.Float(cos), mi.Float(0.0), 0.04))
    # Between the table's cosines (1/64 apart) the lookup is linear: exact
    # to 3e-4 from 0.2 up, within 5e-3 where 1 - F climbs steeply from 0.
    np.testing.assert_allclose(t[3:], 1.0 - fresnel_np(cos[3:]), atol=3e-4)
    np.testing.assert_allclose(t[1:3], 1.0 - fresnel_np(cos[1:3]), atol=5e-3)
    assert t[0] == 0.0
    # Two-sided: lit or seen from behind, the same transmission.
    np.testing.assert_array_equal(
        np.array(coat.transmission(mi.Float(-cos), mi.Float(0.0), 0.04)), t)


@pytest.mark.parametrize("alpha", [0.05, 0.3, 0.5, 0.8, 1.0])
def test_the_coated_diffuse_lobe_matches_mitsubas_roughplastic(alpha):
    """The coat's factor on the Lambertian lobe, T(in) T(out) / (eta^2 (1 -
    R_in)), against ``roughplastic``'s diffuse lobe at angles from head-on to
    87 degrees. The two tabulate the same integrals with different
    quadratures (``roughplastic`` averages R_in over evenly spaced cosines
    with the end points counted fully): within 4 % everywhere, and the
    factor's shape over the angles within 1.5 %."""
    cosines = [1.0, 0.7, 0.4, 0.17, 0.05]
    mine, ref = [], []
    for ci in cosines:
        for co in cosines:
            mine.append(float(np.array(coat.transmission(mi.Float(ci), mi.Float(alpha), 0.04)
                                       * coat.way_out(mi.Float(co), mi.Float(alpha), 0.04))[0]))
            ref.append(roughplastic_diffuse(alpha, ci, co))
    mine, ref = np.array(mine), np.array(ref)
    ratio = mine / ref
    print("alpha %.2f: ratio %.4f-%.4f; factor %.3f (head-on) to %.3f" % (
        alpha, ratio.min(), ratio.max(), ref[0], ref[-1]))
    assert np.all(np.abs(ratio - 1) < 0.04)
    assert np.all(np.abs(ratio / np.median(ratio) - 1) < 0.015)


def test_rough_coats_pass_less_light_than_smooth_ones():
    """What the street needs the coat for: at GGX alpha 0.8 the coated lobe
    keeps under half of what a smooth coat keeps head-on, and less still at
    grazing angles. Most of it is the light the base sends up again: a rough
    coat's masking loses what a smooth one reflects back down, so less is
    recycled (``inner_scale``)."""
    cos = mi.Float([1.0, 0.17])

    def lobe(alpha):
        a = mi.Float(alpha)
        return np.array(coat.transmission(cos, a, 0.04) * coat.way_out(cos, a, 0.04))
    smooth, rough = lobe(0.0), lobe(0.8)
    assert np.all(rough < 0.5 * smooth)
    assert rough[1] / rough[0] < smooth[1] / smooth[0]
    assert float(np.array(coat.inner_scale(mi.Float(0.8), 0.04))[0]) < \
        0.6 * float(np.array(coat.inner_scale(mi.Float(0.0), 0.04))[0])


def test_coat_gradients_are_finite_and_match_finite_differences():
    cos = np.array([0.0, 1e-4, 0.05, 0.33, 0.71, 0.999, 1.0])
    rough = np.array([0.0, 1e-4, 0.31, 0.52, 0.77, 0.999, 1.0])
    x, a = mi.Float(cos), mi.Float(rough)
    dr.enable_grad(x, a)
    dr.backward(dr.sum(coat.transmission(x, a, 0.04) * coat.way_out(x, a, 0.04)))
    gx, ga = np.array(dr.grad(x)), np.array(dr.grad(a))
    assert np.all(np.isfinite(gx)) and np.all(np.isfinite(ga))

    def f(c, r):
        return np.array(coat.transmission(mi.Float(c), mi.Float(r), 0.04)
                        * coat.way_out(mi.Float(c), mi.Float(r), 0.04), np.float64)
    # Inside the table's cells (away from its nodes, where the bilinear
    # lookup has a kink), central differences agree.
    inner = slice(2, 5)
    h = 1e-3
    fd_x = (f(cos + h, rough) - f(cos - h, rough)) / (2 * h)
    fd_a = (f(cos, rough + h) - f(cos, rough - h)) / (2 * h)
    np.testing.assert_allclose(gx[inner], fd_x[inner], rtol=0.03, atol=2e-3)
    np.testing.assert_allclose(ga[inner], fd_a[inner], rtol=0.03, atol=2e-3)


@pytest.mark.parametrize("elevation,roughness", [(8, 0.9), (15, 0.3), (30, 0.6), (60, 0.9)])
def test_a_coated_layer_under_a_constant_sky_matches_roughplastic(elevation, roughness):
    """The whole coated shading (the sky's glossy reflection through the
    Gaussian's M sky directions, and the coated diffuse term) of an opaque
    Gaussian layer against a ``roughplastic`` plane under Mitsuba's
    ``path``, seen from ``elevation`` degrees above it. Measured: the
    specular reflection alone (albedo 0) 0.85-0.99 of the reference, the
    total with albedo 0.3 0.96-1.01 (the M = 64 quadrature of the lobe)."""
    from test_invrgbl import ALPHA, camera, ground_hits, layer, render
    from mi_invrgbl.physics.sh import Y0
    radiance = 0.5
    e = np.radians(elevation)
    cam = camera([0, -4 * np.cos(e), 4 * np.sin(e)], [0, 0, 0], fov=10)
    ratios = []
    for albedo in (0.0, 0.3):
        g, _ = layer(extent=4.0, albedo=(albedo,) * 3, roughness=roughness)
        sky = {"type": "shsun", "sh": "%f %f %f" % ((radiance / Y0,) * 3),
               "sun_direction": [0, 0, 1]}
        img_g, scene_g = render({"integrator": {"type": "invrgbl", "samples": 64, "shadowing": "smith",
                                                "diffuse_fresnel": True},
                                 "ground": g, "sky": sky, "sensor": cam}, spp=4)
        plane = {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale(6),
                 "bsdf": {"type": "roughplastic", "alpha": roughness, "distribution": "ggx",
                          "int_ior": 1.5, "diffuse_reflectance": {"type": "rgb", "value": [albedo] * 3}}}
        img_m, _ = render({"integrator": {"type": "path", "max_depth": 2}, "plane": plane,
                           "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [radiance] * 3}},
                           "sensor": cam}, spp=1024)
        p, _ = ground_hits(scene_g)
        covered = (np.abs(p[..., 0]) < 3) & (np.abs(p[..., 1]) < 3) & (img_g[..., ALPHA] > 0.99)
        assert covered.mean() > 0.5
        ratios.append(img_g[covered][:, 1].mean() / img_m[covered][:, 1].mean())
    print("elevation %d, roughness %.1f: specular alone %.3f, with albedo 0.3 %.3f"
          % (elevation, roughness, *ratios))
    assert 0.8 < ratios[0] < 1.05
    assert 0.93 < ratios[1] < 1.05
