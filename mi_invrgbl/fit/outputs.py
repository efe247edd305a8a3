"""What ``fit`` leaves in ``DIR/fit/``: scenes, PLYs, maps, metrics, log, plot.

``scene.xml`` is the imported scene with the fitted sky, sun and sample
count, and the fitted Gaussians (same file names, now next to it);
``scene_lidar.xml`` is the same scene with the ``lidar_return`` integrator
carrying the fitted sensor response and LiDAR model, so that
``mi.render(scene, sensor=lidar_sensor)`` simulates the recorded sensor.
"""

from __future__ import annotations

import time
import os

import numpy as np
import drjit as dr

from ..outdir import atomic_write_text
from ..io.images import write_exr
from ..physics.gaussian_ply import write_ply
from ..scene import xml
from ..scene.frames import json_safe, write_json
from ..scene.xml import SceneDoc
from .progress import peak_rss_mb, plot_error_vs_time


def fitted_xml(ctx, lidar=False):
    """The fitted scene's XML text (camera or LiDAR integrator)."""
    doc = SceneDoc.load(ctx.scene_path, resolve_paths=False)
    sky = np.array(dr.detach(ctx.params[ctx.sky_key]), np.float64).reshape(-1, 3)
    order = ctx.sh_order if ctx.sh_order is not None else ctx.sky_emitter.order
    sky = sky[: (order + 1) ** 2]
    for em in doc.root.iter("emitter"):
        if em.get("type") == "shsun":
            d = np.array(dr.detach(ctx.params[ctx.sun_dir_key]), np.float64).ravel()
            e = np.array(dr.detach(ctx.params[ctx.sun_key]), np.float64).ravel() if ctx.use_sun \
                else np.zeros(3)
            for child in xml.shsun_emitter(None, sky, order, d, e):
                xml.set_child(em, child)
    if ctx.object_poses:
        # Objects load at frame 0's pose (``scene.posing.set_frame`` moves
        # them on from there): the corrected one, as in the fit's frames.json.
        first = ctx.object_poses.corrected_frames(ctx.frames).frames[0].objects
        for shape in doc.root.iter("shape"):
            if shape.get("type") == "gaussians" and shape.get("id") in first:
                xml.set_child(shape, xml.transform(first[shape.get("id")]))
    # The fitted scene blends as many Gaussians per ray as the fit did: the
    # ones behind the fit's max_hits (or past its transmittance cut) never
    # got a gradient. Drawn with the plugins' larger defaults (64, 1e-3),
    # the KITTI excerpt's 30-minute fit scored 19.63 dB on the held-out
    # frames, with the fit's own (24, 1e-2) 19.80 dB (`eval`).
    traversal = dict(max_hits=int(ctx.config.max_hits),
                     min_transmittance=float(ctx.config.min_transmittance))
    if lidar:
        r = ctx.response
        lobe = ctx.selection.get("lidar_lobe", {}).get("model", "pbr")
        integ = xml.integrator("lidar_return", model=lobe,
                               range_exponent=float(r.range_exponent[0]),
                               angle_exponent=float(r.angle_exponent[0]),
                               beam_gains=xml.numbers_text(np.array(r.beam_gains)),
                               **traversal)
    else:
        samples = ctx.selection.get("samples", {}).get("samples", ctx.config.samples)
        integ = xml.integrator("invrgbl", samples=int(samples), bounces=int(ctx.config.bounces),
                               shadowing=str(ctx.config.shadowing),
                               **({"diffuse_fresnel": True} if ctx.config.diffuse_fresnel else {}),
                               **traversal)
        if ctx.sun_visibility_learned:
            # The fitted v_sun holds for the fitted sun; relight/night switch to trace.
            xml.set_child_param(integ, "string", "sun_visibility", "attribute")
            if ctx.moving_shadows:
                # The field holds the static scene's shadows; the moving
                # objects' are traced per render where the frame has them.
                xml.set_child_param(integ, "string", "moving", " ".join(
                    name for name, node in ctx.model.nodes.items() if node.dynamic))
    doc.set_integrator(integ)
    return doc.to_string()


