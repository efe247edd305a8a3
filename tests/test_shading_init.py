"""Stage 2's starting light and albedo (mi_invrgbl/fit/shading_init.py).

Synthetic Gaussians with known albedo, sky term, sun irradiance and shadows
are shaded with ``c = a (D + E v cos / pi)``; the estimators must recover
``E``, find shadows the trace missed, drop shadows it invented, and give back
the albedo.
"""

import numpy as np
import pytest

from mi_invrgbl.fit import shading_init


def _street(n=4000, e_sun=(3.0, 2.8, 2.5), missed=0.5, invented=0.0, seed=0, bounce=0.0):
    rng = np.random.default_rng(seed)
    up = np.tile([0.0, 0.0, 1.0], (n, 1))
    wall = np.tile([0.0, 1.0, 0.0], (n // 4, 1))
    normals = np.concatenate([up, wall])
    g = len(normals)
    lidar = rng.uniform(0.2, 0.8, g)
    albedo = lidar[:, None] * np.array([0.9, 1.0, 1.1])      # RGB follows LiDAR
    sky = rng.uniform(0.15, 0.3, (g, 1)) * np.array([0.8, 0.9, 1.1])
    cos = np.where(normals[:, 2] > 0.5, 0.8, 0.4)
    true_v = (rng.uniform(size=g) > 0.3).astype(float)
    E = np.array(e_sun)
    # Light passed on by sunlit neighbours: stronger where the sun is blocked
    # (a shadowed facade faces the sunlit street), ``bounce`` times the sky term.
    bounce_term = bounce * sky * np.where(true_v > 0, 0.5, 1.0)[:, None]
    colour = albedo * (sky + bounce_term + E[None] * (true_v * cos)[:, None] / np.pi)
    # The trace misses a share of the shadows (geometry the fit lacks).
    traced = true_v.copy()
    shadow = np.nonzero(true_v == 0)[0]
    traced[shadow[rng.uniform(size=shadow.size) < missed]] = 1.0
    # ... and casts some from geometry the scene lacks (walls above a roof).
    sunlit = np.nonzero(true_v == 1)[0]
    traced[sunlit[rng.uniform(size=sunlit.size) < invented]] = 0.0
    return dict(colour=colour, sky=sky, E=E, true_v=true_v, traced=traced, cos=cos, bounce=bounce_term,
                normals=normals, lidar=lidar, albedo=albedo, seen=np.ones(g, bool))


def test_irradiance_recovered_when_the_trace_is_right():
    s = _street(missed=0.0)
    E, groups = shading_init.estimate_sun_irradiance(s["colour"], s["sky"], s["traced"], s["cos"],
                                                     s["normals"], s["seen"], s["lidar"])
    assert groups == 2
    assert np.allclose(E, s["E"], rtol=0.1), E


def test_missed_shadows_are_found_from_the_lidar_albedo():
    s = _street(missed=0.5)
    v, lowered, raised = shading_init.visibility_from_lidar_albedo(
        s["colour"], s["sky"], s["E"], s["traced"], s["cos"], s["seen"], s["lidar"])
    missed = (s["true_v"] == 0) & (s["traced"] == 1)
    lit = s["true_v"] == 1
    assert missed.any() and lowered > 0 and raised == 0
    assert np.mean(v[missed] < 0.3) > 0.95          # the missed shadows are found
    assert np.mean(v[lit] >= 0.5) > 0.99            # sunlit Gaussians stay sunlit
    # With the shadows found, the albedo comes back (up to noise-free 1 %).
    sun = s["E"][None] * (v * s["cos"])[:, None] / np.pi
    a = shading_init.albedo_from_shading(s["colour"], s["sky"], sun)
    assert np.allclose(a, np.clip(s["albedo"], 0.02, 1.0), rtol=0.02, atol=1e-3)
    # The trace alone bakes the missed shadows into the albedo.
    sun_traced = s["E"][None] * (s["traced"] * s["cos"])[:, None] / np.pi
    baked = shading_init.albedo_from_shading(s["colour"], s["sky"], sun_traced)
    assert np.median(baked[missed].sum(1) / s["albedo"][missed].sum(1)) < 0.5


def test_invented_shadows_are_dropped_and_true_ones_kept():
    s = _street(missed=0.0, invented=0.3)
    v, lowered, raised = shading_init.visibility_from_lidar_albedo(
        s["colour"], s["sky"], s["E"], s["traced"], s["cos"], s["seen"], s["lidar"])
    invented = (s["true_v"] == 1) & (s["traced"] == 0)
    assert invented.any() and raised > 0.1 and lowered == 0
    assert np.mean(v[invented] >= 0.7) > 0.95       # the invented shadows are gone
    assert np.mean(v[s["true_v"] == 0] < 0.3) > 0.99  # true shadows stay
    # Invented shadows would otherwise brighten those albedos by the sun/sky ratio.
    sun = s["E"][None] * (v * s["cos"])[:, None] / np.pi
    a = shading_init.albedo_from_shading(s["colour"], s["sky"], sun)
    assert np.allclose(a, np.clip(s["albedo"], 0.02, 1.0), rtol=0.02, atol=1e-3)


def test_bounce_belongs_in_the_ambient_term():
    # Shadowed Gaussians lit by sky and bounce: counting the bounce as sky
    # (leaving it out of the ambient term) underestimates the sun.
    s = _street(missed=0.0, bounce=1.0)
    args = (s["traced"], s["cos"], s["normals"], s["seen"], s["lidar"])
    sky_only, _ = shading_init.estimate_sun_irradiance(s["colour"], s["sky"], *args)
    ambient, _ = shading_init.estimate_sun_irradiance(s["colour"], s["sky"] + s["bounce"], *args)
    assert np.allclose(ambient, s["E"], rtol=0.1), ambient
    assert np.all(sky_only < 0.8 * s["E"]), sky_only


def test_sun_and_visibility_settle_together():
    # Most shadows missed by the trace: the first estimate is low (the
    # sunlit group holds shadowed Gaussians); the alternation finds the
    # missed shadows and brings the irradiance back.
    s = _street(missed=0.8, bounce=0.5)
    amb = s["sky"] + s["bounce"]
    first, _ = shading_init.estimate_sun_irradiance(s["colour"], amb, s["traced"], s["cos"],
                                                    s["normals"], s["seen"], s["lidar"])
    level = float(first @ np.array([0.2126, 0.7152, 0.0722]))
    E, v, source, lowered, raised = shading_init.settle_sun_and_visibility(
        s["colour"], amb, first, "facings", s["traced"], s["cos"], s["normals"], s["seen"],
        s["lidar"], level)
    missed = (s["true_v"] == 0) & (s["traced"] == 1)
    assert source == "facings" and lowered > 0
    assert np.allclose(E, s["E"], rtol=0.01) and np.all(first < 0.97 * s["E"]), (first, E)
    assert np.mean(v[missed] < 0.3) > 0.95
    # Nothing to correct: the trace and the estimate stand.
    t = _street(missed=0.0)
    E0, _ = shading_init.estimate_sun_irradiance(t["colour"], t["sky"], t["traced"], t["cos"],
                                                 t["normals"], t["seen"], t["lidar"])
    E1, v1, _, lowered, raised = shading_init.settle_sun_and_visibility(
        t["colour"], t["sky"], E0, "facings", t["traced"], t["cos"], t["normals"], t["seen"],
        t["lidar"], 3.0)
    assert lowered == 0 and raised == 0 and np.allclose(E1, E0) and np.array_equal(v1, t["traced"])


def test_settling_without_groups_keeps_the_start():
    # No shadowed Gaussian anywhere: no estimate to alternate with, so the
    # starting irradiance and its source stand; NaN colours stay out.
    s = _street(missed=0.0)
    lit = s["true_v"] > 0
    colour = s["colour"][lit].copy()
    colour[:5] = np.nan
    E, v, source, lowered, raised = shading_init.settle_sun_and_visibility(
        colour, s["sky"][lit], np.array([2.0, 2.0, 2.0]), "selection", s["traced"][lit],
        s["cos"][lit], s["normals"][lit], s["seen"][lit], s["lidar"][lit], 2.0)
    assert np.allclose(E, 2.0) and source == "selection"
    assert np.all(np.isfinite(v)) and np.all(np.isfinite(E))


def test_no_groups_no_estimate_and_nan_colour_is_ignored():
    s = _street()
    all_lit = np.ones_like(s["traced"])
    E, groups = shading_init.estimate_sun_irradiance(s["colour"], s["sky"], all_lit, s["cos"],
                                                     s["normals"], s["seen"], s["lidar"])
    assert E is None and groups == 0
    colour = s["colour"].copy()
    colour[::7] = np.nan
    E, _ = shading_init.estimate_sun_irradiance(colour, s["sky"], s["true_v"], s["cos"],
                                                s["normals"], s["seen"], s["lidar"])
    assert np.all(np.isfinite(E))
    v, _, _ = shading_init.visibility_from_lidar_albedo(colour, s["sky"], s["E"], s["traced"],
                                                        s["cos"], s["seen"], s["lidar"])
    assert np.all(np.isfinite(v)) and v.min() >= 0 and v.max() <= 1


@pytest.mark.parametrize("e", [0.0, 1e-6])
def test_no_sun_leaves_visibility_alone(e):
    s = _street()
    v, lowered, raised = shading_init.visibility_from_lidar_albedo(
        s["colour"], s["sky"], np.full(3, e), s["traced"], s["cos"], s["seen"], s["lidar"])
    assert lowered == 0.0 and raised == 0.0
    assert np.array_equal(v, s["traced"])


def test_sun_irradiance_falls_back_to_the_selection_level_when_facings_disagree():
    from mi_invrgbl.physics.colour import LUMINANCE
    from mi_invrgbl.fit.shading_init import MAX_EXCESS, reconcile_sun_irradiance
    level = 2.0
    agree = np.array([2.2, 2.5, 2.6])
    E, source = reconcile_sun_irradiance(agree, level)
    assert source == "facings" and np.allclose(E, agree)
    # A collapsed estimate (as one KITTI fit started from) keeps its colour
    # and takes the selection's level.
    collapsed = np.array([0.09, 0.10, 0.09])
    E, source = reconcile_sun_irradiance(collapsed, level)
    assert source.startswith("selection") and np.isclose(E @ LUMINANCE, level)
    assert np.allclose(E / E.sum(), collapsed / collapsed.sum())
    # Brighter than the selection's (biased-low) level: trusted up to MAX_EXCESS.
    brighter = agree * 4.5
    E, source = reconcile_sun_irradiance(brighter, level)
    assert source == "facings" and np.allclose(E, brighter)
    too_bright = agree * (MAX_EXCESS + 1)
    assert reconcile_sun_irradiance(too_bright, level)[1].startswith("selection")
    E, source = reconcile_sun_irradiance(None, level)
    assert np.allclose(E, level) and source.startswith("selection")
    assert np.all(np.isfinite(reconcile_sun_irradiance(np.zeros(3), level)[0]))


def test_light_is_raised_until_the_albedo_stops_clipping():
    from mi_invrgbl.fit.shading_init import ALBEDO_CEILING, albedo_from_shading, light_scale
    s = _street(missed=0.0)
    shading = s["sky"] + s["E"][None] * (s["traced"] * s["cos"])[:, None] / np.pi
    # Light that explains the colours with plausible albedo is left alone.
    assert light_scale(s["colour"], shading, s["seen"]) == 1.0
    # A sky term 20x too dark (a bridge overhead, no interreflection in the
    # model): most albedo would clip; the scale brings the 95th percentile
    # back under the ceiling and the albedo reproduces the colours again.
    dark = shading / 20.0
    assert np.mean(albedo_from_shading(s["colour"], dark, 0.0) >= 1.0) > 0.5
    k = light_scale(s["colour"], dark, s["seen"])
    assert 10.0 < k < 40.0
    albedo = albedo_from_shading(s["colour"], k * dark, 0.0)
    assert np.quantile(albedo.max(axis=1), 0.95) <= ALBEDO_CEILING + 1e-9
    assert np.mean(np.abs(albedo * k * dark - s["colour"]) < 1e-9) > 0.94
    # Unseen, NaN and zero-shading Gaussians do not drive it; nothing seen: 1.
    bad = s["colour"].copy()
    bad[:10] = np.nan
    assert np.isfinite(light_scale(bad, dark, s["seen"]))
    assert light_scale(s["colour"], dark, np.zeros_like(s["seen"])) == 1.0
    assert light_scale(s["colour"], np.zeros_like(dark), s["seen"]) <= 100.0


def test_an_overruled_facing_estimate_is_recognised():
    from mi_invrgbl.fit.shading_init import facings_overruled, reconcile_sun_irradiance
    _, agree = reconcile_sun_irradiance(np.array([2.0, 2.0, 2.0]), 1.5)
    _, disagree = reconcile_sun_irradiance(np.array([30.0, 30.0, 30.0]), 1.5)
    _, none = reconcile_sun_irradiance(None, 1.5)
    assert not facings_overruled(agree) and facings_overruled(disagree)
    assert not facings_overruled(none)      # no facing estimate: nothing to try instead


def _lit_blocks(seed=0, n=3000):
    """Gaussians in 4 m blocks of one material each (LiDAR albedo and RGB
    albedo shared within a block), half of them facing up and half a wall,
    a third of them in shadow."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(0.0, 12.0, (n, 3))
    block = np.floor(centres[:, :2] / 4.0).astype(int) @ np.array([3, 1])
    lidar = np.array([0.15, 0.3, 0.45, 0.6, 0.75, 0.2, 0.35, 0.5, 0.65])[block]
    albedo = lidar[:, None] * np.array([0.8, 1.0, 1.2])
    normals = np.where((rng.uniform(size=n) < 0.5)[:, None], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0])
    sky = np.full((n, 3), 0.25)
    v = (rng.uniform(size=n) > 0.33).astype(float)
    sun = np.array([0.3, 0.5, 0.81]) / np.linalg.norm([0.3, 0.5, 0.81])
    E = 4.0
    cos = np.maximum(normals @ sun, 0.0)
    colour = albedo * (sky + E * (v * cos)[:, None] / np.pi)
    return dict(centres=centres, lidar=lidar, albedo=albedo, normals=normals, sky=sky, v=v, sun=sun,
                E=E, colour=colour)


def _start_albedo(s, E, sun, v):
    cos = np.maximum(s["normals"] @ sun, 0.0)
    return shading_init.albedo_from_shading(s["colour"], s["sky"], E * (v * cos)[:, None] / np.pi)


def test_albedo_spread_is_least_under_the_true_light():
    s = _lit_blocks()
    w = np.ones(len(s["lidar"]))
    true = shading_init.albedo_spread(_start_albedo(s, s["E"], s["sun"], s["v"]), s["lidar"],
                                      s["centres"], w)
    assert true is not None and true < 1e-6
    # A weak sun leaves the shadows in the albedo...
    weak = shading_init.albedo_spread(_start_albedo(s, s["E"] / 6, s["sun"], s["v"]), s["lidar"],
                                      s["centres"], w)
    # ... a wrong direction (and the shadows it would cast elsewhere) puts its own there.
    other = np.array([0.64, 0.63, 0.44]) / np.linalg.norm([0.64, 0.63, 0.44])
    v_other = np.random.default_rng(1).permutation(s["v"])
    wrong = shading_init.albedo_spread(_start_albedo(s, s["E"], other, v_other), s["lidar"],
                                       s["centres"], w)
    assert weak > 0.05 and wrong > 0.05, (weak, wrong)


def test_albedo_spread_ignores_unseen_nan_and_small_groups():
    s = _lit_blocks()
    a = _start_albedo(s, s["E"] / 6, s["sun"], s["v"])
    w = np.ones(len(a))
    base = shading_init.albedo_spread(a, s["lidar"], s["centres"], w)
    # Unseen Gaussians with any albedo do not count.
    a2, w2 = a.copy(), w.copy()
    a2[:100] = 1e-3
    w2[:100] = 0.0
    assert np.isclose(shading_init.albedo_spread(a2, s["lidar"], s["centres"], w2),
                      shading_init.albedo_spread(a[100:], s["lidar"][100:], s["centres"][100:], w[100:]))
    # NaN albedo and a LiDAR albedo of 0 or NaN drop the Gaussian.
    a3, rho3 = a.copy(), s["lidar"].copy()
    a3[0] = np.nan
    rho3[1], rho3[2] = 0.0, np.nan
    out = shading_init.albedo_spread(a3, rho3, s["centres"], w)
    assert np.isfinite(out) and abs(out - base) < 0.1 * base
    # No group with enough Gaussians, nothing seen, nothing at all: None.
    assert shading_init.albedo_spread(a[:3], s["lidar"][:3], s["centres"][:3], w[:3]) is None
    assert shading_init.albedo_spread(a, s["lidar"], s["centres"], np.zeros_like(w)) is None
    assert shading_init.albedo_spread(a[:0], s["lidar"][:0], s["centres"][:0], w[:0]) is None


def test_the_start_with_the_least_spread_wins_within_the_margin():
    m = shading_init.START_PSNR_MARGIN
    # Within the margin the spread decides, beyond it the images rule the start out.
    assert shading_init.choose_start([27.2, 27.2 + 0.9 * m], [0.05, 0.20]) == 0
    assert shading_init.choose_start([27.2, 27.2 + 1.1 * m], [0.05, 0.20]) == 1
    assert shading_init.choose_start([18.1, 14.0, 17.8], [0.30, 0.01, 0.25]) == 2
    # Without a spread for every start in reach, the best PSNR.
    assert shading_init.choose_start([27.2, 27.8], [0.05, None]) == 1
    assert shading_init.choose_start([27.2, 27.8], [None, 0.2]) == 1
    assert shading_init.choose_start([27.2, 29.0], [None, 0.2]) == 1
    assert shading_init.choose_start([27.2], [None]) == 0


def test_a_start_that_could_not_be_scored_is_never_chosen_for_its_spread():
    inf = -np.inf
    assert shading_init.choose_start([inf, 27.0, 26.5], [0.01, 0.3, 0.2]) == 2
    assert shading_init.choose_start([inf, inf], [0.3, 0.2]) == 1
    assert shading_init.choose_start([27.0, 26.8], [np.nan, 0.2]) == 0


def test_light_level_search_stops_once_the_score_falls():
    from mi_invrgbl.fit.shading_init import search_levels
    levels = [1.0, 1.2, 1.4, 1.7, 2.0]

    def run(curve):
        asked = []

        def score_at(k):
            asked.append(k)
            return curve[levels.index(k)]
        return search_levels(levels, score_at), asked
    # Falling from the first raise (KITTI's 8-minute start): two scored, 1x kept,
    # and the scene holds 1.2x, so the caller sets 1x again.
    (best, scores, last), asked = run([18.93, 18.73, 18.43, 18.04, 17.57])
    assert (best, last) == (1.0, 1.2) and asked == [1.0, 1.2] and set(scores) == {1.0, 1.2}
    # Rising then falling: stops one past the peak.
    (best, scores, last), asked = run([16.0, 17.0, 17.5, 17.2, 18.0])
    assert best == 1.4 and asked == [1.0, 1.2, 1.4, 1.7] and last == 1.7
    # Rising throughout (a dark scene under a bridge): every level, the last kept.
    (best, _, last), asked = run([8.0, 11.0, 13.0, 15.0, 16.0])
    assert best == last == 2.0 and asked == levels
    # A score that is not finite counts as the worst, and ends the search.
    (best, scores, _), asked = run([18.0, float("nan"), 19.0, 19.5, 20.0])
    assert best == 1.0 and scores[1.2] == -np.inf and asked == [1.0, 1.2]


def _clipped_start(missed, invented, albedo_scale):
    """A start whose albedo clipped: ``_street`` with its albedo scaled (bright
    surfaces in invented shadows need more than 1, dark ones in missed shadows
    less than the floor), the albedo made from the traced visibility."""
    s = _street(missed=missed, invented=invented)
    s["albedo"] = s["albedo"] * albedo_scale
    s["colour"] = s["albedo"] * (s["sky"] + s["E"][None] * (s["true_v"] * s["cos"])[:, None] / np.pi)
    per_v = s["E"][None] * s["cos"][:, None] / np.pi
    a = shading_init.albedo_from_shading(s["colour"], s["sky"], per_v * s["traced"][:, None])
    return s, per_v, a


def _reproduced(s, per_v, v):
    a = shading_init.albedo_from_shading(s["colour"], s["sky"], per_v * v[:, None])
    return a * (s["sky"] + per_v * v[:, None])


@pytest.mark.parametrize("lidar", [True, False])
def test_clipped_albedo_takes_the_visibility_that_reproduces_the_colour(lidar):
    # Bright surfaces (albedo up to 1.17) under invented shadows clip at 1.
    s, per_v, a = _clipped_start(missed=0.0, invented=0.3, albedo_scale=1.3)
    top = (a >= 0.999).any(axis=1)
    assert top.mean() > 0.1
    v, raised, lowered = shading_init.unclip_visibility(
        s["colour"], s["sky"], per_v, s["traced"], a, s["seen"], s["lidar"] if lidar else None)
    assert raised > 0.05 and lowered == 0
    assert np.all(v >= s["traced"]) and v.min() >= 0 and v.max() <= 1   # only raised
    before = np.abs(_reproduced(s, per_v, s["traced"]) - s["colour"]).mean()
    after = np.abs(_reproduced(s, per_v, v) - s["colour"]).mean()
    assert after < 0.3 * before, (before, after)
    # Gaussians that did not clip keep the trace's visibility.
    assert np.array_equal(v[~top], s["traced"][~top])
    # With the LiDAR albedo, the invented shadows come out sunlit.
    invented = (s["true_v"] == 1) & (s["traced"] == 0) & top
    if lidar:
        assert np.mean(v[invented] > 0.9) > 0.9


def test_albedo_at_the_floor_takes_less_sun_and_unseen_gaussians_keep_theirs():
    # Dark surfaces in shadows the trace missed: the sunlit render is too
    # bright for them even at the albedo's floor.
    s, per_v, a = _clipped_start(missed=1.0, invented=0.0, albedo_scale=0.04)
    floor = (a <= 0.0201).any(axis=1)
    assert floor.mean() > 0.05
    seen = s["seen"].copy()
    seen[::2] = False
    v, raised, lowered = shading_init.unclip_visibility(s["colour"], s["sky"], per_v, s["traced"],
                                                        a, seen, s["lidar"])
    assert lowered > 0 and raised == 0 and np.all(v <= s["traced"])
    assert np.array_equal(v[~seen], s["traced"][~seen])
    changed = floor & seen
    err = lambda vv: np.abs(_reproduced(s, per_v, vv) - s["colour"])[changed].mean()
    assert err(v) < 0.5 * err(s["traced"])


def test_unclip_stays_finite_on_nan_and_without_sun():
    s, per_v, a = _clipped_start(missed=0.5, invented=0.3, albedo_scale=1.3)
    colour = s["colour"].copy()
    colour[::5] = np.nan
    v, _, _ = shading_init.unclip_visibility(colour, s["sky"], per_v, s["traced"], a, s["seen"],
                                             s["lidar"])
    assert np.all(np.isfinite(v)) and v.min() >= 0 and v.max() <= 1
    v0, raised, lowered = shading_init.unclip_visibility(s["colour"], s["sky"], per_v * 0.0,
                                                         s["traced"], a, s["seen"], s["lidar"])
    assert raised == lowered == 0 and np.array_equal(v0, s["traced"])
