"""``fit`` end to end on a small scene with known truth (tests/fit_scene.py).

Covers: outputs load and render through the standard pipeline, the fit
lowers the error it reports, the LiDAR response is recovered, checkpoints
resume, a NaN step is rolled back, and Ctrl-C leaves a checkpoint and the
outputs so far.
"""

import json
import os

import numpy as np
import pytest
import mitsuba as mi
import drjit as dr

from fit_scene import build
from mi_invrgbl.fit.runner import FitConfig, run_fit
from mi_invrgbl.fit.losses import LossWeights
from mi_invrgbl.errors import UserError


def small_config(out, **kw):
    base = dict(output=str(out), stage1_iterations=10, stage2_iterations=24, fit_width=48,
                lidar_columns=128, batch_rays=1024, eval_every=8, checkpoint_every=8,
                samples=8, lobe_iterations=10, sun_candidates=12, seed=1)
    base.update(kw)
    return FitConfig(**base)


def narrow_sun_rejection(choose):
    """``choose_lighting`` made to reject its sun narrowly (gain 0.03, bar
    0.05), so that the sun trial runs."""
    def narrowly_rejected(state):
        choice = choose(state)
        sun = choice.report["sun"]
        sun.update(gain=0.03, use_sun=False, direction=sun.get("direction", [0.3, 0.4, 0.866]))
        choice.use_sun, choice.sun_direction, choice.sun_irradiance = False, None, 0.0
        return choice
    return narrowly_rejected


@pytest.fixture(scope="module")
def scene_path(tmp_path_factory):
    d = tmp_path_factory.mktemp("fitscene")
    return build(str(d), n_frames=5, width=48, height=16, columns=128)


@pytest.fixture(scope="module")
def fitted(scene_path, tmp_path_factory):
    out = tmp_path_factory.mktemp("fit")
    metrics = run_fit(scene_path, small_config(out), log=lambda *a: None)
    return out, metrics


def test_outputs_written(fitted):
    out, metrics = fitted
    for name in ("scene.xml", "scene_lidar.xml", "background.ply", "metrics.json", "log.csv",
                 "error_vs_time.png", "checkpoints/latest.npz"):
        assert (out / name).is_file(), name
    maps = sorted(os.listdir(out / "maps"))
    for kind in ("albedo", "roughness", "normal", "lidar_albedo", "lidar_intensity"):
        assert "0000_%s.exr" % kind in maps
    saved = json.loads((out / "metrics.json").read_text())
    assert saved["interrupted"] is False
    assert saved["gaussians"]["background"] > 0
    assert saved["frames"]["held_out"] == [4]
    assert saved["peak_rss_mb"] > 0
    for key in ("sun", "sh", "response_init", "lidar_lobe", "samples", "sky_lookalikes"):
        assert key in saved["selection"]
    # The free angle exponent against the prior's value, judged on the
    # validation frame's returns (frame 2), and the better one kept.
    init = saved["selection"]["response_init"]
    choice = init["angle_exponent_choice"]
    assert choice["scored_on"] == "validation"
    assert np.isfinite(choice["free"]) and np.isfinite(choice["prior"])
    assert (init["angle_exponent"] == 1.0) == (choice["prior"] <= choice["free"])
    chosen = saved["selection"]["samples"]
    # The fit's own M and the smaller one (this fit uses M=8).
    assert set(chosen["by_samples"]) == {"4", "8"}
    # The synthetic test street shows sky above the road: the sky mask
    # marks it, and stage 1 starts from the sky fitted to those pixels.
    mask = saved["selection"]["sky_mask"]
    assert 0.0 < mask["share"] < 0.6 and "sky_start_order" in mask
    assert all(np.isfinite(v["psnr"]) for v in chosen["by_samples"].values())
    assert 'name="samples" value="%d"' % chosen["samples"] in (out / "scene.xml").read_text()


def test_the_written_clouds_are_what_the_metrics_count(fitted):
    from mi_invrgbl.physics.gaussian_ply import read_ply
    out, metrics = fitted
    for name, count in metrics["gaussians"].items():
        assert len(read_ply(str(out / ("%s.ply" % name))).centers) == count, name


def test_fitted_scene_renders_in_mitsuba(fitted):
    out, _ = fitted
    scene = mi.load_file(str(out / "scene.xml"))
    cam = [s for s in scene.sensors() if s.id() == "camera_0004"][0]
    img = np.array(mi.render(scene, sensor=cam, spp=2))
    assert np.isfinite(img).all() and img[..., :3].mean() > 0.05
    lscene = mi.load_file(str(out / "scene_lidar.xml"))
    integ = lscene.integrator()
    p = mi.traverse(integ)
    assert abs(float(p["range_exponent"][0]) - 2.0) < 0.2  # truth: the paper's cos/d^2
    lidar = [s for s in lscene.sensors() if s.id() == "lidar_0004"][0]
    scan = np.array(mi.render(lscene, sensor=lidar))
    assert np.isfinite(scan).all() and (scan[..., 2] > 0).mean() > 0.3


def test_fitted_scene_blends_as_many_gaussians_as_the_fit(fitted):
    # Gaussians behind the fit's max_hits never got a gradient: the fitted
    # scenes must not draw them (the plugins' defaults are 64 and 1e-3).
    out, _ = fitted
    cfg = small_config(out)
    for name in ("scene.xml", "scene_lidar.xml"):
        integ = mi.load_file(str(out / name)).integrator()
        assert integ.max_hits == cfg.max_hits != 64, name
        assert integ.min_transmittance == pytest.approx(cfg.min_transmittance), name


def test_fit_lowers_error(fitted):
    out, _ = fitted
    import csv
    rows = list(csv.DictReader(open(out / "log.csv")))
    assert len(rows) >= 3
    psnr = [float(r["heldout_psnr"]) for r in rows]
    assert psnr[-1] > psnr[0] + 1.0
    assert all(float(r["wall_s"]) >= 0 for r in rows)
    s2 = [float(r["heldout_intensity_rmse"]) for r in rows if r["stage"] == "stage 2"]
    assert s2 and s2[-1] <= s2[0] * 1.05


def test_resume_continues_from_checkpoint(scene_path, tmp_path):
    cfg = small_config(tmp_path, stage2_iterations=16)
    run_fit(scene_path, cfg, log=lambda *a: None)
    lines = []
    cfg = small_config(tmp_path, stage2_iterations=24, resume=True)
    metrics = run_fit(scene_path, cfg, log=lines.append)
    assert any("resuming" in str(line) for line in lines)
    assert metrics["interrupted"] is False
    import csv
    rows = list(csv.DictReader(open(tmp_path / "log.csv")))
    its = [int(r["iteration"]) for r in rows if r["stage"] == "stage 2"]
    assert its[-1] == 24 and its == sorted(its)


def test_resume_in_stage_2_keeps_the_sh_order(scene_path, tmp_path):
    # The SH order is chosen before stage 2; a resumed stage 2 must keep the
    # coefficients above it at zero rather than free all of them.
    run_fit(scene_path, small_config(tmp_path, sh_order="0", stage2_iterations=16), log=lambda *a: None)
    metrics = run_fit(scene_path, small_config(tmp_path, stage2_iterations=24, resume=True),
                      log=lambda *a: None)
    assert metrics["selection"]["sh"]["order"] == 0
    assert 'name="order" value="0"' in (tmp_path / "scene.xml").read_text()
    ckpt = np.load(tmp_path / "checkpoints" / "latest.npz")
    sh = ckpt["sky/sh"].reshape(-1, 3)   # the scene's order-1 emitter: 4 coefficients
    assert sh.shape[0] == 4 and np.all(sh[1:] == 0) and np.all(sh[0] > 0)


def test_nan_step_is_rolled_back(scene_path, tmp_path, monkeypatch):
    from mi_invrgbl.fit import losses
    real = losses.rgb_loss
    calls = {"n": 0}

    def flaky(pred, target, mask=None, **kw):
        calls["n"] += 1
        value = real(pred, target, mask, **kw)
        return value * float("nan") if calls["n"] == 3 else value

    monkeypatch.setattr(losses, "rgb_loss", flaky)
    lines = []
    metrics = run_fit(scene_path, small_config(tmp_path, stage2_iterations=8), log=lines.append)
    assert metrics["rollbacks"] >= 1
    assert any("rolled back" in str(line) for line in lines)
    scene = mi.load_file(str(tmp_path / "scene.xml"))
    params = mi.traverse(scene)
    assert np.isfinite(np.array(params["background.albedo"])).all()


def test_interrupt_writes_checkpoint_and_outputs(scene_path, tmp_path, monkeypatch):
    from mi_invrgbl.fit import stage2
    real = stage2.Stage2.iteration

    def interrupted(self, it, weights=None):
        if it == 5 and weights is None:
            raise KeyboardInterrupt
        return real(self, it, weights)

    monkeypatch.setattr(stage2.Stage2, "iteration", interrupted)
    metrics = run_fit(scene_path, small_config(tmp_path), log=lambda *a: None)
    assert metrics["interrupted"] is True
    assert (tmp_path / "checkpoints" / "latest.npz").is_file()
    assert (tmp_path / "scene.xml").is_file()
    monkeypatch.setattr(stage2.Stage2, "iteration", real)
    metrics = run_fit(scene_path, small_config(tmp_path, resume=True), log=lambda *a: None)
    assert metrics["interrupted"] is False


def test_interrupt_during_the_sun_trial_writes_outputs(scene_path, tmp_path, monkeypatch):
    # Ctrl-C while the trial of a narrowly rejected sun runs: the fit ends
    # as interrupted with its outputs written, and --resume finishes it.
    from mi_invrgbl.fit import runner, stage2
    real_choose, real = runner.choose_lighting, stage2.Stage2.iteration

    narrowly_rejected = narrow_sun_rejection(real_choose)

    def interrupted(self, it, weights=None):
        if it == 2:
            raise KeyboardInterrupt
        return real(self, it, weights)

    monkeypatch.setattr(runner, "choose_lighting", narrowly_rejected)
    monkeypatch.setattr(stage2.Stage2, "iteration", interrupted)
    lines = []
    metrics = run_fit(scene_path, small_config(tmp_path, sun_trial_iterations=4), log=lines.append)
    assert metrics["interrupted"] is True
    assert any("interrupted during the sun trial" in str(x) for x in lines)
    assert (tmp_path / "checkpoints" / "latest.npz").is_file() and (tmp_path / "scene.xml").is_file()
    monkeypatch.setattr(stage2.Stage2, "iteration", real)
    metrics = run_fit(scene_path, small_config(tmp_path, resume=True), log=lambda *a: None)
    assert metrics["interrupted"] is False and metrics["iterations"]["stage 2"] == 24


def test_bad_weights_and_missing_scene(tmp_path):
    from mi_invrgbl.errors import UserError
    with pytest.raises(ValueError):
        LossWeights.parse("rgb2lidar=-1")
    with pytest.raises(UserError):
        run_fit(str(tmp_path / "nope" / "scene.xml"), small_config(tmp_path), log=lambda *a: None)


def _edit_frames(scene_path, tmp_path, edit):
    """A copy of the small scene's folder with frames.json edited by ``edit(frame)``."""
    import shutil
    src = os.path.dirname(scene_path)
    dst = tmp_path / "scene"
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("fit*"))
    meta = json.loads((dst / "frames.json").read_text())
    for f in meta["frames"]:
        edit(f)
    (dst / "frames.json").write_text(json.dumps(meta))
    return str(dst / "scene.xml")


def test_every_frame_held_out_is_refused(scene_path, tmp_path):
    from mi_invrgbl.errors import UserError
    path = _edit_frames(scene_path, tmp_path, lambda f: f.update(held_out=True))
    with pytest.raises(UserError, match="no training frame"):
        run_fit(path, small_config(tmp_path / "fit"), log=lambda *a: None)


def test_validation_frames_sit_between_the_held_out_frames():
    """The import holds out ``index % 5 == 4``; validation frames are taken
    two frames from the held-out ones, so the frames beside a held-out frame
    are trained on, for every split that is a multiple of 5."""
    from types import SimpleNamespace
    from mi_invrgbl.fit.init import split_validation
    frames = [SimpleNamespace(index=i) for i in range(40) if i % 5 != 4]
    for every, expected in ((5, [2, 7, 12, 17, 22, 27, 32, 37]), (10, [2, 12, 22, 32])):
        train, val = split_validation(frames, every)
        assert [f.index for f in val] == expected
        assert len(train) + len(val) == len(frames) and not set(map(id, train)) & set(map(id, val))
        beside = [f for f in frames if (f.index + 1) % 5 == 4 or (f.index - 1) % 5 == 4]
        assert beside and all(any(f is t for t in train) for f in beside)
    assert split_validation(frames, 0)[1] == []
    # Fewer than two frames left to train on: no split.
    assert split_validation(frames[:2], 1) == (frames[:2], [])


