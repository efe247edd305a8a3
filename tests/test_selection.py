"""Lighting selection decides from the images whether a scene needs a sun.

The same small street (tests/fit_scene.py) is rendered with and without a
sun; the selection must find the sun near its true direction in the first and
use none in the second. Scores are printed so a failure shows by how much.
"""

import dataclasses

import numpy as np
import pytest

from fit_scene import build
from mi_invrgbl.fit.init import load_state
from mi_invrgbl.fit.model_selection import choose_lighting
from mi_invrgbl.fit.runner import FitConfig, apply_lighting
from mi_invrgbl.fit.selection import SHARPEN_MARGIN, PatchRegression, surface_patches


def _select(tmp_path, sun, sharpen=True):
    path = build(str(tmp_path), n_frames=5, width=96, height=32, columns=128, sun=sun)
    ctx = load_state(path, FitConfig(output=str(tmp_path / "fit"), fit_width=96, lidar_columns=128,
                                     sun_candidates=32, seed=0, sharpen_sun=sharpen),
                     lambda *a: None)
    apply_lighting(ctx, choose_lighting(ctx))
    chosen = ctx.selection["sun"]
    print(chosen)
    return ctx, chosen


def test_sun_found_when_the_images_show_shadows(tmp_path):
    # One long straight wall casts the only shadow here, which fixes the
    # shadow edge but not the sun's direction along the wall: only the
    # decision is checked. The direction is scored on the synthetic street
    # by ``mi-invrgbl eval`` (sun_direction_error_deg).
    ctx, chosen = _select(tmp_path, sun=True)
    assert chosen["use_sun"], chosen
    assert chosen["gain"] > 0.05 and chosen["direction"][2] > 0
    assert ctx.use_sun
    assert np.allclose(np.array(ctx.params[ctx.sun_dir_key]).ravel(), chosen["direction"], atol=1e-5)
    # The used sun's direction was sharpened: the scan's refined peaks, none
    # explaining more than the direction kept.
    scan = chosen["scan"]
    assert scan["peaks"] and scan["directions_scanned"] > 32
    assert scan["found"]["gain"] == chosen["gain"]        # the decision's score is the search's
    top = max(scan["peaks"], key=lambda p: p["gain"])
    if scan["moved"]:
        assert top["gain"] > SHARPEN_MARGIN * chosen["gain"]
        assert np.allclose(top["direction"], chosen["direction"])
    else:
        assert top["gain"] <= SHARPEN_MARGIN * chosen["gain"]
        assert chosen["direction"] == scan["found"]["direction"]


def test_no_sun_in_an_overcast_scene(tmp_path):
    ctx, chosen = _select(tmp_path, sun=False)
    assert not chosen["use_sun"], chosen
    assert not ctx.use_sun
    # A rejected sun explaining at least the trial's share was sharpened for
    # the trial, and the decision stayed the search's.
    if chosen["gain"] >= 0.025:
        assert "scan" in chosen
    else:
        assert "scan" not in chosen


def test_the_sun_is_not_sharpened_unless_asked(tmp_path):
    # fit's default: the search's direction as it found it.
    ctx, chosen = _select(tmp_path, sun=True, sharpen=False)
    assert chosen["use_sun"] and "scan" not in chosen


def test_scan_peaks_are_the_best_separate_directions():
    from mi_invrgbl.fit.selection import scan_peaks
    up = np.array([0.0, 0.0, 1.0])
    tilt = lambda deg: np.array([np.sin(np.radians(deg)), 0.0, np.cos(np.radians(deg))])
    dirs = np.array([up, tilt(5), tilt(30), tilt(40), tilt(60)])
    gains = np.array([0.08, 0.09, 0.05, 0.06, 0.01])
    # 0 lies 5 degrees from 1, the best: left out; 2 lies 10 from 3: left out.
    assert scan_peaks(dirs, gains, count=4, separation=15.0) == [1, 3, 4]
    assert scan_peaks(dirs, gains, count=2, separation=15.0) == [1, 3]
    assert scan_peaks(dirs, gains, count=4, separation=1.0) == [1, 0, 3, 2]


