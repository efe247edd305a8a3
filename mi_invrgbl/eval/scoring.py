"""Scoring a (fitted) scene on its frames: :func:`evaluate`.

For every selected frame (default: the held-out ones, ``index % 5 == 4``)
the dynamic objects are placed (:func:`mi_invrgbl.scene.posing.set_frame`),
the frame's camera is rendered with the scene's integrator and its LiDAR
with ``lidar_return``, and the renders are compared with the observations:

* camera: PSNR and SSIM in sRGB. The observed images are 8-bit sRGB PNGs,
  so the linear render is converted with the sRGB curve, clipped to [0, 1]
  and compared in [0, 1] (peak 1). Where a frame has a camera motion mask
  (``frames.json`` ``masks``), also the PSNR outside it (``psnr_static``),
  inside it (``psnr_moving``: moving things no node models) and the masked
  share of the pixels (``moving_fraction``).
* camera lookup baseline: the nearest training frame's image shown
  unchanged (:func:`mi_invrgbl.eval.baselines.nearest_training_frame`),
  its PSNR and SSIM (``baseline_psnr``, ``baseline_ssim``, ``baseline_frame``).
* LiDAR: intensity RMSE over the beams that return in the observation,
  range error (mean |dr| where both return), ray-drop accuracy (all beams),
  and the nearest-neighbour baseline's intensity RMSE on the same beams
  (:mod:`mi_invrgbl.eval.baselines`, built from *every* point of the training
  frames, no subsample).
* LiDAR on the raw held-out points (``raw_*``), scored along the rays the
  sensor fired rather than binned into the range image, which moves each
  point to its pixel centre and flatters a lookup the most
  (:func:`mi_invrgbl.eval.lidar_novel_view.score_scene`): intensity RMSE over
  the returns the scene also returns and the baseline's on the same returns,
  range error, ray-drop accuracy and the F1 of the no-return class. Pooled
  over the frames under ``lidar_raw_points`` in ``metrics.json``.
* synthetic ground truth (``frames.json`` ``ground_truth.dir``, as written by
  ``make-scene street``): albedo RMSE after a per-channel scale fit (beside
  it, scored alike, a flat albedo map and the photo's own chromaticity:
  ``albedo_rmse_flat``, ``albedo_rmse_chromaticity``), roughness
  MAE, normal angular error (degrees), LiDAR-albedo RMSE (absolute and
  scale-fitted), all over the pixels where the true surface exists and the
  render covers (alpha > 0.5; the AOVs are divided by alpha), and relighting
  PSNR / SSIM: the scene's ``shsun`` is set to the ground truth's time-B light
  (constant sky radiance -> SH order-0 coefficient ``L / Y_0``, sun direction
  and irradiance), rendered, and compared with ``gt/time_b/N.exr`` (linear,
  both converted to sRGB and clipped); and the same images relit from the
  fitted light as ``mi-invrgbl relight`` edits it (``relight_edit_psnr``: the
  sun turned to time B's direction, sky and sun scaled by the truth's
  time-B / time-A ratios; :func:`relight_pass`).

Ground-truth files and the world alignment: :mod:`.ground_truth`.

:func:`write_metrics` writes ``metrics.json`` (per frame and the mean over
frames; PSNR of identical images is reported as :data:`PSNR_CAP` dB, JSON
has no infinity); what ``fit`` wrote into that file before (selection,
response, times) is kept under ``"fit"``. :func:`format_table` prints them.
"""

from __future__ import annotations

import math
import os
import time
from pathlib import Path

import numpy as np

from ..errors import UserError
from ..io.images import read_mask
from ..scene.frames import Frames, json_safe, write_json
from ..scene.loading import load_scene
from ..scene.posing import set_frame
from . import metrics as M
from .baselines import nearest_training_frame
from .ground_truth import gt_alignment, ground_truth_metrics, load_lights, source_number, sun_metrics
from .inputs import read_channels, read_json_dict, read_png, resolve_inputs, select_frames
from .rendering import SkySwap, find_sky, integrator_like, load_lidar_integrator, render_camera, render_lidar

