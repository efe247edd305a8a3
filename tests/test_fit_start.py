"""Stage 2's start on the small scene of tests/fit_scene.py: the sun it
starts under, the albedo and light it starts from, and the pixel-area hit
lists it fits to."""

import numpy as np
import pytest
import mitsuba as mi
import drjit as dr

from fit_scene import scene_path, small_config  # noqa: F401  (scene_path: a fixture)
from mi_invrgbl.fit.runner import run_fit


def test_stage2_start_chooses_among_sun_directions(scene_path, tmp_path, monkeypatch):
    """Where the sun test keeps other directions, stage 2's start is made
    under each and scored on the validation frames: offered a direction far
    from the true one first, the true one's start scores higher, and the
    kept start is :func:`choose_start`'s pick (the true one's wherever the
    wrong one falls beyond the margin)."""
    from mi_invrgbl.fit import selection
    from mi_invrgbl.fit.stage2 import GLOSSY_START_ROUGHNESS, START_ROUGHNESS
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
    # validation score decides (one roughness for all, or one per Gaussian
    # where that scores at least as well), and its roughness is what stage 2
    # starts from.
    rough = metrics["selection"]["shading_init"]["start_roughness"]
    scores = [c["psnr"] for c in rough["candidates"]]
    assert rough["scored_on"] == "validation"
    assert len(scores) == 1 + len(START_ROUGHNESS) + len(GLOSSY_START_ROUGHNESS)
    assert all(np.isfinite(scores))
    # A glossy roughness competes only Gaussian by Gaussian, never for all.
    for_all = [i for i, c in enumerate(rough["candidates"])
               if c["roughness"] not in GLOSSY_START_ROUGHNESS]
    best = max(for_all, key=lambda i: scores[i])
    mix = rough.get("per_gaussian")
    # The best start with one roughness for all is named whichever is kept.
    assert rough["candidates"][best]["roughness"] == rough["for_all"]
    assert rough["kind"] in ("as_imported", "for_all", "per_gaussian")
    if rough["kind"] == "per_gaussian":
        assert mix["kept"] and mix["psnr"] >= scores[best]
        assert np.isclose(sum(mix["shares"].values()), 1.0, atol=1e-3)
    else:
        assert rough["kind"] == ("as_imported" if rough["for_all"] is None else "for_all")
        assert mix is None or (not mix["kept"] and mix["psnr"] < scores[best])
    # (the first is the kept candidate's start above, at the imported roughness)
    assert np.isclose(scores[0], cands[start["chosen"]]["psnr"])
    # Stage 2 went on from the chosen roughness (4 steps at rate 1e-2 move it
    # little): every Gaussian's is near one of the starts'.
    ckpt = np.load(tmp_path / "checkpoints" / "latest.npz")
    rough_now = np.concatenate([v for k, v in ckpt.items()
                                if k.startswith("model/") and k.endswith(".roughness")])
    if rough["kind"] == "per_gaussian":
        starts = np.array([0.5 if c["roughness"] is None else c["roughness"]
                           for c in rough["candidates"]])
        assert np.all(np.min(np.abs(rough_now[:, None] - starts[None, :]), axis=1) < 0.06)
    else:
        had = 0.5 if rough["for_all"] is None else rough["for_all"]
        assert abs(float(np.median(rough_now)) - had) < 0.06