def test_fit_without_lidar_scans_runs_on_images_alone(scene_path, tmp_path):
    path = _edit_frames(scene_path, tmp_path, lambda f: f.pop("lidar_scan"))
    out = tmp_path / "fit"
    metrics = run_fit(path, small_config(out, stage1_iterations=6, stage2_iterations=8),
                      log=lambda *a: None)
    assert os.path.isfile(out / "scene.xml")
    assert np.isfinite(metrics["heldout_psnr"])
    assert metrics["heldout_intensity_rmse"] is None or not np.isfinite(metrics["heldout_intensity_rmse"])
    scene = mi.load_file(str(out / "scene.xml"))
    img = np.array(mi.render(scene, sensor=scene.sensors()[0], spp=1))
    assert np.all(np.isfinite(img))


@pytest.mark.parametrize("mode", ["learn", "trace"])
def test_sun_visibility_learned_or_traced(scene_path, tmp_path, mode):
    from mi_invrgbl.physics.gaussian_ply import read_ply
    out = tmp_path / mode
    # Each case takes another shadowing term: the fitted scene keeps its own.
    shadowing = "smith" if mode == "trace" else "vcavity"
    metrics = run_fit(scene_path, small_config(out, sun="on", sun_visibility=mode,
                                               render_samples="8", shadowing=shadowing),
                      log=lambda *a: None)
    init = metrics["selection"]["shading_init"]
    assert np.all(np.isfinite(init["sun_irradiance"])) and min(init["sun_irradiance"]) > 0
    # What the start took: the sun trial's estimate of its own start.
    assert 0 < init["seconds"] < metrics["times_s"]["freeze"]
    text = (out / "scene.xml").read_text()
    assert ('name="sun_visibility" value="attribute"' in text) == (mode == "learn")
    assert 'name="shadowing" value="%s"' % shadowing in text
    v = read_ply(str(out / "background.ply")).sun_visibility
    assert np.all((v >= 0) & (v <= 1))
    assert 0.02 < np.mean(v < 0.5) < 0.98      # the facade's shadow, and sunlit ground
    scene = mi.load_file(str(out / "scene.xml"))
    assert scene.integrator().shadowing == shadowing
    cam = [s for s in scene.sensors() if s.id() == "camera_0004"][0]
    img = np.array(mi.render(scene, sensor=cam, spp=2))
    assert np.isfinite(img).all() and img[..., :3].mean() > 0.05


@pytest.mark.parametrize("learn", [True, False])
def test_stage_2_refines_the_sun_direction(scene_path, tmp_path, learn):
    # With learned v_sun the sun direction is a stage-2 variable: it moves
    # from the selection's, stays a unit vector above the horizon and is
    # written out; switched off (or with traced shadows) it stays put.
    import xml.etree.ElementTree as ET
    metrics = run_fit(scene_path, small_config(tmp_path, sun="on", render_samples="8",
                                               learn_sun_direction=learn), log=lambda *a: None)
    chosen = np.array(metrics["selection"]["sun"]["direction"])
    em = [e for e in ET.parse(tmp_path / "scene.xml").getroot().iter("emitter")
          if e.get("type") == "shsun"][0]
    v = [c for c in em if c.get("name") == "sun_direction"][0]
    d = np.array([float(v.get(k)) for k in "xyz"])
    assert abs(np.linalg.norm(d) - 1) < 1e-4 and d[2] > 0.03
    moved = np.degrees(np.arccos(np.clip(d @ chosen / np.linalg.norm(chosen), -1, 1)))
    if learn:
        assert 0.01 < moved < 20, moved
    else:
        assert moved < 1e-3, moved


def test_resume_in_stage_2_keeps_learning_sun_visibility(scene_path, tmp_path):
    # The learned v_sun is an optimiser variable: an interrupted stage 2 must
    # restore it (and its moments) and go on writing it out.
    from mi_invrgbl.physics.gaussian_ply import read_ply
    run_fit(scene_path, small_config(tmp_path, sun="on", stage2_iterations=16, render_samples="8"),
            log=lambda *a: None)
    lines = []
    metrics = run_fit(scene_path, small_config(tmp_path, sun="on", stage2_iterations=24,
                                               render_samples="8", resume=True), log=lines.append)
    assert any("resuming" in str(line) for line in lines) and metrics["interrupted"] is False
    assert 'name="sun_visibility" value="attribute"' in (tmp_path / "scene.xml").read_text()
    v = read_ply(str(tmp_path / "background.ply")).sun_visibility
    assert np.all((v >= 0) & (v <= 1)) and 0.02 < np.mean(v < 0.5) < 0.98


def test_cli_flags_reach_the_config():
    from mi_invrgbl.cli import build_parser
    from mi_invrgbl.commands.fit import config_from_args
    parse = lambda *a: config_from_args(build_parser().parse_args(["fit", "s.xml", *a]))  # noqa: E731
    default = parse()
    assert default.prune_sky_lookalikes and not default.learn_sun_direction
    assert default.sun_visibility == "learn"
    cfg = parse("--keep-sky-lookalikes", "--learn-sun-direction", "--sun-visibility", "trace")
    assert not cfg.prune_sky_lookalikes and cfg.learn_sun_direction and cfg.sun_visibility == "trace"
    assert default.budget_minutes == 0 and parse("--budget", "8").budget_minutes == 8
    assert (default.batch_rays, default.lidar_batch_rays) == (4096, 1024)
    cfg = parse("--batch", "2048", "--lidar-batch", "512")
    assert (cfg.batch_rays, cfg.lidar_batch_rays) == (2048, 512)
    with pytest.raises(UserError, match="--lidar-batch must be positive"):
        parse("--lidar-batch", "0")
    assert default.pixel_grid == 1 and parse("--pixel-grid", "2").pixel_grid == 2
    for bad in ("0", "5"):
        with pytest.raises(UserError, match="--pixel-grid must be"):
            parse("--pixel-grid", bad)


def test_checkpoint_predating_an_option_resumes_with_its_value_then():
    """A checkpoint written before ``lidar_batch_rays`` existed drew as many
    LiDAR beams as camera rays: it resumes under that value, not the new
    default, and other options still have to match."""
    from mi_invrgbl.fit.checkpoint import check_fingerprint
    now = FitConfig(batch_rays=2048, lidar_batch_rays=2048)
    fp = {"scene": "s", "frames": "f", "gaussians": {"background": 3},
          "config": now.model_fields()}
    old = {**fp, "config": {k: v for k, v in fp["config"].items() if k != "lidar_batch_rays"}}
    check_fingerprint("ckpt", old, fp)                       # 2048 then, 2048 now
    fp_default = {**fp, "config": FitConfig(batch_rays=2048).model_fields()}
    with pytest.raises(UserError, match="lidar_batch_rays"):
        check_fingerprint("ckpt", old, fp_default)           # 2048 then, 1024 now
    assert fp_default["config"]["lidar_batch_rays"] == 1024


def test_checkpoint_predating_rgb_space_was_fitted_in_linear_light():
    from mi_invrgbl.fit.checkpoint import check_fingerprint
    now = {"scene": "s", "frames": "f", "gaussians": {"background": 3},
           "config": FitConfig().model_fields()}
    old = {**now, "config": {k: v for k, v in now["config"].items() if k != "rgb_space"}}
    assert now["config"]["rgb_space"] == "srgb"
    with pytest.raises(UserError, match="rgb_space"):
        check_fingerprint("ckpt", old, now)                  # linear then, sRGB now
    check_fingerprint("ckpt", old, {**now, "config": FitConfig(rgb_space="linear").model_fields()})


def test_stage1_score_on_a_pixel_subset(scene_path, tmp_path):
    """Stage 1's progress score on every n-th counted pixel estimates the full
    frame's PSNR, and scores the same pixels each time."""
    from mi_invrgbl.fit.evaluate import score_stage1
    from mi_invrgbl.fit.init import load_state
    state = load_state(scene_path, small_config(tmp_path), log=lambda *a: None)
    frames = state.train_frames[:2]
    full = score_stage1(state, frames, stride=1)
    sub = score_stage1(state, frames, stride=4)
    assert np.isfinite(full) and np.isfinite(sub)
    assert abs(sub - full) < 1.0
    assert score_stage1(state, frames) == pytest.approx(sub, abs=1e-9)   # the config's stride 4
    assert score_stage1(state, frames, stride=4) == pytest.approx(sub, abs=1e-9)
    # A frame with every pixel masked is left out; nothing left scores NaN.
    frame = frames[0]
    valid = frame.camera.valid
    frame.camera.valid = lambda: np.zeros_like(valid(), dtype=bool)
    try:
        assert np.isnan(score_stage1(state, [frame]))
        assert score_stage1(state, frames) == pytest.approx(score_stage1(state, frames[1:]), abs=1e-9)
    finally:
        frame.camera.valid = valid


def _called_from(module):
    """True when a function of ``module`` is on the call stack."""
    import sys
    frame = sys._getframe(1)
    while frame is not None:
        if frame.f_globals.get("__name__") == module.__name__:
            return True
        frame = frame.f_back
    return False


def test_model_selection_never_touches_held_out_frames(scene_path, tmp_path, monkeypatch):
    # Held-out frames (index % 5 == 4) are for `eval` alone: the choices
    # (lighting, LiDAR lobe, sky samples M) are scored on the validation split
    # of the training frames. Every render and trace made on behalf of
    # model_selection is recorded here with the frame it served.
    from mi_invrgbl.fit import model_selection, stage2
    from mi_invrgbl.physics import hits
    held_rays = []
    touched = {"held_out": [], "scored": set(), "traced": 0}
    real_render, real_trace = stage2.Stage2.render_frame, hits.trace

    def render_spy(self, frame, *a, **k):
        if _called_from(model_selection):
            if frame.held_out:
                touched["held_out"].append(frame.index)
            else:
                touched["scored"].add(frame.index)
        return real_render(self, frame, *a, **k)

    def trace_spy(scene, rays, *a, **k):
        if _called_from(model_selection):
            touched["traced"] += 1
            if any(rays is r for r in held_rays):
                touched["held_out"].append("trace")
        return real_trace(scene, rays, *a, **k)

    real_load = __import__("mi_invrgbl.fit.init", fromlist=["load_state"]).load_state

    def load_spy(*a, **k):
        state = real_load(*a, **k)
        for f in state.held_out_frames:
            held_rays.extend(x.rays for x in (f.camera, f.lidar) if x is not None)
        return state

    from mi_invrgbl.fit import runner
    monkeypatch.setattr(runner, "load_state", load_spy)
    monkeypatch.setattr(stage2.Stage2, "render_frame", render_spy)
    monkeypatch.setattr(hits, "trace", trace_spy)
    metrics = run_fit(scene_path, small_config(tmp_path, stage2_iterations=8), log=lambda *a: None)
    assert held_rays and touched["traced"] > 0          # the spies saw the selection work
    assert touched["held_out"] == [], touched
    assert metrics["frames"]["validation"] == [2] and metrics["frames"]["held_out"] == [4]
    assert 2 in touched["scored"]      # (the Lambertian refit steps on training frames too)
    sel = metrics["selection"]
    assert sel["lidar_lobe"]["scored_on"] == "validation" and sel["samples"]["scored_on"] == "validation"
    assert 2 not in metrics["frames"]["train"]
    assert np.isfinite(metrics["heldout_psnr"])            # held-out frames are still reported


def test_resume_refuses_a_checkpoint_of_another_fit(scene_path, tmp_path):
    from mi_invrgbl.errors import UserError
    out = tmp_path / "fit"
    run_fit(scene_path, small_config(out, stage1_iterations=4, stage2_iterations=4), log=lambda *a: None)
    with pytest.raises(UserError, match="another fit.*fit_width") as info:
        run_fit(scene_path, small_config(out, fit_width=32, resume=True), log=lambda *a: None)
    assert "\n" not in str(info.value)
    other = _edit_frames(scene_path, tmp_path, lambda f: f.update(time=f["time"] + 1.0))
    with pytest.raises(UserError, match="another fit.*frames.json"):
        run_fit(other, small_config(out, resume=True), log=lambda *a: None)
    # The same scene and options resume.
    metrics = run_fit(scene_path, small_config(out, stage1_iterations=4, stage2_iterations=6,
                                               resume=True), log=lambda *a: None)
    assert metrics["interrupted"] is False