#: PSNR reported for identical images (MSE = 0).
PSNR_CAP = 100.0

#: Columns of the printed table: (key, header, format).
TABLE = (("psnr", "PSNR", "%6.2f"), ("ssim", "SSIM", "%6.4f"),
         ("baseline_psnr", "NN-PSNR", "%7.2f"),
         ("psnr_static", "PSNR-st", "%7.2f"), ("psnr_moving", "PSNR-mv", "%7.2f"),
         ("lidar_intensity_rmse", "I-RMSE", "%7.4f"), ("baseline_intensity_rmse", "NN-RMSE", "%7.4f"),
         ("range_error", "range", "%6.3f"), ("ray_drop_accuracy", "drop-acc", "%8.4f"),
         ("raw_intensity_rmse", "I-raw", "%7.4f"), ("raw_baseline_intensity_rmse", "NN-raw", "%7.4f"),
         ("raw_range_error", "rng-raw", "%6.3f"), ("raw_drop_accuracy", "drop-raw", "%8.4f"),
         ("raw_drop_f1", "drop-F1", "%7.4f"),
         ("albedo_rmse", "albedo", "%6.4f"), ("albedo_rmse_flat", "alb-flat", "%8.4f"),
         ("albedo_rmse_chromaticity", "alb-chr", "%7.4f"), ("roughness_mae", "rough", "%6.4f"),
         ("normal_angle_deg", "normal°", "%7.2f"), ("lidar_albedo_rmse", "L-alb", "%6.4f"),
         ("relight_psnr", "relight", "%7.2f"), ("relight_edit_psnr", "relit-ed", "%8.2f"))


def image_metrics(render_lin, observed_srgb):
    pred = np.clip(M.linear_to_srgb(render_lin), 0.0, 1.0)
    if pred.shape != observed_srgb.shape:
        raise UserError("the camera renders %dx%d but the observation is %dx%d"
                        % (pred.shape[1], pred.shape[0], observed_srgb.shape[1],
                           observed_srgb.shape[0]))
    return {"psnr": min(M.psnr(pred, observed_srgb, 1.0), PSNR_CAP),
            "ssim": M.ssim(pred, observed_srgb, 1.0)}


def masked_image_metrics(render_lin, observed_srgb, masked):
    """PSNR outside (``psnr_static``) and inside (``psnr_moving``) a frame's
    camera motion mask (``masked``: (H, W) bool, moving things no node
    models), and the masked share of the pixels."""
    pred = np.clip(M.linear_to_srgb(render_lin), 0.0, 1.0)
    out = {"moving_fraction": float(masked.mean()),
           "psnr_static": min(M.psnr(pred, observed_srgb, 1.0, mask=~masked[..., None]), PSNR_CAP)}
    if masked.any():
        out["psnr_moving"] = min(M.psnr(pred, observed_srgb, 1.0, mask=masked[..., None]), PSNR_CAP)
    return out


def lidar_metrics(pred, obs, baseline=None, sensor=None):
    shape = obs["intensity"].shape
    if pred["intensity"].shape != shape:
        raise UserError("the LiDAR renders %dx%d but the observed scan is %dx%d"
                        % (pred["intensity"].shape[1], pred["intensity"].shape[0],
                           shape[1], shape[0]))
    obs_hit = obs["hit"] > 0.5
    out = {"lidar_intensity_rmse": M.rmse(pred["intensity"], obs["intensity"], obs_hit),
           "range_error": M.range_error(pred["range"], obs["range"], pred["hit"], obs["hit"]),
           "ray_drop_accuracy": M.ray_drop_accuracy(pred["hit"], obs["hit"]),
           "lidar_returns": float(obs_hit.mean())}
    if baseline is not None and sensor is not None:
        dirs = np.asarray(sensor.ray_directions_local(), np.float64)
        if dirs.shape[:2] == shape:
            to_world = np.array(sensor.world_transform().matrix, np.float64).reshape(4, 4)
            dirs_w = dirs @ to_world[:3, :3].T
            dirs_w /= np.maximum(np.linalg.norm(dirs_w, axis=-1, keepdims=True), 1e-12)
            nn = baseline.predict_scan(obs["range"], dirs_w, to_world[:3, 3], obs_hit)
            out["baseline_intensity_rmse"] = M.rmse(nn, obs["intensity"], obs_hit)
    return out


