"""``fit`` end to end on a small scene with known truth (tests/fit_scene.py).

Covers: outputs load and render through the standard pipeline, the fit
lowers the error it reports, the LiDAR response is recovered, checkpoints
resume, a NaN step is rolled back, and Ctrl-C leaves a checkpoint and the
outputs so far. The budget's plans and stops are in test_fit_budget.py,
stage 2's start in test_fit_start.py.
"""

import json
import os

import numpy as np
import pytest
import mitsuba as mi
import drjit as dr

from fit_scene import narrow_sun_rejection, scene_path, small_config  # noqa: F401  (scene_path: a fixture)
from mi_invrgbl.fit.runner import FitConfig, run_fit
from mi_invrgbl.fit.losses import LossWeights
from mi_invrgbl.errors import UserError


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