def test_densify_carries_adam_moments(scene_path, tmp_path):
    # Kept Gaussians continue with their Adam moments. Clones and split
    # halves take their parent's second moment and a zero first moment, so
    # that they step at the usual size on their own gradients. A clone and
    # its parent share the parent's opacity a: (1 - a')^2 = 1 - a.
    from mi_invrgbl.fit.init import load_state
    from mi_invrgbl.fit.stage1 import Stage1
    # (The scene's Gaussians start at opacity 0.95 and sizes 0.15-0.18 m: these
    # thresholds prune, clone and split some of each after a few steps.)
    cfg = small_config(tmp_path, densify_fraction=0.3, densify_grad=0.0, prune_opacity=0.95,
                       split_scale=0.16)
    state = load_state(scene_path, cfg, log=lambda *a: None)
    s1 = Stage1(state)
    for it in range(1, 4):
        s1.iteration(it)
    key = "background.center"
    t0, m0, v0 = s1.opt.moments(key)
    s1.pull()
    node = state.model.nodes["background"]
    old = node.numpy("center")
    old_opacity = state.model.cloud("background", stage=1).opacities
    report = s1.densify()
    pruned, cloned, split, count = report["background"]
    assert pruned > 0 and cloned > 0 and split > 0, report
    assert count == old.shape[0] - pruned - split + cloned + 2 * split
    t1, m1, v1 = s1.opt.moments(key)
    new = state.model.nodes["background"].numpy("center")
    new_opacity = state.model.cloud("background", stage=1).opacities
    assert new.shape[0] == count and m1.size == 3 * count
    assert int(np.ravel(t1)[0]) == int(np.ravel(t0)[0])
    m0, v0, m1, v1 = (a.reshape(-1, 3) for a in (m0, v0, m1, v1))
    assert np.abs(m0).max() > 0                         # the moments were not zero to begin with
    where = {tuple(c): i for i, c in enumerate(old)}
    parent = np.array([where.get(tuple(c), -1) for c in new])
    n_kept = count - cloned - 2 * split
    kept, clones, halves = np.arange(n_kept), np.arange(n_kept, n_kept + cloned), \
        np.arange(n_kept + cloned, count)
    assert (parent[kept] >= 0).all() and (parent[clones] >= 0).all()
    assert np.array_equal(m1[kept], m0[parent[kept]]) and np.array_equal(v1[kept], v0[parent[kept]])
    # Fresh rows: zero first moment, the parent's second moment.
    assert not m1[clones].any() and not m1[halves].any()
    assert np.array_equal(v1[clones], v0[parent[clones]])
    assert (v1[halves] > 0).any()
    # A clone and its parent (the kept row with the same centre) share the opacity.
    a = old_opacity[parent[clones]]
    expect = 1.0 - np.sqrt(1.0 - a)
    assert np.allclose(new_opacity[clones], expect, atol=2e-3)
    twin = {tuple(new[i]): i for i in kept}
    assert np.allclose(new_opacity[[twin[tuple(new[i])] for i in clones]], expect, atol=2e-3)
    # The optimiser goes on stepping over the new arrays.
    loss, _, ok = s1.iteration(4)
    assert ok and np.isfinite(loss)


def test_densify_screen_ranks_by_the_gradient_times_the_distance(scene_path, tmp_path):
    # With densify_screen a Gaussian's accumulated positional gradient is
    # the metric one times its distance from the step's camera (about its
    # gradient in image space). The same seed takes the same step either
    # way, so the ratio of the two accumulations is that distance, taken
    # here from the frame's camera pose in frames.json and the Gaussians' centres.
    import copy
    from mi_invrgbl.fit.init import load_state
    from mi_invrgbl.fit.stage1 import Stage1
    acc, origin, centres = {}, None, None
    for screen in (False, True):
        state = load_state(scene_path, small_config(tmp_path, densify_screen=screen),
                           log=lambda *a: None)
        s1 = Stage1(state)
        pick = copy.deepcopy(s1.rng).integers(0, len(state.train_frames))
        frame = state.train_frames[pick]
        record = [r for r in state.frames if r.index == frame.index][0]
        origin = np.asarray(record.camera_to_world, np.float64)[:3, 3]   # frames.json's camera
        centres = state.model.nodes["background"].numpy("center").astype(np.float64)
        s1.iteration(1)
        acc[screen] = np.array(s1.grad_accum["background"][0], np.float64)
    seen = acc[False] > 1e-12
    assert seen.sum() > 50, seen.sum()
    distance = np.linalg.norm(centres - origin, axis=1)
    ratio = acc[True][seen] / acc[False][seen]
    assert np.allclose(ratio, distance[seen], rtol=1e-3), np.abs(ratio / distance[seen] - 1).max()
    assert not acc[True][~seen].any()
    assert distance.min() > 0.5 and distance.max() > 2 * distance.min()   # the ranking changes


def test_densify_screen_ranks_in_metres_on_a_frame_without_images(scene_path, tmp_path):
    # A LiDAR-only frame has no camera to measure pixels from: the step's
    # accumulation is the metric one, with or without densify_screen.
    import copy
    from mi_invrgbl.fit.init import load_state
    from mi_invrgbl.fit.stage1 import Stage1
    acc = {}
    for screen in (False, True):
        state = load_state(scene_path, small_config(tmp_path, densify_screen=screen),
                           log=lambda *a: None)
        s1 = Stage1(state)
        pick = copy.deepcopy(s1.rng).integers(0, len(state.train_frames))
        state.train_frames[pick].camera = None
        s1.iteration(1)
        assert s1._view_origin is None
        acc[screen] = np.array(s1.grad_accum["background"][0], np.float64)
    seen = acc[False] > 1e-12
    assert seen.sum() > 50, seen.sum()
    assert np.allclose(acc[True], acc[False], rtol=1e-5, atol=0)


def test_step_with_finite_loss_but_infinite_gradient_is_rolled_back():
    # sqrt at 0: the loss is 0, its gradient infinite. One read-back checks
    # both; the step is skipped, learning rates halved, the value kept.
    import drjit as dr
    from mi_invrgbl.fit.steps import make_optimizer, safe_step
    opt = make_optimizer({"x": mi.Float([0.0, 1.0])}, {"x": 0.1})
    lines, state = [], {}
    ok = safe_step(opt, dr.sum(dr.sqrt(opt["x"])), lines.append, state, "test step")
    assert not ok and state["rollbacks"] == 1 and state["scale"] == 0.5
    assert "a gradient is not finite" in lines[0]
    assert np.allclose(np.array(opt["x"]), [0.0, 1.0]) and abs(opt.learning_rate("x") - 0.05) < 1e-9
    lines.clear()
    assert not safe_step(opt, dr.sum(opt["x"]) * float("nan"), lines.append, state, "test step")
    assert "loss is nan" in lines[0]
    assert safe_step(opt, dr.sum(dr.square(opt["x"])), lines.append, state, "test step")


def test_early_stop_and_budget_plan():
    from mi_invrgbl.fit.budget import EarlyStop, MAX_ITERATIONS, plan_stage, position_lr_factor
    stop = EarlyStop(patience=3, min_gain=0.02)
    scores = [20.0, 21.0, 21.5, 21.51, 21.52, 21.4]      # gains of 0.01, 0.02, -0.1 after 21.5
    assert [stop.update(s) for s in scores] == [False] * 5 + [True]
    assert stop.best == 21.5
    assert not EarlyStop(patience=1).update(float("nan"))
    plan = plan_stage("stage 1", 60.0, 0.01, done=4)     # 6000 iterations' worth of time
    assert plan.batch_scale == 4 and plan.iterations == 4 + 6000 // 4
    assert plan_stage("stage 2", 60.0, 0.01, batched=False).iterations == 6000
    # A stage 1 whose larger batches cost as much per ray (a CPU) takes more steps instead.
    cpu = plan_stage("stage 1", 60.0, 0.01, done=4, batched=False)
    assert cpu.batch_scale == 1 and cpu.iterations == 4 + 6000
    small = plan_stage("stage 1", 10.0, 0.1)
    assert small.batch_scale == 1 and small.iterations == 100 <= MAX_ITERATIONS
    assert position_lr_factor(0.0) == 1.0 and abs(position_lr_factor(1.0) - 0.01) < 1e-12


def test_stage_progress_counts_the_time_share_of_a_slow_stage():
    # A budgeted stage whose steps ran slower than planned has spent its
    # time before its steps: its schedules must have ended all the same.
    from mi_invrgbl.fit.budget import position_lr_factor, stage_progress
    assert stage_progress(50, 100) == 0.5
    assert stage_progress(50, 100, elapsed=90.0, seconds=100.0) == 0.9
    assert stage_progress(90, 100, elapsed=10.0, seconds=100.0) == 0.9
    assert stage_progress(500, 100, elapsed=500.0, seconds=100.0) == 1.0
    assert stage_progress(0, 0) == 0.0 and stage_progress(3, 10, 1.0, 0.0) == 0.3
    slow = position_lr_factor(stage_progress(560, 1000, elapsed=100.0, seconds=100.0))
    assert abs(slow - 0.01) < 1e-12 and position_lr_factor(stage_progress(560, 1000)) > 0.07


def test_overrun_report_names_the_fixed_costs():
    # The KITTI excerpt's 2-minute fit on 2 cores (metrics.json times_s):
    # its steps between the stages alone exceed the budget.
    from mi_invrgbl.fit.budget import overrun_report
    times = {"load": 1.2, "stage 1": 56.5, "selection": 25.1, "material init": 6.1,
             "freeze": 88.1, "stage 2": 1.1, "lobe selection": 2.9, "samples selection": 0.2}
    note = overrun_report(2, 251.7, times)
    assert note.startswith("[fit] ran 252 s of a 2-minute budget")
    assert "stages took 58 s, the rest 194 s" in note
    assert note.index("freeze 88 s") < note.index("selection 25 s") < note.index("other 71 s")
    assert "samples selection" not in note        # under a second: counted in "other"
    assert overrun_report(2, 125.0, times) is None     # within 5 %
    assert overrun_report(0, 999.0, times) is None     # no budget
    assert overrun_report(8, float("nan"), times) is None


def test_small_budget_warning_from_the_measured_step():
    # Stage 1's measured step and the frame count predict the steps no
    # budget shrinks. The KITTI excerpt on 2 cores (40 frames, 0.30 s a
    # step) cannot keep 2 minutes (it took 252 s) but keeps 8 (478 s); the
    # street (24 frames, 0.15 s) kept 2 minutes (125 s); so did an H100 (0.02 s).
    from mi_invrgbl.fit.budget import small_budget_warning
    note = small_budget_warning(2, 3.0, 60.0, 40, 0.301)
    assert note is not None and "about 193 s" in note and "about 256 s" in note
    assert small_budget_warning(8, 3.0, 240.0, 40, 0.310) is None
    assert small_budget_warning(2, 3.0, 60.0, 24, 0.149) is None
    assert small_budget_warning(2, 8.0, 60.0, 40, 0.02) is None
    assert small_budget_warning(0, 3.0, 60.0, 40, 0.3) is None


def test_stage1_leaves_stage2_time_where_the_fixed_costs_eat_the_budget():
    # The KITTI excerpt at 8 minutes on 2 cores (40 frames, 0.296 s a step;
    # its fixed costs took 190 s): stage 1 gives up part of its 240 s so
    # that stage 2 keeps 40 % of what the fixed costs leave. The street at
    # 8 minutes (24 frames, 0.173 s), KITTI at 30 minutes and a GPU at 8
    # keep the full share; at 2 minutes KITTI's fixed costs leave stage 2
    # nothing to keep on 2 cores, and stage 1 keeps its share.
    from mi_invrgbl.fit.budget import (FIXED_STEPS_PER_FRAME, MIN_STAGE2_STEPS,
                                       STAGE1_OF_REST, min_stage2_seconds, stage1_seconds)
    rest = 480 - 20 - FIXED_STEPS_PER_FRAME * 40 * 0.296
    kitti8 = stage1_seconds(8, 20.0, 40, 0.296)
    assert kitti8 == pytest.approx(STAGE1_OF_REST * rest) and 120 < kitti8 < 240
    assert 480 - 20 - 190 - kitti8 > min_stage2_seconds(0.296)   # what stage 2 is left
    assert stage1_seconds(8, 5.0, 24, 0.173) == pytest.approx(240.0)
    assert stage1_seconds(30, 20.0, 40, 0.308) == pytest.approx(900.0)
    assert stage1_seconds(8, 20.0, 40, 0.02) == pytest.approx(240.0)
    assert stage1_seconds(2, 20.0, 40, 0.296) == pytest.approx(60.0)
    # The same 2 minutes on one H200 (0.048 s a step, 22 s spent before
    # stage 1; there the steps outside the stages took 69 s): the minimum
    # is counted in steps, so stage 1 gives up time there too, and what it
    # leaves holds stage 2's minimum at the GPU's step (3.8 configured
    # steps) with room to spare. A minimum in seconds (30) gave none.
    gpu2 = stage1_seconds(2, 22.0, 40, 0.048)
    assert gpu2 < 45.0
    assert 120 - 69 - gpu2 > MIN_STAGE2_STEPS * 3.8 * 0.048
    # Never more than the share.
    values = [stage1_seconds(m, 20.0, 40, 0.296) for m in np.linspace(2, 60, 300)]
    assert all(v <= 30 * m + 1e-9 for v, m in zip(values, np.linspace(2, 60, 300)))