def test_per_gaussian_start_roughness_rule():
    """Each Gaussian leaves the validation's best start for the start that
    rendered its pixels best only by the margin and on enough pixels; where
    none does, or the best start's errors were not measured, no mix is made."""
    from types import SimpleNamespace
    from mi_invrgbl.fit.stage2 import PER_GAUSSIAN_MARGIN, PER_GAUSSIAN_MIN_PIXELS, Stage2
    nodes = {"a": SimpleNamespace(count=3), "b": SimpleNamespace(count=2)}
    fake = SimpleNamespace(ctx=SimpleNamespace(model=SimpleNamespace(nodes=nodes)))
    trials = [(20.0, None, {}), (21.0, 0.75, {}), (19.0, 0.1, {})]
    imported = [np.array([0.5, 0.6, 0.7]), np.array([0.8, 0.9])]

    def per_node(i):
        r = trials[i][1]
        return imported if r is None else [np.full(3, r), np.full(2, r)]
    many = PER_GAUSSIAN_MIN_PIXELS * 2
    best_err = np.array([1.0, 1.0, 1.0, 1.0, 1.0])
    wsum = np.array([many, many, many, PER_GAUSSIAN_MIN_PIXELS / 2, many])
    glossy = np.array([PER_GAUSSIAN_MARGIN * 0.9, PER_GAUSSIAN_MARGIN * 1.1, 2.0, 0.1, 3.0])
    imp = np.array([2.0, 2.0, 2.0, 2.0, 0.5])
    errors = [(imp, wsum), (best_err, wsum), (glossy, wsum)]
    rough, shares = Stage2._per_gaussian_roughness(fake, trials, errors, 1, per_node)
    # Gaussian 0 beats the margin (0.1); 1 misses it and 3 has too few
    # pixels (0.75); 4 is best as imported (its own 0.9).
    assert np.allclose(np.concatenate(rough), [0.1, 0.75, 0.75, 0.75, 0.9])
    assert [len(x) for x in rough] == [3, 2]
    assert shares == {"0.75": 0.6, "0.1": 0.2, "as imported": 0.2}
    # An unmeasured start takes no part; nothing changes -> None.
    assert Stage2._per_gaussian_roughness(fake, trials, [None, (best_err, wsum), None], 1,
                                          per_node) is None
    assert Stage2._per_gaussian_roughness(fake, trials, [(imp, wsum), None, (glossy, wsum)], 1,
                                          per_node) is None
    # Non-finite errors never win.
    bad = np.full(5, np.nan)
    assert Stage2._per_gaussian_roughness(fake, trials, [None, (best_err, wsum), (bad, wsum)], 1,
                                          per_node) is None


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
    assert si["start_roughness"]["kind"] == "as_imported" and si["start_roughness"]["for_all"] is None
    assert len(si["start_roughness"]["candidates"]) == 1
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


def test_roughness_starts_keep_the_sun_level_the_kept_start_took(scene_path, tmp_path,
                                                                 monkeypatch):
    """The starts made again under each start roughness keep the sun level
    (facings or selection) of the start they remake, even where the rules
    would decide otherwise under another roughness: here the rules say
    "facings" for the first start and "selection" for every later one, and
    the start stage 2 goes on from still has the facings' irradiance."""
    from mi_invrgbl.fit import shading_init
    from mi_invrgbl.fit.stage2 import Stage2
    original = shading_init.reconcile_sun_irradiance
    made = []            # keep, per start made

    def flipping(estimate, level, keep=None):
        if keep is None and estimate is not None:
            keep = "selection" if made else "facings"
        return original(estimate, level, keep)
    start_under = Stage2.start_under

    def recording(self, sky, direction, keep=None):
        report = start_under(self, sky, direction, keep)
        made.append(keep)
        return report
    monkeypatch.setattr(shading_init, "reconcile_sun_irradiance", flipping)
    monkeypatch.setattr(Stage2, "start_under", recording)
    metrics = run_fit(scene_path, small_config(tmp_path, sun="on", render_samples="8",
                                               stage1_iterations=30, stage2_iterations=4),
                      log=lambda *a: None)
    si = metrics["selection"]["shading_init"]
    assert "start_candidates" not in si           # one sun, the facings not overruled
    assert len(made) >= 3 and made[0] is None     # the first start, then the roughness ones
    assert all(k == "facings" for k in made[1:])
    assert si["sun_irradiance_from"] == "facings"