def _mean(rows):
    keys = []
    for r in rows:
        keys += [k for k, v in r.items() if k not in keys and isinstance(v, (int, float))
                 and not isinstance(v, bool) and k not in ("index", "position", "baseline_frame")]
    out = {}
    for k in keys:
        vals = [r[k] for r in rows if isinstance(r.get(k), (int, float)) and r[k] is not None
                and math.isfinite(r[k])]
        if vals:
            out[k] = float(np.mean(vals))
    return out


def format_table(rows, mean) -> str:
    cols = [c for c in TABLE if any(c[0] in r for r in rows)]
    head = "frame " + " ".join("%8s" % c[1] for c in cols)
    lines = [head, "-" * len(head)]

    def fmt(row, label):
        cells = []
        for key, _, f in cols:
            v = row.get(key)
            cells.append("%8s" % ("-" if v is None else (f % v).strip()))
        return "%-5s " % label + " ".join(cells)

    for r in rows:
        lines.append(fmt(r, "%d" % r["index"]))
    lines.append(fmt(mean, "mean"))
    return "\n".join(lines)


def json_clean(value):
    """``value`` with NaN as null, infinite PSNR capped at :data:`PSNR_CAP`."""
    return json_safe(value, pos_inf=PSNR_CAP)


def lookup_baseline(frames, positions, log=print):
    """The lookup baseline (:class:`~mi_invrgbl.eval.lidar_novel_view.Lookup`)
    from *every* point of the training frames (neither held out nor scored);
    None without training points."""
    from .lidar_novel_view import build_lookup
    t = time.time()
    lookup = build_lookup(frames, positions)
    if lookup is None:
        log("[eval] no training points: nearest-neighbour baseline skipped")
        return None
    log("[eval] nearest-neighbour baseline: every one of %d points from %d training frame(s), "
        "%.1f s" % (len(lookup), lookup.sweeps, time.time() - t))
    return lookup


#: Raw-point scores copied into each frame's row: (row key, section, score key).
RAW_KEYS = (("raw_intensity_rmse", "model", "intensity_rmse"),
            ("raw_range_error", "model", "range_mae"),
            ("raw_drop_accuracy", "model", "drop_accuracy"),
            ("raw_drop_f1", "model", "drop_f1"),
            ("raw_coverage", "model", "coverage"),
            ("raw_baseline_intensity_rmse", "baseline", "intensity_rmse_on_model_returns"),
            ("raw_baseline_range_error", "baseline", "range_mae"),
            ("raw_baseline_drop_accuracy", "baseline", "drop_accuracy"))


def raw_point_pass(scene, frames, positions, rows, lidar_integ, lookup, log=print):
    """LiDAR scores on the raw held-out points along their own rays
    (:func:`mi_invrgbl.eval.lidar_novel_view.score_scene`), into ``rows``;
    returns the pooled scores (None where no scored frame has points)."""
    from .lidar_novel_view import score_scene
    if frames.lidar is None or not any(frames[k].points is not None
                                       and os.path.isfile(frames[k].points) for k in positions):
        log("[eval] no points files for the scored frames: raw-point LiDAR score skipped")
        return None
    t = time.time()
    res = score_scene(frames.path, positions=positions, scene=scene, integrator=lidar_integ,
                      frames=frames, lookup=lookup, baseline=False, range_image=False,
                      log=lambda *a: None)
    for row in rows:
        scores = res["per_frame"].get(row["index"])
        for key, section, name in RAW_KEYS if scores else ():
            if section in scores:
                row[key] = scores[section][name]
    log("[eval] raw-point LiDAR score: %d returns, %d non-returns, %.1f s"
        % (res["raw_points"]["returns"], res["raw_points"]["non_returns"], time.time() - t))
    pooled = res["raw_points"]
    pooled["train_points"] = res["train_points"]
    return pooled