def test_stage2_keeps_its_least_steps_past_the_budget():
    # KITTI at 8 minutes on a slower machine: 2 s left after the fixed costs
    # (less the reserve) would give stage 2 its timed steps alone; it gets
    # its least steps instead, and the fit says it runs past the budget.
    from mi_invrgbl.fit.budget import MIN_STAGE2_STEPS, stage2_seconds
    seconds, least = stage2_seconds(left=26.0, reserve=24.0, seconds_per_step2=0.75)
    assert least and seconds == pytest.approx(MIN_STAGE2_STEPS * 0.75)
    seconds, least = stage2_seconds(left=5.0, reserve=24.0, seconds_per_step2=0.75)
    assert least and seconds == pytest.approx(MIN_STAGE2_STEPS * 0.75)   # (nothing left at all)
    # Where the budget leaves more, stage 2 takes what it leaves.
    seconds, least = stage2_seconds(left=300.0, reserve=24.0, seconds_per_step2=0.75)
    assert not least and seconds == pytest.approx(276.0)


def test_a_spent_deadline_stops_stage2_only_after_its_least_steps():
    import types
    from mi_invrgbl.fit.runner import ValidationStop
    state = types.SimpleNamespace(validation_frames=[], selection={}, log=print)
    plan = types.SimpleNamespace(eval_every=10, name="stage 2")
    stop = ValidationStop(state, plan, deadline=-1.0, score=lambda: 0.0, not_before=54)
    assert all(stop(it) is None for it in range(4, 54))
    assert stop(54) == "its share of the budget is spent"
    # Without a least step count the spent deadline stops it at once.
    stop = ValidationStop(state, plan, deadline=-1.0, score=lambda: 0.0)
    assert stop(4) == "its share of the budget is spent"


def test_a_budgeted_stage2_runs_its_least_steps_whatever_set_its_time(scene_path, tmp_path,
                                                                      monkeypatch):
    # The budget left stage 2 more than its least steps by the timed step
    # (not the minimum's branch), but its steps ran slower than timed: the
    # deadline, spent at once here, still lets it run MIN_STAGE2_STEPS.
    from mi_invrgbl.fit import runner
    from mi_invrgbl.fit.budget import MIN_STAGE2_STEPS
    monkeypatch.setattr(runner, "stage2_seconds", lambda left, reserve, spi: (1e-3, False))
    # Stage 1 is not what is tested: a spent share keeps it to its own least steps.
    monkeypatch.setattr(runner, "stage1_seconds", lambda minutes, elapsed, frames, spi: 1e-3)
    lines = []
    metrics = run_fit(scene_path, small_config(tmp_path, budget_minutes=0.75, eval_every=5,
                                               sun_trial_iterations=0), log=lines.append)
    assert metrics["iterations"]["stage 2"] >= MIN_STAGE2_STEPS, metrics["iterations"]
    stops = [str(x) for x in lines if "stage 2 stops at iteration" in str(x)]
    assert len(stops) <= 1
    if stops and "share of the budget is spent" in stops[0]:
        assert int(stops[0].split("iteration ")[1].split()[0]) >= MIN_STAGE2_STEPS


def test_validation_stop_returns_to_the_best_state():
    # A stage whose validation score peaks at iteration 2 and falls after:
    # it stops after PATIENCE evaluations without a gain and goes back to
    # the state kept at its best; where the last state scores best it stays.
    import types
    from mi_invrgbl.fit.budget import PATIENCE
    from mi_invrgbl.fit.runner import ValidationStop
    scores = {1: 20.0, 2: 22.0, 3: 21.0, 4: 20.5, 5: 20.2, 6: 20.0}
    lines = []
    state = types.SimpleNamespace(validation_frames=[object()], selection={}, log=lines.append)
    plan = types.SimpleNamespace(eval_every=1, name="stage 1")
    now = {"it": 0}
    stop = ValidationStop(state, plan, float("inf"), lambda: scores[now["it"]],
                          keep=lambda: "state@%d" % now["it"])
    reasons = []
    for it in range(1, 7):
        now["it"] = it
        reasons.append(stop(it))
        if reasons[-1]:
            break
    assert reasons[-1] and len(reasons) == 2 + PATIENCE
    restored = []
    assert stop.restore_best(restored.append, now["it"], "stage 1")
    assert restored == ["state@2"] and "back to iteration 2" in lines[-1]
    record = state.selection["budget"]["stage 1"]["best_validation"]
    assert record["iteration"] == 2 and record["kept"] == "best" and record["last_score"] < 22.0
    # Rising to the end: nothing to go back to.
    stop = ValidationStop(state, plan, float("inf"), lambda: float(now["it"]), keep=lambda: now["it"])
    for it in range(1, 4):
        now["it"] = it
        assert stop(it) is None
    assert not stop.restore_best(restored.append, 3, "stage 2") and restored == ["state@2"]
    # A NaN score is never kept as the best, and the stop test's own last
    # score is reused rather than scoring again.
    calls = []
    seq = {1: 20.0, 2: float("nan"), 3: 19.0}

    def counted():
        calls.append(now["it"])
        return seq[now["it"]]
    stop = ValidationStop(state, plan, float("inf"), counted, keep=lambda: now["it"])
    for it in range(1, 4):
        now["it"] = it
        stop(it)
    assert stop.best_iteration == 1 and stop.best_score == 20.0
    assert stop.restore_best(restored.append, 3, "stage 1") and restored[-1] == 1
    assert calls == [1, 2, 3]


def test_log_cadence_keeps_a_budgeted_stage_s_log_to_its_share():
    # A fake clock: steps of 0.35 s, log points of 2.2 s (KITTI's stage 1 on
    # 2 cores). Every 50 steps the points take 11 % of the time; spaced by
    # their cost, about LOG_SHARE, on multiples of 50, and still a curve.
    from mi_invrgbl.fit.loop import LOG_SHARE, LogCadence

    def run(share, steps=3000, step_s=0.35, point_s=2.2):
        now = [0.0]
        cadence = LogCadence(50, share, clock=lambda: now[0], next_at=50)
        points, spent = [], 0.0
        for it in range(1, steps + 1):
            now[0] += step_s
            if cadence.due(it):
                now[0] += point_s
                spent += point_s
                cadence.logged(it, point_s)
                points.append(it)
        return points, spent / now[0]

    every, share_every = run(None)
    assert every == list(range(50, 3001, 50)) and share_every > 0.10
    points, share = run(LOG_SHARE)
    assert share <= LOG_SHARE * 1.05 and share >= LOG_SHARE / 3, share
    assert all(p % 50 == 0 for p in points) and len(points) >= 8
    # Cheap points (a small scene) stay at the configured cadence.
    cheap, _ = run(LOG_SHARE, point_s=0.001)
    assert cheap == list(range(50, 3001, 50))


def test_validation_scores_keep_to_their_share_of_a_budgeted_stage_1():
    # A fake clock: KITTI's stage 1 at 8 minutes on 2 cores, steps of 0.5 s,
    # a validation score of 2 s, the plan's interval 18 steps. Scored on
    # every multiple of 18 the scores take 18 % of the stage; spaced by
    # their cost, about VALIDATION_SHARE, still on multiples of 18, the
    # first on the plan's grid; cheap scores stay on the plan's grid.
    import types
    from mi_invrgbl.fit.budget import VALIDATION_SHARE
    from mi_invrgbl.fit.runner import ValidationStop

    def run(score_s, steps=400, step_s=0.5, every=18, start=0, share=VALIDATION_SHARE):
        now = [0.0]

        def score():
            now[0] += score_s
            return 20.0 + 1e-3 * now[0]     # rising: no plateau, no stop
        state = types.SimpleNamespace(validation_frames=[object()], selection={}, log=print)
        plan = types.SimpleNamespace(eval_every=every, name="stage 1")
        stop = ValidationStop(state, plan, float("inf"), score, share=share, clock=lambda: now[0])
        scored = []
        for it in range(start + 1, start + steps + 1):
            now[0] += step_s
            before = stop.scores
            assert stop(it) is None
            if stop.scores > before:
                scored.append(it)
        return scored, stop.score_seconds / now[0], state.selection["budget"]["stage 1"]["validation"]

    scored, share, record = run(2.0)
    assert all(it % 18 == 0 for it in scored) and scored[0] == 18
    # (The second score comes on the grid too: the cadence needs two to
    # measure a step's time; over 400 steps that adds a few tenths of a per cent.)
    assert share <= VALIDATION_SHARE * 1.2 and 3 <= len(scored) <= 8, (scored, share)
    assert record["scores"] == len(scored) and abs(record["seconds"] - 2.0 * len(scored)) < 1e-6
    assert record["every"] > 18
    cheap, share, _ = run(0.01)
    assert cheap == list(range(18, 401, 18)) and share < VALIDATION_SHARE
    # A resumed stage (from iteration 100) scores first on the plan's grid.
    resumed, _, _ = run(2.0, start=100)
    assert resumed[0] == 108 and all(it % 18 == 0 for it in resumed)
    # Without a share (stage 2's stop) every multiple of the interval scores.
    grid, share, _ = run(2.0, share=None)
    assert grid == list(range(18, 401, 18)) and share > 0.15


def test_validation_stop_lowers_the_rates_at_a_plateau_before_it_stops():
    # A stage that levels off goes back to its best state with every rate
    # PLATEAU_LR_FACTOR lower, PLATEAU_REDUCTIONS times, then stops; the
    # resumed stage that improves again counts its patience afresh.
    import types
    from mi_invrgbl.fit.budget import PATIENCE, PLATEAU_LR_FACTOR, PLATEAU_REDUCTIONS
    from mi_invrgbl.fit.runner import ValidationStop
    assert PLATEAU_REDUCTIONS == 2
    lines = []
    state = types.SimpleNamespace(validation_frames=[object()], selection={}, log=lines.append)
    plan = types.SimpleNamespace(eval_every=1, name="stage 2")
    # Up to 2 at iteration 2, level for PATIENCE evaluations, up again after
    # the first reduction, level again twice.
    scores = [20.0, 22.0] + [21.9] * PATIENCE + [22.5] + [22.4] * PATIENCE + [22.4] * PATIENCE
    resumed = []
    now = {"it": 0}
    stop = ValidationStop(state, plan, float("inf"), lambda: scores[now["it"] - 1],
                          keep=lambda: "state@%d" % now["it"],
                          resume_from=lambda kept, damping: resumed.append((kept, damping)))
    reason = None
    for it in range(1, len(scores) + 1):
        now["it"] = it
        reason = stop(it)
        if reason:
            break
    first, second = 2 + PATIENCE, 3 + 2 * PATIENCE
    assert resumed == [("state@2", PLATEAU_LR_FACTOR), ("state@%d" % (first + 1), PLATEAU_LR_FACTOR ** 2)]
    assert stop.plateaus == [first, second]
    assert reason and now["it"] == second + PATIENCE
    assert state.selection["budget"]["stage 2"]["plateaus"] == [
        {"at": first, "back_to": 2}, {"at": second, "back_to": first + 1}]
    assert "back to it with the learning rates x0.3" in lines[0]
    # Without a way back (or without a kept state) it stops at the first plateau.
    stop = ValidationStop(state, plan, float("inf"), lambda: scores[now["it"] - 1])
    for it in range(1, len(scores) + 1):
        now["it"] = it
        if stop(it):
            break
    assert now["it"] == first and stop.plateaus == []