def test_scan_peaks_keep_away_from_directions_taken_and_below_a_gain():
    from mi_invrgbl.fit.selection import scan_peaks
    tilt = lambda deg: np.array([np.sin(np.radians(deg)), 0.0, np.cos(np.radians(deg))])
    dirs = np.array([tilt(0), tilt(5), tilt(30), tilt(40), tilt(60)])
    gains = np.array([0.08, 0.09, 0.05, 0.06, 0.01])
    # 0 and 1 lie within 15 degrees of a direction already refined.
    assert scan_peaks(dirs, gains, count=4, separation=15.0, away_from=[tilt(3)]) == [3, 4]
    assert scan_peaks(dirs, gains, count=4, separation=15.0, min_gain=0.05) == [1, 3]


def test_a_sharpened_sun_never_explains_less(tmp_path):
    # sharpen_sun keeps what the search found unless a refined peak beats
    # it: handed a "found" direction that explains everything, it stays.
    from mi_invrgbl.fit.selection import PatchRegression, sharpen_sun, surface_patches
    ctx, chosen = _select(tmp_path, sun=True)
    rng = np.random.default_rng(0)
    G = 500
    centers = rng.uniform(-3, 3, (G, 3)); centers[:, 2] = 0.0
    normals = np.tile([0.0, 0.0, 1.0], (G, 1))
    lum = rng.uniform(0.2, 0.4, G)
    reg = PatchRegression(lum, surface_patches(centers, normals))
    found = (np.array([0.0, 0.0, 1.0]), np.array([1.0, 1.0]), np.ones(G))
    out = sharpen_sun(ctx.scene, centers, normals, lum, reg, found, scan_gaussians=200,
                      directions=24, peaks=2)
    assert not out["moved"] and out["best"] is found
    assert out["gaussians_scanned"] == 200 and len(out["peaks"]) == 2
    assert out["gains"][0] == 1.0 and out["directions"][0] is found[0]
    # A scene with fewer Gaussians than the scan's share scans all of them.
    out = sharpen_sun(ctx.scene, centers, normals, lum, reg, found, scan_gaussians=10 * G,
                      directions=24, peaks=2)
    assert out["gaussians_scanned"] == G and not out["moved"]


def test_a_colour_that_is_not_finite_is_left_out_of_the_shading_test():
    # Three patches of a flat ground, a shadow across each: the gain of the
    # shadow's feature with NaN colours (and a NaN weight) equals the gain
    # without those Gaussians, and stays finite.
    rng = np.random.default_rng(1)
    G = 300
    centers = rng.uniform(0, 6, (G, 3)); centers[:, 2] = 0.0
    normals = np.tile([0.0, 0.0, 1.0], (G, 1))
    patches = surface_patches(centers, normals)
    lit = (centers[:, 0] % 2.0 > 1.0).astype(float)
    lum = 0.2 * (1.0 + 2.0 * lit) * rng.uniform(0.9, 1.1, G)
    weights = rng.uniform(0.5, 1.0, G)
    bad = np.zeros(G, bool); bad[[3, 50, 120]] = True
    lum_nan = lum.copy(); lum_nan[bad] = np.nan
    w_nan = weights.copy(); w_nan[7] = np.inf; bad[7] = True
    gain, rho = PatchRegression(lum_nan, patches, w_nan).fit(lit)
    keep = ~bad
    ref_gain, ref_rho = PatchRegression(lum[keep], patches[keep], weights[keep]).fit(lit[keep])
    assert np.isfinite(gain) and gain > 0.5
    assert gain == pytest.approx(ref_gain, rel=1e-9) and rho == ref_rho
    # Nothing finite at all: no gain, not NaN.
    assert PatchRegression(np.full(G, np.nan), patches).fit(lit) == (0.0, rho_first())


def rho_first():
    from mi_invrgbl.fit.selection import SUN_RATIOS
    return float(SUN_RATIOS[0])