def test_a_sun_level_to_keep_overrides_the_rules():
    """``keep`` takes the facings' estimate or the selection's level
    whatever the two bounds say; an unknown one is refused."""
    from mi_invrgbl.physics.colour import LUMINANCE
    from mi_invrgbl.fit.shading_init import (MAX_EXCESS, facings_overruled, kept_sun_level,
                                             reconcile_sun_irradiance)
    level = 2.0
    agree = np.array([2.2, 2.5, 2.6])
    too_bright = agree * (MAX_EXCESS + 1)
    E, source = reconcile_sun_irradiance(too_bright, level, "facings")
    assert source == "facings" and np.allclose(E, too_bright)
    E, source = reconcile_sun_irradiance(agree, level, "selection")
    assert facings_overruled(source) and np.isclose(E @ LUMINANCE, level)
    # No facing estimate: the selection's level, whatever is kept.
    E, source = reconcile_sun_irradiance(None, level, "facings")
    assert np.allclose(E, level) and kept_sun_level(source) is None
    assert kept_sun_level("facings") == "facings"
    assert kept_sun_level(reconcile_sun_irradiance(too_bright, level)[1]) == "selection"
    with pytest.raises(ValueError, match="keep"):
        reconcile_sun_irradiance(agree, level, "trust")


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
    closer than with an albedo that takes the whole colour as diffuse light.
    The specular part includes what the lobe reflects of the Gaussians
    blocking its sky samples (as stage 1 coloured them), as the render's
    lobe reflects their light: measured, RMS 0.0065 against 0.0070 with the
    lobe blind to them (specular share 3.5 % against 2.8 %)."""
    from mi_invrgbl.fit.stage2 import Stage2

    si, bias, rmse = start_against_stage1(scene_path, tmp_path / "with")

    def no_specular(self, names, frames=8, transmission=False, blockers=None):
        count = sum(self.ctx.model.nodes[n].count for n in names)
        return np.zeros((count, 3)), np.ones((count, 1))

    original = Stage2.seen_by_cameras

    def blind_to_blockers(self, names, frames=8, transmission=False, blockers=None):
        return original(self, names, frames, transmission)

    monkeypatch.setattr(Stage2, "seen_by_cameras", blind_to_blockers)
    si_b, bias_b, rmse_b = start_against_stage1(scene_path, tmp_path / "blind")
    monkeypatch.setattr(Stage2, "seen_by_cameras", no_specular)
    _, bias0, rmse0 = start_against_stage1(scene_path, tmp_path / "without")
    print(si["specular_share"], bias, rmse, si_b["specular_share"], bias_b, rmse_b, bias0, rmse0)
    assert 0.0 < si["specular_share"] < 1.0
    assert si["specular_share"] > si_b["specular_share"]
    assert rmse < rmse_b
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

    def way_out_as_1(self, names, frames=8, transmission=False, blockers=None):
        spec, t_out = original(self, names, frames, transmission, blockers)
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


def test_gaussian_errors_follow_the_pixels(scene_path, tmp_path):
    """Per-Gaussian pixel errors (:meth:`Stage2.gaussian_errors`) against
    pictures made to order: with the start's own renders as the photos every
    error is 0; with one pixel changed, exactly the Gaussians blended into it
    get an error, and their weights are the frozen hits' own."""
    from mi_invrgbl.fit import runner
    from mi_invrgbl.fit.init import load_state
    from mi_invrgbl.fit.render import camera_shaded

    state = load_state(scene_path, small_config(tmp_path / "fit", sun="on", pixel_grid=1),
                       log=lambda *a: None)
    runner.apply_lighting(state, runner.choose_lighting(state))
    stage2, frozen = runner.freeze(state, initialise=True)
    err, wsum = stage2.gaussian_errors(frames=2)
    total = sum(node.count for node in state.model.nodes.values())
    assert err.shape == wsum.shape == (total,)
    assert np.all(np.isfinite(err)) and np.all(err >= 0) and np.all(wsum >= 0)
    assert np.all(err[wsum == 0] == 0) and np.any(err > 0)
    # The two frames it samples: the first and the last training frame.
    train = [f for f in state.train_frames if f.index in frozen.camera]
    sample = [train[0], train[-1]]
    vals = stage2.model_values()
    with dr.suspend_grad():
        for f in sample:
            fh = frozen.camera[f.index]
            nodes = frozen.nodes(f, vals)
            lighting = stage2.lighting(nodes, frozen.cache(f), frame=f)
            out = camera_shaded(state.camera_integrator, state.scene, lighting, nodes,
                                f.camera.rays, fh)
            rgb = np.stack([np.array(out["rgb"][k]) for k in range(3)], axis=1)
            f.camera.image = np.clip(rgb, 0.0, 1.0).reshape(f.camera.image.shape).astype(
                f.camera.image.dtype)
    err0, wsum0 = stage2.gaussian_errors(frames=2)
    assert np.allclose(wsum0, wsum) and np.max(err0) < 1e-8
    # One observed pixel of the first frame changed: only its Gaussians see it.
    f = sample[0]
    fh = frozen.camera[f.index]
    ray, weight = np.array(fh.ray), np.array(fh.weight)
    valid = f.camera.valid()
    pixel = int(ray[np.argmax(np.where(valid[ray], weight, 0.0))])
    image = f.camera.image.reshape(-1, 3).copy()
    image[pixel] = 1.0 - image[pixel]
    f.camera.image = image.reshape(f.camera.image.shape)
    err1, _ = stage2.gaussian_errors(frames=2)
    lighting = stage2.lighting(frozen.nodes(f, vals), frozen.cache(f), frame=f)
    gi = np.array(lighting.table.global_index(fh.node_ids, fh.prims))
    on_pixel = np.zeros(total, bool)
    on_pixel[gi[(ray == pixel) & (weight > 0)]] = True
    assert np.array_equal(err1 > 1e-8, on_pixel)