def test_optimizer_damping_scales_the_schedules_and_survives_a_rebuild():
    import drjit as dr
    import mitsuba as mi
    from mi_invrgbl.fit.variables import Optimizer
    from mi_invrgbl.fit.budget import ANNEAL_END, ANNEAL_FROM, anneal_lr_factor

    class Var:
        def __init__(self, key, lr):
            self.key, self.lr, self.node = key, lr, None
            self.value = mi.Float([1.0, 2.0])

        def read(self):
            return self.value

    opt = Optimizer([Var("a", 0.1), Var("b", 0.01)])
    lr = lambda o, k: float(o.adam.state[k][2])   # noqa: E731
    opt.set_damping(0.3)
    assert lr(opt, "a") == pytest.approx(0.03) and lr(opt, "b") == pytest.approx(0.003)
    opt.scale_learning_rates(0.5, lambda v: v.key == "a")
    assert lr(opt, "a") == pytest.approx(0.015) and lr(opt, "b") == pytest.approx(0.003)
    new = opt.rebuild([Var("a", 0.1), Var("b", 0.01)], {})
    assert new.damping == 0.3 and lr(new, "a") == pytest.approx(0.03)
    # Stage 1's anneal: flat until ANNEAL_FROM, ANNEAL_END at the end, monotone.
    assert anneal_lr_factor(0.0) == anneal_lr_factor(ANNEAL_FROM) == 1.0
    assert anneal_lr_factor(1.0) == pytest.approx(ANNEAL_END) == anneal_lr_factor(2.0)
    f = [anneal_lr_factor(p) for p in np.linspace(0, 1, 50)]
    assert all(a >= b for a, b in zip(f, f[1:])) and dr.all(mi.Bool(True))
    # The same shape from FitConfig's anneal_from / anneal_end; from 1: none.
    assert anneal_lr_factor(0.5, 0.5, 0.03) == 1.0
    assert anneal_lr_factor(0.75, 0.5, 0.03) == pytest.approx(0.03 ** 0.5)
    assert anneal_lr_factor(1.0, 0.5, 0.03) == pytest.approx(0.03)
    assert anneal_lr_factor(1.0, 1.0, 0.03) == 1.0


def test_batch_probe_keeps_larger_batches_only_where_they_are_cheap():
    import time
    from mi_invrgbl.fit.budget import probe_batch_scale, MIN_STEPS

    def machine(cost):
        scale = [1]

        def step(it):
            time.sleep(cost(scale[0]))

        def set_scale(k):
            scale[0] = k
        return step, set_scale, scale

    # Overhead-bound (a GPU on small batches): 16x the rays for 1.2x the time.
    step, set_scale, scale = machine(lambda k: 0.01 * (1 + 0.0125 * (k - 1)))
    probe = probe_batch_scale(step, set_scale, 10, 60.0, 0.01)
    assert probe.scale == 16 and scale[0] == 16 and probe.iterations_run == 6
    # Proportional to the rays (a CPU): the configured batch stays.
    step, set_scale, scale = machine(lambda k: 0.004 * k)
    probe = probe_batch_scale(step, set_scale, 10, 60.0, 0.004)
    assert probe.scale == 1 and scale[0] == 1 and probe.iterations_run == 3
    # Partly overhead-bound (2 CPU cores on a small scene): 4x the rays for
    # 2.4x the time is not worth a quarter of the steps.
    step, set_scale, scale = machine(lambda k: 0.01 * (1 + 0.467 * (k - 1)))
    assert probe_batch_scale(step, set_scale, 10, 60.0, 0.01).scale == 1
    # Cheap, but the share would leave too few steps: no larger batch.
    step, set_scale, scale = machine(lambda k: 0.01)
    assert probe_batch_scale(step, set_scale, 10, 0.01 * (MIN_STEPS - 1), 0.01).scale == 1


def test_replan_adds_iterations_only_where_the_plan_was_too_slow():
    # A stage planned 96 iterations after iteration 4 at 1 s each, with 100 s
    # to its deadline. Re-timed after a tenth of them: at 0.5 s per step it
    # takes what fits (95 s left at iteration 14: 14 + 190), at the planned
    # speed or slower it keeps its plan, and it never takes more than 4x the
    # plan. It re-times only once.
    from mi_invrgbl.fit.budget import Replan
    capped = 4 + 4 * 96
    for step, expect in ((0.5, 204), (1.0, 100), (2.0, 100), (0.01, capped), (0.0, capped)):
        now = [0.0]
        r = Replan(first=4, deadline=100.0, clock=lambda: now[0])
        total = 100
        for it in range(5, 14):
            now[0] += step
            assert r(it, total) == total         # before a tenth of the plan has run
        now[0] += step
        total = r(14, total)
        assert total == expect, (step, total)
        assert r.timed == pytest.approx(step, abs=1e-9)
        now[0] += 50 * step
        assert r(64, total) == total             # once only


def test_stage1_plan_and_replan_stop_at_the_step_cap():
    # A share that holds 10 000 steps of the configured batch (a CPU: no
    # larger batches) plans STAGE1_MAX_STEPS and says what it cut; a share
    # below the cap is planned as before; a re-timed plan never passes it.
    from mi_invrgbl.fit.budget import Replan, STAGE1_MAX_STEPS, plan_stage
    big = plan_stage("stage 1", 1000.0, 0.1, done=4, batched=False, most=STAGE1_MAX_STEPS)
    assert big.iterations == STAGE1_MAX_STEPS and big.uncapped == 10004
    assert big.as_dict()["uncapped_iterations"] == 10004
    assert big.eval_every == STAGE1_MAX_STEPS // 12
    small = plan_stage("stage 1", 100.0, 0.1, done=4, batched=False, most=STAGE1_MAX_STEPS)
    assert small.iterations == 1004 and small.uncapped is None
    assert "uncapped_iterations" not in small.as_dict()
    now = [0.0]
    r = Replan(first=4, deadline=1000.0, clock=lambda: now[0], most=STAGE1_MAX_STEPS)
    total = 1004
    now[0] += 1.0                      # 100 steps in 1 s: 99 000 more would fit
    assert r(104, total) == STAGE1_MAX_STEPS
    r = Replan(first=4, deadline=1000.0, clock=lambda: now[0], most=500)
    assert r(104, total) == total      # a cap below the plan never shortens it


def test_stage2_scores_its_validation_frames_at_most_every_interval():
    # Stage 2's plateau test waits PATIENCE scores: a long plan (60 minutes:
    # 6 000 steps) scores every STAGE2_EVAL_INTERVAL steps, not every 500,
    # so it waits as many steps as a short one; a short plan keeps its twelfth.
    from mi_invrgbl.fit.budget import (EVALUATIONS, MIN_EVAL_INTERVAL, STAGE2_EVAL_INTERVAL,
                                       plan_stage)
    long = plan_stage("stage 2", 2200.0, 0.36, done=4, batched=False,
                      longest_interval=STAGE2_EVAL_INTERVAL)
    assert long.iterations == 4 + int(2200.0 / 0.36)
    assert long.eval_every == STAGE2_EVAL_INTERVAL < long.iterations // EVALUATIONS
    short = plan_stage("stage 2", 100.0, 0.36, done=4, batched=False,
                       longest_interval=STAGE2_EVAL_INTERVAL)
    assert short.eval_every == short.iterations // EVALUATIONS < STAGE2_EVAL_INTERVAL
    assert plan_stage("stage 2", 2200.0, 0.36, batched=False).eval_every == 6111 // EVALUATIONS
    assert plan_stage("stage 2", 10.0, 0.36, batched=False,
                      longest_interval=1).eval_every == MIN_EVAL_INTERVAL


@pytest.mark.slow
@pytest.mark.parametrize("slow", [4.0])
def test_budget_retimes_a_stage_planned_from_busy_steps(scene_path, tmp_path, monkeypatch, slow):
    # The steps a stage times at its start ran while another job held the
    # cores (here: their time reads 4x too long): the plan is too short, and
    # the stage, re-timed after a tenth of it, takes the iterations its share
    # still holds instead of ending with most of its share unused.
    from mi_invrgbl.fit import runner
    real = runner.time_iterations
    monkeypatch.setattr(runner, "time_iterations", lambda *a, **k: slow * real(*a, **k))
    lines = []
    budget = 1.5
    metrics = run_fit(scene_path, small_config(tmp_path, budget_minutes=budget, eval_every=5),
                      log=lines.append)
    plan = metrics["selection"]["budget"]["stage 2"]
    print("\n".join(str(x) for x in lines if "budget" in str(x) or "stops" in str(x)), plan)
    assert "replanned" in plan, plan
    assert plan["iterations"] > plan["replanned"]["iterations_before"]
    assert plan["replanned"]["seconds_per_iteration"] < plan["seconds_per_iteration"]
    assert any("stage 2 re-timed" in str(x) for x in lines)
    # Still within its share, and the log ends at the raised plan or an early stop.
    assert metrics["times_s"]["stage 2"] <= plan["seconds"] + 3 * plan["seconds_per_iteration"] + 5
    last = metrics["iterations"]["stage 2"]
    assert last <= plan["iterations"]
    assert last > plan["replanned"]["iterations_before"] or any(
        str(x).startswith("[fit] stage 2 stops") for x in lines)


@pytest.mark.slow
def test_budget_sets_iterations_and_stops_in_time(scene_path, tmp_path):
    import csv
    budget = 1.5   # minutes: the fixed costs (tracing, selection, outputs) take about half
    lines = []
    metrics = run_fit(scene_path, small_config(tmp_path, budget_minutes=budget, eval_every=5),
                      log=lines.append)
    print("\n".join(str(x) for x in lines if "budget" in str(x) or "stops" in str(x)))
    plans = metrics["selection"]["budget"]
    print(plans, metrics["times_s"])
    rows = list(csv.DictReader(open(tmp_path / "log.csv")))
    from mi_invrgbl.fit.budget import SHARES
    # Stage 1 keeps to its share; stage 2 takes what is left of the budget.
    for stage, share in (("stage 1", SHARES["stage 1"]), ("stage 2", 1.0)):
        plan = plans[stage]
        assert plan["iterations"] > 4 and plan["seconds_per_iteration"] > 0
        assert plan["seconds"] <= share * 60 * budget + 1e-6
        last = max(int(r["iteration"]) for r in rows if r["stage"] == stage)
        assert last <= plan["iterations"]
        stopped = [str(x) for x in lines if str(x).startswith("[fit] %s stops" % stage)]
        assert last == plan["iterations"] or stopped, (stage, last, plan)
        # A stage's training ends within its share (plus the iteration that
        # crossed the deadline and the last evaluations).
        assert metrics["times_s"][stage] <= plan["seconds"] + 3 * plan["seconds_per_iteration"] + 5
    # The iteration counts came from the budget, not --stage1/--stage2 (10 and 24 here).
    assert plans["stage 1"]["iterations"] != 10
    assert metrics["interrupted"] is False and np.isfinite(metrics["heldout_psnr"])
    # Stage 2's lighting followed its normals before its validation scores.
    retraced = metrics["selection"]["lighting_retraced"]
    assert retraced["refreshes"] >= 1 and retraced["turn_deg"] > 0
    assert retraced["gaussians"] >= 0 and retraced["seconds"] >= 0


def test_budgeted_stages_go_back_and_on_at_their_plateaus(scene_path, tmp_path, monkeypatch):
    # Every validation score made to count as no gain: each budgeted stage
    # goes back to its best state with lower rates PLATEAU_REDUCTIONS times
    # (through the stages' real snapshots and optimisers) and then stops.
    from mi_invrgbl.fit import runner
    from mi_invrgbl.fit.budget import EarlyStop, PLATEAU_REDUCTIONS
    monkeypatch.setattr(runner, "EarlyStop", lambda: EarlyStop(patience=1, min_gain=1e9))
    lines = []
    metrics = run_fit(scene_path, small_config(tmp_path, budget_minutes=0.6, eval_every=5),
                      log=lines.append)
    plans = metrics["selection"]["budget"]
    for stage in ("stage 1", "stage 2"):
        stops = [str(x) for x in lines if str(x).startswith("[fit] %s stops" % stage)]
        if "validation score" not in "".join(stops):
            continue     # the stage's time ran out first
        assert len(plans[stage]["plateaus"]) == PLATEAU_REDUCTIONS, plans[stage]
    assert any("plateaus" in plans[s] for s in plans), plans
    assert any("back to it with the learning rates x0.09" in str(x) for x in lines)
    assert metrics["interrupted"] is False and np.isfinite(metrics["heldout_psnr"])