def test_sky_start_is_the_sky_that_renders_stage_1_best(tmp_path):
    # Stage 1's colours were fitted in front of stage 1's sky; the sky stage
    # 2 starts from is the candidate under which the validation images come
    # out best, and the scene's sky is left as it was.
    import drjit as dr
    import mitsuba as mi
    from mi_invrgbl.fit.model_selection import choose_sky_start
    path = build(str(tmp_path), n_frames=5, width=96, height=32, columns=128, sun=False)
    ctx = load_state(path, FitConfig(output=str(tmp_path / "fit"), fit_width=96, lidar_columns=128,
                                     sun_candidates=32, seed=0), lambda *a: None)
    choice = choose_lighting(ctx)
    good = np.asarray(choice.sh_init, np.float32)
    wrong = good * 0.25

    def pick(stage1_sky, sky_pixels_fit):
        ctx.params[ctx.sky_key] = mi.Float(stage1_sky.ravel())
        ctx.params.update()
        c = choose_sky_start(ctx, dataclasses.replace(choice, sh_init=sky_pixels_fit))
        after = np.array(dr.detach(ctx.params[ctx.sky_key]), np.float32)
        assert np.allclose(after, stage1_sky.ravel())        # the scene's sky untouched
        print(c.report["sh"]["start"])
        return c

    c = pick(wrong, good)
    assert c.report["sh"]["start"]["chosen"] == "sky pixels"
    assert np.allclose(c.sh_init, good)
    c = pick(good, wrong)
    assert c.report["sh"]["start"]["chosen"].startswith("stage 1")
    assert np.allclose(np.asarray(c.sh_init)[:1], good[:1], atol=1e-6)
    scores = c.report["sh"]["start"]["psnr"]
    assert scores["sky pixels"] < scores[c.report["sh"]["start"]["chosen"]] - 0.5


def test_patch_regression_recovers_ratio_and_ignores_albedo():
    rng = np.random.default_rng(0)
    n = 4000
    centers = rng.uniform(0, 20, (n, 3)); centers[:, 2] = 0
    normals = np.tile([0.0, 0, 1], (n, 1))
    patches = surface_patches(centers, normals)
    albedo = rng.uniform(0.05, 0.9, patches.max() + 1)[patches]   # one albedo per patch
    s = (rng.random(n) > 0.3).astype(float)                         # lit or shadowed
    lum = albedo * 0.2 * (1 + 2.0 * s) * np.exp(rng.normal(0, 0.02, n))
    gain, rho = PatchRegression(lum, patches).fit(s)
    assert rho == pytest.approx(2.0)
    assert gain > 0.9
    gain0, rho0 = PatchRegression(lum, patches).fit(rng.random(n))  # unrelated shading
    assert gain0 < 0.05


def test_sh_order_ignores_pixels_that_are_not_sky():
    # A uniform sky seen in a band above the horizon, with 12 % of its
    # "sky" pixels showing a bright roof on one side: a plain least-squares
    # fit buys a tilted order-1 sky for them; the trimmed fit keeps order 0
    # and the true radiance.
    from mi_invrgbl.fit.selection import fit_sh_orders, sh_basis_numpy
    rng = np.random.default_rng(0)
    n = 4000
    phi = rng.uniform(-0.6, 0.6, n)
    elev = rng.uniform(0.02, 0.35, n)
    d = np.stack([np.cos(elev) * np.cos(phi), np.cos(elev) * np.sin(phi), np.sin(elev)], 1)
    sky = np.array([0.32, 0.38, 0.5])
    rgb = np.tile(sky, (n, 1)) + rng.normal(0, 0.004, (n, 3))
    roof = (phi > 0.3) & (rng.uniform(size=n) < 0.5)
    rgb[roof] = [0.9, 0.75, 0.6]
    order, errors, coeffs = fit_sh_orders(d, rgb, max_order=2)
    print(roof.mean(), order, errors)
    assert 0.08 < roof.mean() < 0.2
    assert order == 0
    fitted = sh_basis_numpy(np.array([[0.0, 0.0, 1.0]]), 0) @ coeffs[0]
    assert np.allclose(fitted.ravel(), sky, atol=0.01)
    # Plain least squares on the same pixels is pulled towards the roof.
    B = sh_basis_numpy(d, 0)
    plain, *_ = np.linalg.lstsq(B, rgb, rcond=None)
    assert np.abs((B[:1] @ plain).ravel() - sky).max() > 0.04