def image_baseline(frames, k, positions, observed) -> dict:
    """The camera lookup baseline's scores at frame ``k`` (empty without a
    usable training image)."""
    j = nearest_training_frame(frames, k, positions)
    if j is None:
        return {}
    shown = read_png(frames[j].image)
    if shown.shape != observed.shape:
        return {}
    return {"baseline_frame": frames[j].index,
            "baseline_psnr": min(M.psnr(shown, observed, 1.0), PSNR_CAP),
            "baseline_ssim": M.ssim(shown, observed, 1.0)}


def score_frame(scene, frames, k, spp, cam_integ, lidar_integ, nn=None, gt_dir=None,
                R=np.eye(3), save_renders=None, log=print, positions=()) -> dict:
    """One frame's row: camera, LiDAR and ground-truth metrics (``positions``:
    every scored frame, none of which the image baseline may show)."""
    rec = frames[k]
    t = time.time()
    cam_sensor, lidar_sensor = set_frame(scene, frames, k)
    row = {"index": rec.index}
    if cam_sensor is None:
        raise UserError("%s: no camera sensor '%s' for frame %d"
                        % (frames.path, rec.camera, rec.index))
    cam = render_camera(scene, cam_sensor, spp, cam_integ)
    observed = None
    if rec.image is not None:
        observed = read_png(rec.image)
        row.update(image_metrics(cam["rgb"], observed))
        row.update(image_baseline(frames, k, positions, observed))
        if rec.masks.get("camera") is not None and Path(rec.masks["camera"]).is_file():
            row.update(masked_image_metrics(cam["rgb"], observed, read_mask(
                rec.masks["camera"], observed.shape[:2], "image %s" % Path(rec.image).name)))
    if lidar_sensor is not None and rec.lidar_scan is not None:
        obs = read_channels(rec.lidar_scan, ["intensity", "range", "hit"], "LiDAR scan")
        pred = render_lidar(scene, lidar_sensor, lidar_integ)
        row.update(lidar_metrics(pred, obs, nn, lidar_sensor))
    elif rec.lidar_scan is not None:
        log("[eval] frame %d: no LiDAR sensor '%s' in the scene" % (rec.index, rec.lidar))
    if gt_dir is not None:
        row.update(ground_truth_metrics(cam, gt_dir, source_number(rec), R, observed))
    if save_renders:
        from ..io.images import write_exr
        os.makedirs(save_renders, exist_ok=True)
        write_exr(os.path.join(save_renders, "camera_%04d.exr" % rec.index),
                  cam["rgb"], ["R", "G", "B"])
    row["time_s"] = time.time() - t
    log("[eval] frame %d scored in %.1f s" % (rec.index, row["time_s"]))
    return row


def edit_ratios(lights, source="lights.json"):
    """Per-channel time-B / time-A ratios of the truth's sky radiance and sun
    irradiance, or None where ``lights`` lacks a level (a zero time-A level
    has no ratio: that light is left off the edit). A level that is not
    three finite numbers >= 0 is refused, naming ``source``."""
    a, b = lights.get("time_a") or {}, lights.get("time_b") or {}
    out = []
    for key in ("sky_radiance", "sun_irradiance"):
        if key not in a or key not in b:
            return None
        levels = []
        for time_name, light in (("time_a", a), ("time_b", b)):
            try:
                v = np.asarray(light[key], np.float64).ravel()
            except (TypeError, ValueError):
                v = np.array([np.nan])
            if v.shape != (3,) or not np.all(np.isfinite(v)) or np.any(v < 0):
                raise UserError("%s: %s.%s must be three finite numbers >= 0, got %r"
                                % (source, time_name, key, light[key]))
            levels.append(v)
        la, lb = levels
        out.append(np.where(la > 0, lb / np.where(la > 0, la, 1.0), 0.0))
    return out