@pytest.mark.slow
def test_budgeted_stage1_stops_at_the_step_cap(scene_path, tmp_path, monkeypatch):
    # The runner plans and re-plans stage 1 under STAGE1_MAX_STEPS (here 12,
    # far below what the share holds): stage 1 ends at the cap, records what
    # the share held, and says so; stage 2 still runs.
    # Stage 2 is planned with scores at most STAGE2_EVAL_INTERVAL steps apart.
    from mi_invrgbl.fit import runner
    monkeypatch.setattr(runner, "STAGE1_MAX_STEPS", 12)
    planned = {}

    def plan_stage(name, *args, **kwargs):
        planned[name] = kwargs
        return budget_plan_stage(name, *args, **kwargs)
    budget_plan_stage = runner.plan_stage
    monkeypatch.setattr(runner, "plan_stage", plan_stage)
    lines = []
    metrics = run_fit(scene_path, small_config(tmp_path, budget_minutes=0.6, eval_every=5),
                      log=lines.append)
    plan = metrics["selection"]["budget"]["stage 1"]
    print(plan)
    assert planned["stage 2"]["longest_interval"] == runner.STAGE2_EVAL_INTERVAL
    assert plan["iterations"] == 12 and plan["uncapped_iterations"] > 12
    assert metrics["iterations"]["stage 1"] <= 12
    assert any("stage 1 takes 12 steps" in str(x) for x in lines)
    assert metrics["iterations"]["stage 2"] > 0 and np.isfinite(metrics["heldout_psnr"])


@pytest.mark.slow
def test_a_stage_that_goes_back_logs_the_state_it_keeps(scene_path, tmp_path, monkeypatch):
    # A budgeted stage that goes back to its best validation state logs one
    # more row at its last iteration, scored on the kept state, and
    # metrics.json's held-out score is that row's (not the state it left).
    import csv
    from mi_invrgbl.fit import runner
    went_back = []

    def back_to_the_first_kept(self, restore, it, name):
        if self.best_state is None:
            return False
        restore(self.best_state)
        went_back.append(name)
        return True
    monkeypatch.setattr(runner.ValidationStop, "restore_best", back_to_the_first_kept)
    metrics = run_fit(scene_path, small_config(tmp_path, budget_minutes=0.6, eval_every=5),
                      log=lambda *a: None)
    rows = list(csv.DictReader(open(tmp_path / "log.csv")))
    assert went_back
    for stage in set(went_back):
        its = [int(r["iteration"]) for r in rows if r["stage"] == stage]
        assert its[-1] == its[-2] == metrics["iterations"][stage], (stage, its[-4:])
    assert metrics["heldout_psnr"] == pytest.approx(float(rows[-1]["heldout_psnr"]), abs=1e-3)


def test_stage2_start_is_restored_exactly(scene_path, tmp_path):
    # The sun trial runs a second candidate from the same start and may go
    # back to the first: every node value, the step sizes, the shading start
    # and the visibility flag come back; values changed after the snapshot
    # (arrays are replaced, not written into) do not leak into it.
    from mi_invrgbl.fit.init import load_state
    state = load_state(scene_path, small_config(tmp_path), log=lambda *a: None)
    state.lr_state["stage 2"] = {"albedo": 0.01}
    state.selection["shading_init"] = {"light_scale": 1.0}
    point = state.stage2_start()
    before = {n: {k: np.array(v) for k, v in node.values.items()}
              for n, node in state.model.nodes.items()}
    for node in state.model.nodes.values():
        for k in list(node.values):
            node.values[k] = node.values[k] * 0.5 + 1.0
        node.values["extra"] = mi.Float(1.0)
    state.lr_state["stage 2"] = {"albedo": 0.5}
    state.lr_state["other"] = {}
    state.selection["shading_init"] = {"light_scale": 4.0}
    state.sun_visibility_learned = not point.sun_visibility_learned
    state.restore_stage2_start(point)
    for n, node in state.model.nodes.items():
        assert sorted(node.values) == sorted(before[n])
        for k, v in node.values.items():
            np.testing.assert_array_equal(np.array(v), before[n][k])
    assert state.lr_state == {"stage 2": {"albedo": 0.01}}
    assert state.selection["shading_init"] == {"light_scale": 1.0}
    assert state.sun_visibility_learned == point.sun_visibility_learned


def test_a_budget_below_the_fixed_costs_is_reported(scene_path, tmp_path):
    # A budget smaller than loading, tracing and selection: the fit still
    # finishes (both stages get their timed steps only), and its last log
    # line says where the time went instead of leaving the overrun unexplained.
    lines = []
    metrics = run_fit(scene_path, small_config(tmp_path, budget_minutes=0.02, eval_every=5),
                      log=lines.append)
    assert metrics["wall_s"] > 1.05 * 0.02 * 60
    note = [str(x) for x in lines if str(x).startswith("[fit] ran ")]
    assert len(note) == 1 and "of a 0.02-minute budget" in note[0], lines[-3:]
    assert "the stages took" in note[0] and "which no budget shrinks" in note[0]
    # ...and said so once stage 1 was timed, before it ran.
    early = [str(x) for x in lines if "is too little for this scene" in str(x)]
    assert len(early) == 1 and lines.index(early[0]) < lines.index(note[0])
    # Steps of a second or more are named (freezing the geometry, at least).
    assert ("freeze %.0f s" % metrics["times_s"]["freeze"] in note[0]) == \
        (metrics["times_s"]["freeze"] >= 1.0)


@pytest.mark.slow   # (40-50 s each on 2 cores: real budgeted fits)
def test_sun_trial_keeps_to_its_share_of_a_budget(scene_path, tmp_path, monkeypatch):
    # Under a budget the trial of a narrowly rejected sun takes at most
    # SUN_TRIAL_STEPS of stage 2's share, however many iterations it may run.
    from mi_invrgbl.fit import runner
    real_choose = runner.choose_lighting

    def narrowly_rejected(state):
        choice = real_choose(state)
        choice.report["sun"].update(gain=0.03, use_sun=False,
                                    direction=choice.report["sun"].get("direction", [0.3, 0.4, 0.866]))
        choice.use_sun, choice.sun_direction, choice.sun_irradiance = False, None, 0.0
        return choice

    monkeypatch.setattr(runner, "choose_lighting", narrowly_rejected)
    # (However little of stage 2's share this tiny budget leaves it.)
    monkeypatch.setattr(runner.Budget, "sun_trial_fits", lambda self, *a: True)
    budget = 0.75
    metrics = run_fit(scene_path, small_config(tmp_path, budget_minutes=budget, eval_every=5,
                                               sun_trial_iterations=100000), log=lambda *a: None)
    t = metrics["selection"]["sun"]["trial"]
    from mi_invrgbl.fit.budget import SHARES, SUN_TRIAL_STEPS
    limit = SUN_TRIAL_STEPS * SHARES["stage 2"] * 60 * budget
    assert 0 < t["iterations"] < 100000
    # The sun's start is counted within the limit; the rest is split between
    # the two candidates' steps (plus scoring both and one step past a deadline).
    assert 0 < t["sun_start_seconds"] < t["seconds"]
    assert t["seconds"] < limit + 10, (t, limit)
    assert metrics["iterations"]["stage 2"] >= t["iterations"]


def test_sun_trial_fits_where_stage2_keeps_a_quarter_of_its_share():
    # The trial's start and scores cost the same however few its steps: on
    # the KITTI excerpt at 8 minutes it once took 134 s for one step per
    # candidate and left stage 2 nothing. The trial (a third of stage 2's
    # share, its start included) runs only where stage 2 keeps a quarter of
    # its share after it and the start leaves the trial room for steps.
    import time
    from mi_invrgbl.fit.budget import Budget, OUTPUT_RESERVE, SHARES
    now = time.perf_counter()
    share = SHARES["stage 2"] * 480.0                       # 144 s
    reserve = OUTPUT_RESERVE * 480.0
    late = Budget(8.0, now - (480.0 - (reserve + share / 3 + share / 4 - 5)))
    street = Budget(8.0, now - (480.0 - (reserve + 87.0)))  # the street at 8 minutes
    early = Budget(8.0, now - (480.0 - 300.0))              # 300 s left
    assert late.stage2_left() == pytest.approx(share / 3 + share / 4 - 5, abs=1.0)
    assert not late.sun_trial_fits() and street.sun_trial_fits() and early.sun_trial_fits()
    # A start that would eat more than three quarters of the trial's limit
    # (48 s here) leaves the candidates too few steps: no trial however much
    # time is left (the street's start took 21 s, KITTI's before the sky
    # stopped being re-traced 53-62 s).
    assert street.sun_trial_fits(21.0) and early.sun_trial_fits(35.0)
    assert not early.sun_trial_fits(40.0) and not street.sun_trial_fits(85.0)


@pytest.mark.slow   # (40-50 s each on 2 cores: real budgeted fits)
def test_no_sun_trial_where_stage2_is_short(scene_path, tmp_path, monkeypatch):
    # Where the budget cannot afford the trial the sun test's decision
    # stands and stage 2 gets the time.
    from mi_invrgbl.fit import runner
    monkeypatch.setattr(runner, "choose_lighting", narrow_sun_rejection(runner.choose_lighting))
    monkeypatch.setattr(runner.Budget, "sun_trial_fits", lambda self, *a: False)
    trials = []
    monkeypatch.setattr(runner, "sun_trial", lambda *a, **k: trials.append(a) or (_ for _ in ()).throw(
        AssertionError("the trial ran")))
    metrics = run_fit(scene_path, small_config(tmp_path, budget_minutes=0.75, eval_every=5,
                                               sun_trial_iterations=50), log=lambda *a: None)
    sun = metrics["selection"]["sun"]
    assert not trials and sun["trial"]["skipped"] is True and sun["use_sun"] is False
    assert metrics["iterations"]["stage 2"] > 0


def test_a_sun_trial_that_takes_every_stage2_step_is_logged_as_stage2(scene_path, tmp_path,
                                                                   monkeypatch):
    # Without a budget the trial's steps count in stage 2's: a trial as long
    # as the stage leaves it no steps of its own. Its winner is the stage's
    # result, and log.csv and the iteration count end at stage 2, not stage 1.
    import csv
    from mi_invrgbl.fit import runner
    real_choose = runner.choose_lighting

    narrowly_rejected = narrow_sun_rejection(real_choose)

    monkeypatch.setattr(runner, "choose_lighting", narrowly_rejected)
    metrics = run_fit(scene_path, small_config(tmp_path, stage2_iterations=6,
                                               sun_trial_iterations=50), log=lambda *a: None)
    assert metrics["selection"]["sun"]["trial"]["iterations"] == 6
    assert metrics["iterations"]["stage 2"] == 6
    rows = list(csv.DictReader(open(tmp_path / "log.csv")))
    assert rows[-1]["stage"] == "stage 2" and int(rows[-1]["iteration"]) == 6
    assert np.isfinite(float(rows[-1]["heldout_psnr"]))


@pytest.mark.parametrize("trial, unscorable", [(4, False), (0, False), (4, True)])
def test_sun_trial_decides_a_narrowly_rejected_sun(scene_path, tmp_path, monkeypatch, trial,
                                                   unscorable):
    # The sun test is made to reject its sun narrowly (gain 0.03, bar 0.05):
    # stage 2 then runs `trial` iterations without and with it, scores both
    # on the validation frames only and keeps the better. With --sun-trial 0
    # the test's decision stands. When neither trial can be scored (NaN), the
    # test's decision stands too, and metrics.json holds null, not NaN.
    from mi_invrgbl.fit import runner
    real_choose, real_score = runner.choose_lighting, runner.score_stage2
    scored = []

    narrowly_rejected = narrow_sun_rejection(real_choose)

    def score_spy(stage2, frames, *a, **k):
        scored.append([f.index for f in frames])
        if unscorable and [f.index for f in frames] == [2]:
            return float("nan"), float("nan")
        return real_score(stage2, frames, *a, **k)

    monkeypatch.setattr(runner, "choose_lighting", narrowly_rejected)
    monkeypatch.setattr(runner, "score_stage2", score_spy)
    metrics = run_fit(scene_path, small_config(tmp_path, stage2_iterations=10,
                                               sun_trial_iterations=trial), log=lambda *a: None)
    sun = metrics["selection"]["sun"]
    assert np.isfinite(metrics["heldout_psnr"])
    if trial == 0:
        assert "trial" not in sun and sun["use_sun"] is False
        return
    t = sun["trial"]
    if unscorable:
        assert sun["use_sun"] is False
        def refuse(constant):
            raise AssertionError("metrics.json holds " + constant)
        with open(tmp_path / "metrics.json") as f:
            written = json.load(f, parse_constant=refuse)
        trial_written = written["selection"]["sun"]["trial"]
        assert trial_written["psnr_without"] is None and trial_written["psnr_with"] is None
        return
    assert t["iterations"] == 4 and np.isfinite(t["psnr_without"]) and np.isfinite(t["psnr_with"])
    assert sun["use_sun"] == (t["psnr_with"] > t["psnr_without"] + 0.2)
    # The trial's scores come from the validation frame (2); held-out 4 only in the log.
    trial_scores = [s for s in scored if 4 not in s]
    assert trial_scores and all(s == [2] for s in trial_scores)
    lighting = metrics.get("lighting") or {}
    if "sun_used" in lighting:
        assert lighting["sun_used"] == sun["use_sun"]