def _ground(rng, n, size):
    """``n`` Gaussians on flat ground ``size`` metres across: their 2 m
    patches and one albedo per patch."""
    centers = rng.uniform(0, size, (n, 3)); centers[:, 2] = 0
    patches = surface_patches(centers, np.tile([0.0, 0, 1], (n, 1)))
    return patches, rng.uniform(0.1, 0.8, patches.max() + 1)[patches]


def test_cross_validated_gain_separates_shadows_from_picked_noise():
    # 300 candidate "directions" of random lit/shadowed patterns: the best of
    # them explains some noise where it was picked, but not on other patches;
    # a real shadow pattern (darker where s = 0) does both.
    from mi_invrgbl.fit.selection import cross_validated_gain, score_candidates
    rng = np.random.default_rng(1)
    n = 400
    patches, albedo = _ground(rng, n, 40)
    noise_feats = (rng.random((n, 300)) > 0.5).astype(float)
    w = np.ones(n)
    overcast = albedo * np.exp(rng.normal(0, 0.3, n))
    picked = score_candidates(PatchRegression(overcast, patches, w), noise_feats)[:, 0].max()
    assert picked > 0.02
    assert cross_validated_gain(overcast, patches, w, noise_feats) < 0.005
    s = noise_feats[:, 7]
    sunny = albedo * (1 + 2.0 * s) * np.exp(rng.normal(0, 0.3, n))
    assert cross_validated_gain(sunny, patches, w, noise_feats) > 0.5


def test_sky_occlusion_model_is_fitted_not_taken_as_traced():
    # Shading that is all sun, with a traced sky visibility that is noise:
    # the sky-occlusion model must fall back to none (b = 0) and leave the
    # sun its gain; taken as traced (b = 1) it would add its noise to every
    # Gaussian, and the sun would explain little "beyond" it.
    from mi_invrgbl.fit.selection import SUN_RATIOS, sky_occlusion_gains
    rng = np.random.default_rng(2)
    n = 3000
    patches, albedo = _ground(rng, n, 30)
    s = (rng.random(n) > 0.4).astype(float)
    lum = albedo * (1 + 2.0 * s) * np.exp(rng.normal(0, 0.1, n))
    noise_sky = rng.uniform(0.02, 1.0, n)
    reg = PatchRegression(lum, patches)
    gain_sky, over, b = sky_occlusion_gains(reg, s, noise_sky)
    print(gain_sky, over, b)
    assert b == 0.0 and gain_sky == pytest.approx(0.0, abs=1e-12)
    assert over > 0.8
    as_traced, _ = reg.fit(s, noise_sky)            # the old, b = 1 reference
    assert as_traced < over - 0.2
    # Darkening that sky occlusion explains: the sky model takes it, and a
    # "sun" whose pattern is unrelated adds nothing beyond it.
    sky = rng.uniform(0.1, 1.0, n)
    lum = albedo * sky * np.exp(rng.normal(0, 0.05, n))
    gain_sky, over, b = sky_occlusion_gains(PatchRegression(lum, patches), s, sky)
    print(gain_sky, over, b)
    assert b == 1.0 and gain_sky > 0.9 and over < 0.01
    assert 0.0 in SUN_RATIOS