def relight_pass(scene, frames, positions, rows, sky, lights, gt_dir, R, spp, integrator,
                 log=print) -> None:
    """Relighting scores against the ground truth's time-B images, into ``rows``.

    Two lights, each set once for all frames (the integrator's lighting
    precompute, minutes at 1e5-1e6 Gaussians, is redone whenever the sun or
    the geometry changes, so interleaving lights would pay it twice per
    frame even in a static scene):

    * ``relight_psnr``: the truth's time-B light put in as it is. It scores
      the fitted light's level too: the images fix only albedo times light,
      so an albedo fitted under a light 0.8x the truth's renders 1.25x too
      bright under the truth's.
    * ``relight_edit_psnr`` (where the truth gives both times' levels): the
      fitted light edited as ``mi-invrgbl relight`` edits it, the sun turned
      to time B's direction and sky and sun scaled per channel by the
      truth's time-B / time-A ratios (:meth:`SkySwap.edit`). It scores what a
      user relighting the fitted scene gets, forgiving the per-channel scale
      the albedo RMSE forgives too.
    """
    todo = [(k, row, Path(gt_dir) / "time_b" / ("%06d.exr" % source_number(frames[k])))
            for k, row in zip(positions, rows)]
    todo = [item for item in todo if item[2].is_file()]
    light = lights["time_b"]
    if not todo:
        return
    direction = R @ np.asarray(light.get("sun_direction", [0, 0, 1]), np.float64)
    passes = [("relight", "", lambda swap: swap.put(light, R))]
    ratios = edit_ratios(lights, Path(gt_dir) / "lights.json")
    if ratios is not None:
        passes.append(("relight_edit", ", the fitted light edited",
                       lambda swap: swap.edit(ratios[0], direction, ratios[1])))
    swap = SkySwap(sky)
    try:
        for key, what, apply in passes:
            apply(swap)
            for k, row, gt_b in todo:
                t = time.time()
                cam_sensor, _ = set_frame(scene, frames, k)
                relit = render_camera(scene, cam_sensor, spp, integrator)
                truth = read_channels(gt_b, ["r", "g", "b"], "relighting ground truth")
                truth = np.stack([truth["r"], truth["g"], truth["b"]], -1)
                m = image_metrics(relit["rgb"], np.clip(M.linear_to_srgb(truth), 0.0, 1.0))
                row[key + "_psnr"], row[key + "_ssim"] = m["psnr"], m["ssim"]
                row[key + "_time_s"] = time.time() - t
                log("[eval] frame %d relit (time B%s) in %.1f s" % (frames[k].index, what,
                                                                   row[key + "_time_s"]))
    finally:
        swap.restore()


#: Camera samples per pixel ``eval`` renders with (0: each sensor's own).
#: The pixel positions are random, so a few samples add noise that is the
#: estimate's, not the scene's: the KITTI excerpt's 30-minute fit scored
#: 20.79 / 20.38 dB on held-out frames 4 / 9 at the imported scenes' 4 spp
#: and 20.99 / 20.57 at 32, for 50-64 s per frame either way (most of a
#: frame's time is the sky visibility and the LiDAR, not the pixels).
EVAL_SPP = 32