def test_stage2_start_chooses_among_sun_directions(scene_path, tmp_path, monkeypatch):
    """Where the sun test keeps other directions, stage 2's start is made
    under each and scored on the validation frames: offered a direction far
    from the true one first, the true one's start scores higher, and the
    kept start is :func:`choose_start`'s pick (the true one's wherever the
    wrong one falls beyond the margin)."""
    from mi_invrgbl.fit import selection
    from mi_invrgbl.fit.stage2 import START_ROUGHNESS
    from mi_invrgbl.fit.shading_init import START_PSNR_MARGIN, choose_start
    from fit_scene import SUN
    true = np.array(SUN) / np.linalg.norm(SUN)
    # Far enough from the truth that the validation frames rule its start
    # out (13.3-13.4 dB against 18.3 in four runs, beyond START_PSNR_MARGIN).
    # A nearer one, (0.6, -0.5, 0.62), started 1.5-2.1 dB below and with an
    # albedo spread close to the true sun's, and once in a CI run its start
    # was kept.
    wrong = np.array([0.9, 0.1, 0.35]) / np.linalg.norm([0.9, 0.1, 0.35])
    monkeypatch.setattr(selection, "alternative_directions",
                        lambda *a: [wrong.tolist(), true.tolist()])
    metrics = run_fit(scene_path, small_config(tmp_path, sun="on", render_samples="8",
                                               stage1_iterations=30, stage2_iterations=4),
                      log=lambda *a: None)
    start = metrics["selection"]["shading_init"]["start_candidates"]
    cands = start["candidates"]
    assert start["scored_on"] == "validation" and len(cands) >= 2
    assert all(np.isfinite(c["psnr"]) for c in cands)
    on_true = [c["psnr"] for c in cands if np.allclose(c["sun_direction"], true, atol=1e-5)]
    on_wrong = [c["psnr"] for c in cands if np.allclose(c["sun_direction"], wrong, atol=1e-5)]
    assert on_true and on_wrong and max(on_true) > max(on_wrong)
    # The kept start is the rule's pick from what the report records: the
    # least albedo spread among the starts within the margin of the best.
    chosen = cands[start["chosen"]]
    assert start["chosen"] == choose_start([c["psnr"] for c in cands],
                                           [c.get("albedo_spread") for c in cands])
    assert np.allclose(metrics["selection"]["sun"]["direction"], chosen["sun_direction"], atol=1e-5)
    # Where the images reject the wrong sun beyond the margin (1.7-2.1 dB
    # below the true one's in local runs; one CI run of this 30-step stage
    # 1 brought it within 1 dB, and its spread then decided), the true
    # one's start is kept.
    if max(on_wrong) < max(on_true) - START_PSNR_MARGIN:
        assert np.allclose(chosen["sun_direction"], true, atol=1e-5)
    # The kept start is made again under each start roughness; the best
    # validation score decides, and its roughness is what stage 2 starts from.
    rough = metrics["selection"]["shading_init"]["start_roughness"]
    scores = [c["psnr"] for c in rough["candidates"]]
    assert rough["scored_on"] == "validation" and len(scores) == 1 + len(START_ROUGHNESS)
    assert all(np.isfinite(scores))
    assert rough["candidates"][int(np.argmax(scores))]["roughness"] == rough["chosen"]
    # (the first is the kept candidate's start above, at the imported roughness)
    assert np.isclose(scores[0], cands[start["chosen"]]["psnr"])
    # Stage 2 went on from the chosen roughness (4 steps at rate 1e-2 move it little).
    ckpt = np.load(tmp_path / "checkpoints" / "latest.npz")
    rough_now = np.concatenate([v for k, v in ckpt.items()
                                if k.startswith("model/") and k.endswith(".roughness")])
    had = 0.5 if rough["chosen"] is None else rough["chosen"]
    assert abs(float(np.median(rough_now)) - had) < 0.06


def test_stage2_start_made_again_when_the_best_was_not_the_last(scene_path, tmp_path, monkeypatch):
    """With no roughness to try, the best sun direction's start, made before
    the last candidate's, is made again: the scene stage 2 fits holds the
    chosen direction, not the last one tried."""
    from mi_invrgbl.fit import selection, stage2
    from fit_scene import SUN
    true = np.array(SUN) / np.linalg.norm(SUN)
    # Far enough from the truth that the validation frames rule its start
    # out (13.3-13.4 dB against 18.3 in four runs, beyond START_PSNR_MARGIN).
    # A nearer one, (0.6, -0.5, 0.62), started 1.5-2.1 dB below and with an
    # albedo spread close to the true sun's, and once in a CI run its start
    # was kept.
    wrong = np.array([0.9, 0.1, 0.35]) / np.linalg.norm([0.9, 0.1, 0.35])
    monkeypatch.setattr(selection, "alternative_directions",
                        lambda *a: [true.tolist(), wrong.tolist()])
    monkeypatch.setattr(stage2, "START_ROUGHNESS", ())
    metrics = run_fit(scene_path, small_config(tmp_path, sun="on", render_samples="8",
                                               stage1_iterations=30, stage2_iterations=4),
                      log=lambda *a: None)
    si = metrics["selection"]["shading_init"]
    cands = si["start_candidates"]["candidates"]
    assert si["start_roughness"]["chosen"] is None and len(si["start_roughness"]["candidates"]) == 1
    chosen = np.array(cands[si["start_candidates"]["chosen"]]["sun_direction"])
    assert np.allclose(chosen, true, atol=1e-5)
    ckpt = np.load(tmp_path / "checkpoints" / "latest.npz")
    assert np.allclose(ckpt["sky/sun_direction"].ravel(), true, atol=1e-4)


def test_stage2_start_scores_the_facings_irradiance_against_the_selection(scene_path, tmp_path,
                                                                         monkeypatch):
    """Where the facings' sun irradiance disagrees with the lighting
    selection's level, the start is made with each; among those the
    validation frames do not rule out, the least albedo spread within
    LiDAR-albedo groups chooses, and the chosen start's irradiance is the
    one in the scene."""
    from mi_invrgbl.fit import shading_init
    monkeypatch.setattr(shading_init, "MAX_EXCESS", 1e-3)     # every estimate "disagrees"
    monkeypatch.setattr(shading_init, "MAX_DISAGREEMENT", 1e-3)
    metrics = run_fit(scene_path, small_config(tmp_path, sun="on", render_samples="8",
                                               stage1_iterations=30, stage2_iterations=4),
                      log=lambda *a: None)
    si = metrics["selection"]["shading_init"]
    cands = si["start_candidates"]["candidates"]
    sources = [c["sun_irradiance_from"] for c in cands]
    assert any(s.startswith("selection (facings gave") for s in sources) and "facings" in sources
    assert all(np.isfinite(c["psnr"]) for c in cands)
    assert all(c["albedo_spread"] is not None and np.isfinite(c["albedo_spread"]) for c in cands)
    best = shading_init.choose_start([c["psnr"] for c in cands], [c["albedo_spread"] for c in cands])
    assert si["start_candidates"]["chosen"] == best
    assert si["sun_irradiance_from"] == sources[best]


def start_against_stage1(scene_path, out, unclipped=False, **config):
    """Stage 2's start made on the fit tests' street (sun on, one ray per
    pixel): its ``shading_init`` report and the mean and RMS difference of
    its picture from stage 1's on the same frozen hits, each blended
    without the sky and divided by the blended opacity (pixels at least half
    covered, every training frame; with ``unclipped``, only those where no
    Gaussian whose starting albedo sits at a bound (0.02 or 1) has a blend
    weight of 1 % or more)."""
    from mi_invrgbl.fit import runner
    from mi_invrgbl.fit.init import load_state
    from mi_invrgbl.fit.render import VirtualNode, frozen_gaussian_hits
    from mi_invrgbl.physics import hits as hitlib

    # One ray per pixel, as the frozen hits below are traced.
    state = load_state(scene_path, small_config(out, sun="on", pixel_grid=1, **config),
                       log=lambda *a: None)
    runner.apply_lighting(state, runner.choose_lighting(state))
    stage2, frozen = runner.freeze(state, initialise=True)
    si = state.selection["shading_init"]
    diffs = []
    vals = stage2.values()
    for f in state.train_frames:
        # Both pictures on the same frozen hits, blended without the sky
        # behind them (stage 1's Gaussians are far from opaque after ten
        # steps): the start's shaded colour and stage 1's colour.
        nodes = frozen.nodes(f, vals)
        cn = [VirtualNode(n.id, n.data, n.opacities,
                          {"albedo": state.model.nodes[name].values["colour"]}, n.count)
              for n, name in zip(nodes, state.model.nodes)]
        fh = frozen.camera[f.index]
        g = frozen_gaussian_hits(nodes, f.camera.rays, fh)
        lighting = stage2.lighting(nodes, frozen.cache(f), frame=f)
        shaded, *_ = state.camera_integrator.shade_gaussian_hits(lighting, nodes, f.camera.rays,
                                                                  fh, g)
        col = mi.Color3f(hitlib.gather_attribute(cn, "albedo", g.node_ids, g.prims, g.active))
        pics = [hitlib.composite_front_to_back(g, fh.weight, fh.t_after, {"rgb": c},
                                               {"rgb": mi.Color3f(0.0)})["rgb"]
                for c in (shaded, col)]
        alpha = hitlib.composite_front_to_back(g, fh.weight, fh.t_after,
                                               {"a": mi.Color3f(1.0)}, {"a": mi.Color3f(0.0)})["a"]
        a = np.array(alpha[0]) > 0.5
        if unclipped:
            alb = hitlib.gather_attribute(nodes, "albedo", g.node_ids, g.prims, g.active)
            at_bound = mi.Float(dr.any((alb >= 0.999) | (alb <= 0.0201)))
            w = hitlib.composite_front_to_back(g, fh.weight, fh.t_after,
                                               {"b": mi.Color3f(at_bound)},
                                               {"b": mi.Color3f(0.0)})["b"]
            a &= np.array(w[0]) < 0.01
        cover = np.maximum(np.array(alpha[0]), 1e-6)[:, None]
        d = (np.array(pics[0]).T - np.array(pics[1]).T) / cover
        diffs.append(d[a])
    d = np.concatenate(diffs)
    return si, float(d.mean()), float(np.sqrt(np.mean(d ** 2)))


def test_stage2_start_leaves_the_specular_light_out_of_the_albedo(scene_path, tmp_path,
                                                                  monkeypatch):
    """Stage 1's colour is diffuse plus specular light. The start's albedo
    takes the specular part (:meth:`Stage2.seen_by_cameras`) out and is solved
    with the render's own bounce light, so the start renders stage 1's
    picture: its pixels are neither brighter nor darker on average, and
    closer than with an albedo that takes the whole colour as diffuse light."""
    from mi_invrgbl.fit.stage2 import Stage2

    si, bias, rmse = start_against_stage1(scene_path, tmp_path / "with")

    def no_specular(self, names, frames=8, transmission=False):
        count = sum(self.ctx.model.nodes[n].count for n in names)
        return np.zeros((count, 3)), np.ones((count, 1))

    monkeypatch.setattr(Stage2, "seen_by_cameras", no_specular)
    _, bias0, rmse0 = start_against_stage1(scene_path, tmp_path / "without")
    print(si["specular_share"], bias, rmse, bias0, rmse0)
    assert 0.0 < si["specular_share"] < 1.0
    assert bias0 > 0.004            # the specular light on top: too bright
    assert abs(bias) < 0.003
    assert rmse < 0.7 * rmse0