def test_cross_validated_gain_averages_splits():
    # A weak real sun: one random split's gain scatters, the mean of eight
    # scatters less (the gains are those of the eight splits' halves).
    from mi_invrgbl.fit.selection import cross_validated_gain, cross_validated_gains
    rng = np.random.default_rng(3)
    n = 600
    patches, albedo = _ground(rng, n, 40)
    feats = (rng.random((n, 40)) > 0.5).astype(float)
    lum = albedo * (1 + 0.3 * feats[:, 5]) * np.exp(rng.normal(0, 0.3, n))
    w = np.ones(n)
    g = cross_validated_gains(lum, patches, w, feats, seed=0, splits=8)
    assert g.shape == (16,)
    assert cross_validated_gain(lum, patches, w, feats, seed=0, splits=8) == pytest.approx(g.mean())
    one = [cross_validated_gain(lum, patches, w, feats, seed=k, splits=1) for k in range(12)]
    eight = [cross_validated_gain(lum, patches, w, feats, seed=k, splits=8) for k in range(12)]
    print(np.std(one), np.std(eight), np.mean(eight))
    assert np.std(eight) < 0.6 * np.std(one)
    assert np.mean(eight) > 0.0


def test_sun_statistics_stay_finite_on_degenerate_input():
    # One patch (no split has two halves) and luminance without any
    # within-patch variance: the statistics are zeros, never NaN.
    from mi_invrgbl.fit.selection import cross_validated_gains, sky_occlusion_gains
    n = 60
    patches = np.zeros(n, np.int64)
    feats = (np.arange(n * 4).reshape(n, 4) % 3 > 0).astype(float)
    lum = np.linspace(0.1, 0.5, n)
    g = cross_validated_gains(lum, patches, np.ones(n), feats)
    assert g.shape == (1,) and np.all(g == 0.0)
    two = np.arange(n) % 2
    flat = np.full(n, 0.3)
    gain_sky, over, b = sky_occlusion_gains(PatchRegression(flat, two), feats[:, 0],
                                            np.full(n, 0.02))
    assert (gain_sky, over) == (0.0, 0.0) and np.isfinite(b)


def test_render_samples_choice_keeps_to_a_budget(monkeypatch):
    """With a deadline, M for rendering scores the fit's own M first (its
    visibility is cached) and other M only while their predicted time fits."""
    import time
    from types import SimpleNamespace
    from mi_invrgbl.fit import model_selection as ms

    scored = []

    def fake_score(stage2, frames, samples, caches):
        scored.append(samples)
        time.sleep(0.02 * samples)              # time grows with M, like the trace
        return 20.0 + 0.01 * samples, float("nan")
    monkeypatch.setattr(ms, "score_stage2", fake_score)
    frames = [SimpleNamespace(index=i, camera=object()) for i in range(3)]
    ctx = SimpleNamespace(
        config=SimpleNamespace(samples=16, render_samples="auto", weights=SimpleNamespace(rgb=1.0)),
        validation_frames=frames, train_frames=[], observations=list(range(30)),
        times={"freeze": 10.0})
    frozen = SimpleNamespace(caches={f.index: object() for f in frames})
    # No deadline: the fit's M first, then the smaller ones (a larger M is
    # not tried: the albedo is fitted to the fit's M).
    out = ms.choose_render_samples(ctx, None, frozen)
    assert scored == [16, 4, 8] and "skipped_for_budget" not in out
    # M=8 is within 0.1 dB of the best (M=16): it renders faster.
    assert out["samples"] == 8 and set(out["by_samples"]) == {"4", "8", "16"}
    # 0.16 dB below it is not.
    monkeypatch.setattr(ms, "score_stage2",
                        lambda stage2, frames, samples, caches: (20.0 + 0.02 * samples, 0.0))
    assert ms.choose_render_samples(ctx, None, frozen)["samples"] == 16
    monkeypatch.setattr(ms, "score_stage2", fake_score)
    # A deadline already passed: only the fit's M (free), the rest skipped.
    scored.clear()
    out = ms.choose_render_samples(ctx, None, frozen, deadline=time.perf_counter())
    assert scored == [16] and out["samples"] == 16 and out["skipped_for_budget"] == [4, 8]
    # A fit with M=32: freezing took 10 s for 30 frames, so M=4 on 3 frames
    # is predicted at 0.125 s; then 0.02 s per sample as measured. With 1 s:
    # M=32 (0.64 s, free of the prediction: its visibility is cached), M=4
    # (0.08 s) and M=8 (0.16 s) fit, M=16 (0.32 s) no longer does.
    ctx.config.samples = 32
    scored.clear()
    out = ms.choose_render_samples(ctx, None, frozen, deadline=time.perf_counter() + 1.0)
    assert scored == [32, 4, 8] and out["skipped_for_budget"] == [16]