def write_maps(ctx, stage2, out_dir):
    """Per training frame: albedo, roughness, normal, LiDAR albedo (camera view)
    and LiDAR intensity (range image) EXRs."""
    written = 0
    with dr.suspend_grad():
        vals = stage2.values()
        for f in ctx.train_frames:
            out = stage2.render_frame(f, vals)
            name = "%04d" % f.index
            if "camera" in out:
                c = out["camera"]
                H, W = f.camera.height, f.camera.width
                arr = lambda v, k: np.stack([np.array(v[i]) for i in range(k)], 1).reshape(H, W, k)  # noqa: E731
                write_exr(os.path.join(out_dir, name + "_albedo.exr"), arr(c["albedo"], 3), ["R", "G", "B"])
                write_exr(os.path.join(out_dir, name + "_normal.exr"), arr(c["normal"], 3), ["X", "Y", "Z"])
                write_exr(os.path.join(out_dir, name + "_roughness.exr"),
                          np.array(c["roughness"]).reshape(H, W, 1), ["Y"])
                write_exr(os.path.join(out_dir, name + "_lidar_albedo.exr"),
                          np.array(c["lidar_albedo"]).reshape(H, W, 1), ["Y"])
                write_exr(os.path.join(out_dir, name + "_rgb.exr"), arr(c["rgb"], 3), ["R", "G", "B"])
                written += 1
            if "lidar" in out:
                B, Wl = f.lidar.intensity.shape
                write_exr(os.path.join(out_dir, name + "_lidar_intensity.exr"),
                          np.stack([np.array(out["lidar"]["intensity"]).reshape(B, Wl),
                                    f.lidar.intensity], -1), ["fitted", "observed"])
    return written


def write_outputs(ctx, stage2, interrupted=False):
    fit_dir = ctx.fit_dir
    os.makedirs(fit_dir, exist_ok=True)
    stage = 2 if stage2 is not None else 1
    plys = {}
    for name in ctx.model.nodes:
        path = os.path.join(fit_dir, "%s.ply" % name)
        write_ply(path, ctx.model.cloud(name, stage=stage))
        plys[name] = path
    atomic_write_text(os.path.join(fit_dir, "scene.xml"), fitted_xml(ctx))
    atomic_write_text(os.path.join(fit_dir, "scene_lidar.xml"), fitted_xml(ctx, lidar=True))
    frames = ctx.frames
    if ctx.object_poses:
        # The moving objects where stage 1 put them, for eval and the apps
        # (frames.json in the fit folder is found before the import's).
        frames = ctx.object_poses.corrected_frames(ctx.frames)
        frames.save(os.path.join(fit_dir, "frames.json"))
        ctx.selection["object_poses"] = ctx.object_poses.summary()
    if stage2 is not None and any(f.lidar is not None for f in ctx.train_frames):
        from .response import fit_scene_ray_drop
        ctx.selection["ray_drop"] = fit_scene_ray_drop(
            os.path.join(fit_dir, "scene.xml"), os.path.join(fit_dir, "scene_lidar.xml"),
            frames=frames, log=ctx.log)
    maps = 0
    if stage2 is not None:
        maps = write_maps(ctx, stage2, os.path.join(fit_dir, "maps"))
    rows = ctx.speed_log.rows
    final = rows[-1] if rows else {}
    metrics = {
        "scene": ctx.scene_path,
        "interrupted": interrupted,
        "gaussians": {n: node.count for n, node in ctx.model.nodes.items()},
        "frames": {"train": [f.index for f in ctx.train_frames],
                   "validation": [f.index for f in ctx.validation_frames],
                   "held_out": [f.index for f in ctx.held_out_frames]},
        "heldout_psnr": float(final["heldout_psnr"]) if final.get("heldout_psnr") not in (None, "") else None,
        "heldout_intensity_rmse": float(final["heldout_intensity_rmse"])
        if final.get("heldout_intensity_rmse") not in (None, "") else None,
        "selection": ctx.selection,
        "response": {"range_exponent": float(ctx.response.range_exponent[0]),
                     "angle_exponent": float(ctx.response.angle_exponent[0]),
                     "beam_gains": np.array(ctx.response.beam_gains).tolist()},
        "times_s": ctx.times,
        "iterations": ctx.iterations,
        "wall_s": time.perf_counter() - ctx.t_start + ctx.wall_offset,
        "peak_rss_mb": peak_rss_mb(),
        "rollbacks": ctx.lr_state.get("rollbacks", 0),
        "config": ctx.config.to_json(),
        "maps_written": maps,
    }
    # A score that could not be computed (NaN) is written as null: strict JSON.
    write_json(os.path.join(fit_dir, "metrics.json"), json_safe(metrics))
    plot_error_vs_time(rows, os.path.join(fit_dir, "error_vs_time.png"))
    ctx.log("[fit] results in %s: scene.xml, scene_lidar.xml, %s, maps/ (%d frames), metrics.json, "
            "log.csv, error_vs_time.png" % (fit_dir, ", ".join(os.path.basename(p) for p in plys.values()),
                                            maps))
    return metrics