def test_stage2_start_with_the_diffuse_light_through_a_coat(scene_path, tmp_path, monkeypatch):
    """With ``diffuse_fresnel`` the render dims each Gaussian's diffuse
    light by the coat's transmission on the way in and out. The start's
    albedo divides both out, the way out as the training cameras see it
    (blend-weighted over their views), so each Gaussian whose albedo lies
    above its floor renders, averaged over those views, stage 1's colour.
    This street's images have no coat, and its cameras see the ground at
    grazing angles, where the way out lets 0.3-0.4 of the light through: a
    coated ground would need an albedo above 1 almost everywhere. So the
    albedo's upper bound is lifted here (to 10), which leaves the check to
    the division itself. With the way out taken as 1 the same Gaussians
    render too dark."""
    from mi_invrgbl.fit import runner, shading_init
    from mi_invrgbl.fit.init import load_state
    from mi_invrgbl.fit.render import frozen_gaussian_hits
    from mi_invrgbl.fit.stage2 import Stage2

    monkeypatch.setattr(shading_init, "albedo_from_shading", lambda colour, sky, sun: np.clip(
        colour / np.maximum(sky + sun, 1e-3), 0.02, 10.0))

    def start(tag):
        state = load_state(scene_path, small_config(tmp_path / tag, sun="on", pixel_grid=1,
                                                    diffuse_fresnel=True), log=lambda *a: None)
        runner.apply_lighting(state, runner.choose_lighting(state))
        stage2, frozen = runner.freeze(state, initialise=True)
        vals = stage2.values()
        acc, wsum = None, None
        for f in state.train_frames:
            nodes = frozen.nodes(f, vals)
            fh = frozen.camera[f.index]
            g = frozen_gaussian_hits(nodes, f.camera.rays, fh)
            lighting = stage2.lighting(nodes, frozen.cache(f), frame=f)
            shaded, *_ = state.camera_integrator.shade_gaussian_hits(lighting, nodes,
                                                                      f.camera.rays, fh, g)
            gi = np.array(lighting.table.global_index(fh.node_ids, fh.prims))
            w = np.where(f.camera.valid()[np.array(fh.ray)], np.array(fh.weight, np.float64), 0.0)
            c = np.array(shaded, np.float64).T
            if acc is None:
                acc, wsum = np.zeros((lighting.table.total, 3)), np.zeros(lighting.table.total)
            wsum += np.bincount(gi, w, minlength=wsum.size)
            for k in range(3):
                acc[:, k] += np.bincount(gi, w * c[:, k], minlength=wsum.size)
        names = list(state.model.nodes)
        colour = np.concatenate([state.model.nodes[n].numpy("colour") for n in names])
        albedo = np.concatenate([state.model.nodes[n].numpy("albedo") for n in names])
        inside = np.all(albedo > 0.021, axis=1) & (wsum > 0.5)
        d = acc[inside] / wsum[inside, None] - colour[inside]
        return int(inside.sum()), float(np.median(d)), float(np.mean(d))

    n, median, mean = start("coat")
    original = Stage2.seen_by_cameras

    def way_out_as_1(self, names, frames=8, transmission=False):
        spec, t_out = original(self, names, frames, transmission)
        return spec, np.ones_like(t_out)

    monkeypatch.setattr(Stage2, "seen_by_cameras", way_out_as_1)
    n1, median1, mean1 = start("coat_out1")
    print(n, median, mean, n1, median1, mean1)
    assert n > 50 and n1 > 50
    assert abs(median) < 0.003
    assert median1 < -0.01


def test_pixel_rays_at_offsets_within_the_pixel():
    # A pixel's far edge is its right neighbour's near edge, and no offset
    # is the centre; eval's 2 x 2 scoring (fit.evaluate) relies on both.
    from mi_invrgbl.fit.observations import camera_rays, pixel_rays
    sensor = mi.load_dict({"type": "perspective", "fov": 60, "to_world": mi.ScalarTransform4f().look_at(
        origin=[0, 0, 0], target=[0, 0, 1], up=[0, 1, 0]),
        "film": {"type": "hdrfilm", "width": 8, "height": 4}})
    w, h = 8, 4
    idx = mi.UInt32([0, 9, 30])
    centre = camera_rays(sensor, w, h)
    a = pixel_rays(sensor, w, h, idx)
    np.testing.assert_allclose(np.array(a.d), np.array(dr.gather(mi.Vector3f, centre.d, idx)), atol=1e-6)
    one, zero = mi.Float([1.0, 1.0, 1.0]), mi.Float([0.0, 0.0, 0.0])
    right_edge = pixel_rays(sensor, w, h, idx, (one, mi.Float([0.5, 0.5, 0.5])))
    next_left = pixel_rays(sensor, w, h, idx + 1, (zero, mi.Float([0.5, 0.5, 0.5])))
    np.testing.assert_allclose(np.array(right_edge.d), np.array(next_left.d), atol=1e-6)
    assert np.abs(np.array(right_edge.d) - np.array(a.d)).max() > 1e-3


def test_pixel_area_hits_average_the_sub_pixel_rays(scene_path, tmp_path):
    """Stage 2's camera hits merged over a 2 x 2 grid of rays per pixel
    (:func:`freeze_pixels`) composite what the four sub-ray traces average:
    every per-hit channel and the sky seen through them. A merged list holds
    each Gaussian once per pixel, and grid 1 is the centre ray's trace."""
    from mi_invrgbl.fit.init import load_state
    from mi_invrgbl.fit.observations import pixel_rays
    from mi_invrgbl.fit.render import freeze, freeze_pixels, frozen_gaussian_hits
    from mi_invrgbl.physics import hits as hitlib

    state = load_state(scene_path, small_config(tmp_path), log=lambda *a: None)
    frame = state.train_frames[0]
    state.model.push(frame.poses, stage=1)
    cam, scene = frame.camera, state.scene
    nodes = hitlib.gaussian_nodes(scene)
    n = cam.width * cam.height

    def channels(fh, rays):
        g = frozen_gaussian_hits(nodes, rays, fh)
        colour = hitlib.gather_attribute(nodes, "albedo", g.node_ids, g.prims, g.active)
        out = hitlib.composite_front_to_back(g, fh.weight, fh.t_after,
                                             {"rgb": mi.Color3f(colour), "alpha": 1.0},
                                             {"rgb": mi.Color3f(dr.select(fh.surface, 0.0, 0.7))})
        return np.stack([np.array(out["rgb"][c]) for c in range(3)] + [np.array(out["alpha"])], 1)

    merged = freeze_pixels(scene, cam, 2, 32, 1e-2, 1e-4)
    average, separate = 0.0, 0
    for v in (0.25, 0.75):
        for u in (0.25, 0.75):
            rays = pixel_rays(cam.sensor, cam.width, cam.height, dr.arange(mi.UInt32, n),
                              (dr.full(mi.Float, u, n), dr.full(mi.Float, v, n)))
            fh = freeze(scene, rays, 32, 1e-2, 1e-4)
            average, separate = average + channels(fh, rays) / 4, separate + fh.hit_count
    got = channels(merged, cam.rays)
    assert np.all(np.isfinite(got)) and average[:, 3].max() > 0.5      # Gaussians are seen
    np.testing.assert_allclose(got, average, atol=2e-5)
    keys = np.array(merged.ray).astype(np.int64) * 10 ** 9 + np.array(merged.prims) * 100 \
        + np.array(merged.node_ids) % 100
    assert len(np.unique(keys)) == merged.hit_count
    assert merged.hit_count < 0.75 * separate          # sub-rays share most Gaussians
    one = freeze_pixels(scene, cam, 1, 32, 1e-2, 1e-4)
    np.testing.assert_array_equal(np.array(one.weight),
                                  np.array(freeze(scene, cam.rays, 32, 1e-2, 1e-4).weight))
    with pytest.raises(ValueError, match="pixel grid"):
        freeze_pixels(scene, cam, 9)


@pytest.mark.slow   # (40-50 s each on 2 cores: real budgeted fits)
def test_a_resumed_budgeted_fit_goes_on_as_planned(scene_path, tmp_path, monkeypatch):
    """A budgeted fit interrupted in stage 1 and resumed goes on with its
    plan: the learning-rate schedules from where they stood (not from the
    stage's start), the validation stop and the log's cadence; a fit
    interrupted in stage 2 resumes with its validation stop too. The
    budget counts the first run's time."""
    from mi_invrgbl.fit import runner, stage1, stage2
    from mi_invrgbl.fit.budget import resumed_plan, resumed_progress

    # The progress a resumed stage goes on from, and its plan.
    assert resumed_progress(0.4, 100, 100, 200) == pytest.approx(0.4)
    assert resumed_progress(0.4, 100, 150, 200) == pytest.approx(0.7)
    assert resumed_progress(0.4, 100, 200, 200) == pytest.approx(1.0)
    assert resumed_progress(0.9, 100, 100, 100) == 1.0
    plan = resumed_plan("stage 1", {"seconds_per_iteration": 0.5, "iterations": 200,
                                    "batch_scale": 2, "eval_every": 16,
                                    "replanned": {"seconds_per_iteration": 0.25}}, 100, 200)
    assert (plan.seconds, plan.iterations, plan.batch_scale, plan.eval_every) == (25.0, 200, 2, 16)

    real1, real2 = stage1.Stage1.iteration, stage2.Stage2.iteration
    stops = {"stage 1": 14, "stage 2": 9}

    def interrupt(real, name):
        def step(self, it, *a, **k):
            if it == stops[name] and not k.get("weights") and not a:
                raise KeyboardInterrupt
            return real(self, it, *a, **k)
        return step

    factors = []
    real_factor = runner.position_lr_factor
    monkeypatch.setattr(runner, "position_lr_factor", lambda p: factors.append(p) or real_factor(p))
    # No sun trial: its steps are stage-2 iterations too, and a trial
    # interrupted restarts stage 2 from its start, not mid-way.
    cfg = dict(budget_minutes=0.75, eval_every=5, checkpoint_every=1, sun_trial_iterations=0)
    monkeypatch.setattr(stage1.Stage1, "iteration", interrupt(real1, "stage 1"))
    metrics = run_fit(scene_path, small_config(tmp_path, **cfg), log=lambda *a: None)
    assert metrics["interrupted"] is True
    then = metrics["selection"]["budget"]["stage 1"]["progress"]
    assert 0.0 < then < 1.0
    monkeypatch.setattr(stage1.Stage1, "iteration", real1)
    monkeypatch.setattr(stage2.Stage2, "iteration", interrupt(real2, "stage 2"))
    factors.clear()
    lines = []
    metrics = run_fit(scene_path, small_config(tmp_path, resume=True, **cfg), log=lines.append)
    text = "\n".join(map(str, lines))
    assert "stage 1 resumed at iteration" in text
    # The first resumed step is scheduled at (about) the progress it had
    # reached, not at 0; the schedules then run on to the stage's end.
    assert factors and factors[0] >= then - 1e-6 and factors[0] < 1.0
    assert factors == sorted(factors)
    assert metrics["interrupted"] is True           # now in stage 2
    monkeypatch.setattr(stage2.Stage2, "iteration", real2)
    made = []
    real_stop = runner.stage2_stop
    monkeypatch.setattr(runner, "stage2_stop", lambda *a: made.append(a) or real_stop(*a))
    lines.clear()
    metrics = run_fit(scene_path, small_config(tmp_path, resume=True, **cfg), log=lines.append)
    assert metrics["interrupted"] is False
    assert "stage 2 resumed at iteration" in "\n".join(map(str, lines)) and made


def test_pixel_area_hits_of_a_frame_that_sees_no_gaussian(scene_path, tmp_path):
    """A camera turned away from every Gaussian: the merged list holds one
    inactive entry (as a centre-ray freeze does) and the sky is seen whole."""
    from types import SimpleNamespace
    from mi_invrgbl.fit.init import load_state
    from mi_invrgbl.fit.observations import camera_rays
    from mi_invrgbl.fit.render import freeze_pixels

    state = load_state(scene_path, small_config(tmp_path), log=lambda *a: None)
    state.model.push(state.train_frames[0].poses, stage=1)
    sensor = mi.load_dict({"type": "perspective", "fov": 30, "to_world": mi.ScalarTransform4f().look_at(
        origin=[0, 0, 500], target=[0, 0, 1000], up=[0, 1, 0]),
        "film": {"type": "hdrfilm", "width": 6, "height": 4}})
    cam = SimpleNamespace(sensor=sensor, width=6, height=4, rays=camera_rays(sensor, 6, 4))
    fh = freeze_pixels(state.scene, cam, 2)
    assert np.all(np.array(fh.node_ids) == 0)
    np.testing.assert_allclose(np.array(fh.t_after), 1.0)
    assert fh.n_rays == 24 and not np.any(np.array(fh.surface))