def test_alternative_sun_directions_are_strong_and_far_apart():
    from mi_invrgbl.fit.selection import (ALTERNATIVE_GAIN, ALTERNATIVE_SEPARATION,
                                          alternative_directions)
    best = np.array([0.0, 0.0, 1.0])
    dirs = np.array([[0.0, 0.0, 1.0],                      # the best itself
                     [np.sin(0.2), 0.0, np.cos(0.2)],      # 11 deg from it: too close
                     [1.0, 0.0, 1.0],                      # 45 deg, strong
                     [1.0, 0.1, 1.0],                      # 45 deg but 4 deg from the last
                     [0.0, 1.0, 0.5],                      # far, strong
                     [-1.0, 0.0, 0.3]])                    # far, weak
    gains = np.array([0.10, 0.099, 0.09, 0.095, 0.08, 0.04])
    out = alternative_directions(best, 0.10, dirs, gains)
    assert len(out) == 3 and np.allclose(out[0], best)
    # Strongest first among those far enough: [1, 0.1, 1] (0.095) beats [1, 0, 1].
    assert np.allclose(out[1], np.array([1.0, 0.1, 1.0]) / np.linalg.norm([1.0, 0.1, 1.0]))
    assert np.allclose(out[2], np.array([0.0, 1.0, 0.5]) / np.linalg.norm([0.0, 1.0, 0.5]))
    for a in out:
        for b in out:
            if a is not b:
                assert np.degrees(np.arccos(np.clip(np.dot(a, b), -1, 1))) >= ALTERNATIVE_SEPARATION
    # Nothing near the best's gain: the best alone.
    assert len(alternative_directions(best, 0.10, dirs, gains * (ALTERNATIVE_GAIN - 0.1))) == 1


def test_the_log_names_the_search_and_the_sharpened_direction():
    from types import SimpleNamespace
    from mi_invrgbl.fit.model_selection import LightingChoice, log_lighting
    lines = []
    scan = {"found": {"direction": [0.0, 0.0, 1.0], "gain": 0.06}, "moved": True,
            "peaks": [{"direction": [0.0, 0.6, 0.8], "gain": 0.1}],
            "directions_scanned": 400, "gaussians_scanned": 4000, "seconds": 61.0}
    sun = {"direction": [0.0, 0.6, 0.8], "gain": 0.06, "cv_gain": 0.03, "gain_over_sky": 0.04,
           "median_gain": 0.001, "sun_to_sky": 1.0, "use_sun": True, "scan": scan}
    choice = LightingChoice(report={"sun": sun, "sh": {}}, use_sun=True, sh_order=2,
                            sh_init=None, sun_direction=sun["direction"], sun_irradiance=1.0)
    log_lighting(SimpleNamespace(log=lines.append), choice, 1.0)
    assert "best direction [0.0, 0.0, 1.0] explains 6.0 %" in lines[0]
    assert "moved 36.9 deg to [0.0, 0.6, 0.8]" in lines[1] and "400 directions" in lines[1]
    sun.update(scan=dict(scan, moved=False), direction=[0.0, 0.0, 1.0])
    lines.clear()
    log_lighting(SimpleNamespace(log=lines.append), choice, 1.0)
    assert "the search's direction kept" in lines[1]
    del sun["scan"]
    lines.clear()
    log_lighting(SimpleNamespace(log=lines.append), choice, 1.0)
    assert len(lines) == 1