def evaluate(scene_path, frames_spec="held-out", spp=EVAL_SPP, samples=None, lidar_model=None,
             baseline=True, relight=True, save_renders=None, log=print):
    """Score a scene; returns the metrics dictionary (see the module docstring)."""
    scene_xml, scene_lidar = resolve_inputs(scene_path)
    frames = Frames.load(scene_xml)
    positions = select_frames(frames, frames_spec)
    t0 = time.time()
    scene = load_scene(str(scene_xml))
    lidar_integ = load_lidar_integrator(scene_lidar, lidar_model)
    cam_integ = integrator_like(scene, samples)
    log("[eval] %s: %d frame(s) to score, loaded in %.1f s%s"
        % (scene_xml, len(positions), time.time() - t0,
           "" if scene_lidar is None else "; LiDAR response from %s" % scene_lidar.name))
    lookup = lookup_baseline(frames, positions, log) if baseline else None
    nn = lookup.nn if lookup is not None else None

    gt_dir = frames.ground_truth if frames.ground_truth is not None \
        and Path(frames.ground_truth).is_dir() else None
    if frames.ground_truth is not None and gt_dir is None:
        log("[eval] ground truth %s not found: material metrics skipped" % frames.ground_truth)
    R = gt_alignment(frames, positions, gt_dir) if gt_dir else np.eye(3)
    lights = load_lights(gt_dir) if gt_dir and relight else None
    sky = find_sky(scene) if lights and "time_b" in lights else None
    if lights and "time_b" in lights and sky is None:
        log("[eval] the scene has no shsun emitter: relighting score skipped")

    rows = [score_frame(scene, frames, k, spp, cam_integ, lidar_integ, nn, gt_dir, R,
                        save_renders, log, positions) for k in positions]
    raw = raw_point_pass(scene, frames, positions, rows, lidar_integ, lookup, log)
    if sky is not None:
        # A moved sun needs traced sun visibility, not the fitted per-Gaussian field.
        relight_integ = integrator_like(scene, samples, "trace")
        scored_with = cam_integ if cam_integ is not None else scene.integrator()
        if hasattr(relight_integ, "cache") and hasattr(scored_with, "cache"):
            # The same sky (M, bounces): start from the scoring pass's, as
            # its last frame left it, rather than tracing it afresh.
            relight_integ.cache = scored_with.cache.sky_copy()
        relight_pass(scene, frames, positions, rows, sky, lights, gt_dir, R, spp,
                     relight_integ, log)

    lighting = sun_metrics(sky, lights, R) if sky is not None else None
    if lighting:
        log("[eval] sun: %s" % ("not used" if not lighting["sun_used"] else
                                 "%.1f deg from the true time-A direction"
                                 % lighting["sun_direction_error_deg"]))
    return {"format": "mi-invrgbl-metrics/1", "scene": str(Path(scene_xml).absolute()),
            "frames_json": str(frames.path), "selection": frames_spec,
            "lidar_response": str(scene_lidar) if scene_lidar else "default",
            "camera_spp": int(spp),
            "ground_truth": str(gt_dir) if gt_dir else None,
            "notes": {"psnr": "sRGB in [0, 1], peak 1; identical images = %g dB" % PSNR_CAP,
                      "baseline_psnr": "the nearest training frame's image, unchanged",
                      "albedo_rmse": "per-channel least-squares scale fit, then RMSE",
                      "albedo_rmse_flat": "a flat albedo map scored alike (the truth's spread)",
                      "albedo_rmse_chromaticity": "the scored photo's own chromaticity (linear "
                                                  "colour over its channel mean) scored alike",
                      "lidar_intensity_rmse": "range image: over beams that return in the "
                                              "observation",
                      "raw_intensity_rmse": "raw held-out points along their own rays, over "
                                            "returns the scene also returns; the baseline "
                                            "(every training point) on the same returns",
                      "raw_drop_f1": "F1 of the no-return class over all rays",
                      "relight_psnr": "the truth's time-B sky and sun put in as they are",
                      "relight_edit_psnr": "the fitted light with the sun turned to time B's "
                                           "direction, sky and sun scaled per channel by the "
                                           "truth's time-B / time-A ratios"},
            "frames": rows, "mean": _mean(rows), "lighting": lighting,
            "lidar_raw_points": raw}


def write_metrics(result, out) -> str:
    """Write ``result`` to ``out`` (standard JSON, atomically), keeping what
    ``fit`` wrote there before under ``"fit"``; returns the path."""
    out = str(out)
    # DIR/fit/metrics.json first holds what ``fit`` reported (selection,
    # response, times); keep it under "fit" instead of overwriting it.
    previous = read_json_dict(out)
    if previous is not None:
        if previous.get("format") != result["format"]:
            result["fit"] = previous
        elif "fit" in previous:
            result["fit"] = previous["fit"]
    write_json(out, json_clean(result))
    return out
