"""Initialisation: the fit's state from an imported scene, and the LiDAR
response and LiDAR albedo that stage 2 starts from."""

from __future__ import annotations

import os
import time

import numpy as np
import drjit as dr
import mitsuba as mi

from ..errors import UserError
from ..physics.sh import num_coeffs
from ..scene.frames import Frames
from ..scene.loading import load_scene
from .config import FitConfig
from .object_bounds import boxed_objects, object_boxes
from .model import GaussianModel
from .observations import load_observations
from .render import Response, dominant_hit
from .response import MIN_COS, estimate_response, prior_for
from .selection import fit_sh_orders, pad_sh
from .sky_mask import frame_sky_mask
from .state import FitState, SkyKeys
from ..physics.host_arrays import jit_array


def split_validation(train, every):
    """(training, validation) frames: every ``every``-th training frame by
    index validates, as long as two frames are left to train on.

    The validation frames are ``index % every == min(2, every // 2)``: with
    ``every`` a multiple of 5 they sit midway between the import's held-out
    frames (``index % 5 == 4``), two frames from each, so the training
    frames next to a held-out frame stay training frames."""
    if every <= 0:
        return list(train), []
    val = [f for f in train if f.index % every == min(2, every // 2)]
    if len(train) - len(val) < 2:
        return list(train), []
    return [f for f in train if f not in val], val


def load_state(scene_path, config: FitConfig, log=print) -> FitState:
    """Load the imported scene, ``frames.json`` and the observations."""
    t = time.perf_counter()
    scene_path = os.path.abspath(scene_path)
    frames = Frames.load(scene_path)
    scene = load_scene(scene_path)
    params = mi.traverse(scene)
    moving = [n for n, o in frames.objects.items() if o.moving]
    model = GaussianModel(scene, object_names=moving)
    # Objects are loaded at their frame-0 pose: keep them in their own frame.
    for name, node in model.nodes.items():
        if node.dynamic:
            pose0 = frames[0].objects.get(name)
            if pose0 is not None:
                model.set_cloud(name, model.cloud(name, stage=2), pose=pose0)
    camera_integrator = scene.integrator()
    if not hasattr(camera_integrator, "shade_gaussian_hits"):
        camera_integrator = mi.load_dict({"type": "invrgbl", "samples": config.samples})
    # The fit's choice, whatever the imported scene's integrator says.
    camera_integrator.shadowing = config.shadowing
    camera_integrator.diffuse_fresnel = bool(config.diffuse_fresnel)
    lidar_integrator = mi.load_dict({"type": "lidar_return", "max_hits": config.max_hits,
                                     "min_transmittance": config.min_transmittance})
    sky = None
    for emitter in scene.emitters():
        if hasattr(emitter, "sky_radiance"):
            eid = emitter.id() or "sky"
            if eid + ".sh" in params:
                sky = SkyKeys(emitter, eid + ".sh", eid + ".sun_irradiance", eid + ".sun_direction")
    if sky is None:
        raise UserError("%s: the scene has no 'shsun' emitter to fit the sky and sun with" % scene_path)
    observations = load_observations(scene, frames, config.fit_width, config.lidar_columns,
                                     log=log)
    train = [o for o in observations if not o.held_out]
    held_out = [o for o in observations if o.held_out]
    if not train:
        raise UserError("%s: every frame is held out; nothing to train on" % frames.path)
    train, validation = split_validation(train, config.validation_every)
    seen = [o.lidar.intensity.ravel()[o.lidar.hit.ravel() & o.lidar.valid()]
            for o in train if o.lidar is not None]
    seen = np.concatenate(seen) if seen else np.zeros(0)
    seen = seen[seen > 0]
    n_beams = frames.lidar.beams
    state = FitState(
        scene_path=scene_path, config=config, log=log, rng=np.random.default_rng(config.seed),
        frames=frames, scene=scene, params=params, model=model,
        camera_integrator=camera_integrator, lidar_integrator=lidar_integrator, sky=sky,
        observations=observations, train_frames=train, validation_frames=validation,
        held_out_frames=held_out,
        intensity_scale=float(np.percentile(seen, 95)) if seen.size else 1.0,
        response=Response(mi.Float(2.0), mi.Float(1.0), dr.ones(mi.Float, max(n_beams, 1))))
    if config.object_bounds:
        # From the import's centres, before a resume loads its checkpoint.
        state.object_boxes = object_boxes(model, boxed_objects(frames))
    if config.object_poses:
        from .object_poses import ObjectPoseFit
        fit = ObjectPoseFit(observations, train, [n for n, v in model.nodes.items() if v.dynamic])
        state.object_poses = fit if fit else None
        if fit:
            t_align = time.perf_counter()
            state.selection["object_poses_start"] = fit.align_from_images(model, log)
            fit.bake()
            state.times["object poses"] = time.perf_counter() - t_align
    attach_sky_masks(state)
    state.times["load"] = time.perf_counter() - t
    cam = train[0].camera
    log("[fit] %s: %d Gaussians in %d node(s) (%s), %d training + %d validation + %d held-out "
        "frames, %dx%d pixels per image; loaded in %.1f s"
        % (scene_path, model.total, len(model.nodes),
           ", ".join("%s%s" % (n, " (moving)" if v.dynamic else "") for n, v in model.nodes.items()),
           len(train), len(validation), len(held_out), cam.width if cam else 0,
           cam.height if cam else 0, state.times["load"]))
    return state


def attach_sky_masks(state: FitState):
    """The sky mask (:mod:`.sky_mask`) of every training and validation image;
    its share of their pixels goes into the selection report."""
    if not state.config.sky_mask or state.config.stage1_sky <= 0:
        return
    total = sky = 0
    for frame in state.train_frames + state.validation_frames:
        if frame.camera is None:
            continue
        frame.camera.sky = frame_sky_mask(state.model, frame)
        total += frame.camera.sky.size
        sky += int(frame.camera.sky.sum())
    if total:
        state.selection["sky_mask"] = {"share": sky / total, "pixels": sky}


def init_sky_from_mask(state: FitState):
    """Start the SH sky from the sky-mask pixels of the training images (a
    trimmed least-squares fit, :func:`.selection.fit_sh_orders`), so that
    stage 1 sees the sky the images show from its first step; left as
    imported when fewer than 64 pixels are marked."""
    dirs, rgb = [], []
    for f in state.train_frames:
        if f.camera is None or f.camera.sky is None or not f.camera.sky.any():
            continue
        d = np.stack([np.array(f.camera.rays.d[k]) for k in range(3)], 1)
        dirs.append(d[f.camera.sky])
        rgb.append(f.camera.image.reshape(-1, 3)[f.camera.sky])
    if sum(len(d) for d in dirs) < 64:
        return
    order_max = state.sky_emitter.order
    chosen, _, coeffs = fit_sh_orders(np.concatenate(dirs), np.concatenate(rgb),
                                      max_order=order_max, seed=state.config.seed)
    state.params[state.sky_key] = jit_array(mi.Float, pad_sh(coeffs[chosen], order_max))
    state.params.update()
    state.selection.setdefault("sky_mask", {})["sky_start_order"] = int(chosen)


def sh_mask(order, emitter_order) -> mi.Float:
    """1 for the SH coefficients up to ``order``, 0 above (the emitter's layout)."""
    mask = np.zeros((num_coeffs(emitter_order), 3), np.float32)
    mask[: num_coeffs(int(order))] = 1
    return jit_array(mi.Float, mask)


def init_materials(ctx: FitState, frozen):
    """LiDAR albedo and response from a log-linear regression over the
    training scans."""
    cfg = ctx.config
    t = time.perf_counter()
    # (RGB albedo and the sun's level: Stage2.init_shading, once visibility is traced.)
    # LiDAR: per return, the dominant Gaussian, its distance and incidence.
    offsets, off = {}, 0
    for name, node in ctx.model.nodes.items():
        offsets[ctx.model.shape_ids[name]] = off
        off += node.count
    normals = np.concatenate([ctx.model.nodes[n].numpy("normal") for n in ctx.model.nodes])
    train = _lidar_returns(ctx.train_frames, frozen, offsets, normals)
    info = {}
    if train is not None:
        I, D, C, B, S = train
        # On a road seen from a roof-mounted LiDAR cos(theta) ~ h / d, so the
        # angle and range exponents are nearly collinear there: both are
        # fitted with priors from the sensor's kind, and the free angle
        # exponent is kept only where it predicts the validation frames'
        # returns better than the prior's value (where the data identify
        # it, if there are no validation returns). On the KITTI excerpt the
        # free one predicts better (b ~ 0.1, a ~ 0.1; holding a = 1 pushed b
        # to -0.6 and raised the intensity error at new poses from 0.116 to
        # 0.152). On tests/fit_scene.py the free fit trades one exponent for
        # the other at an equal training residual (b 1.41, a 1.62, or after
        # a differently shaped stage 1 b -0.5, a 3.5, against the truth 2
        # and 1), which reproduces the training poses but not a new pose.
        kw = dict(n_surfaces=ctx.model.total, fit_gains=cfg.fit_response,
                  prior=prior_for(getattr(ctx.frames.lidar, "intensity", None)))
        res = estimate_response(I, D, C, B, S, ctx.frames.lidar.beams, fit_range=cfg.fit_response,
                                fit_angle=cfg.fit_response, **kw)
        if cfg.fit_response:
            held = estimate_response(I, D, C, B, S, ctx.frames.lidar.beams, fit_range=True,
                                     fit_angle=False, **kw)
            val = _lidar_returns(ctx.validation_frames, frozen, offsets, normals)
            errors = [_prediction_rmse(r, val) for r in (res, held)]
            if np.isfinite(errors).all():
                info["angle_exponent_choice"] = {"free": errors[0], "prior": errors[1],
                                                 "scored_on": "validation"}
                if errors[1] <= errors[0]:
                    res = held
            elif not res.extra.get("angle_exponent_identified", False):
                res = held
        info.update({"range_exponent": float(res.range_exponent), "angle_exponent": float(res.angle_exponent),
                "residual_rms": float(res.residual_rms), "returns_used": int(res.n_used)})
        if cfg.fit_response:
            ctx.response.range_exponent = mi.Float(float(res.range_exponent))
            ctx.response.angle_exponent = mi.Float(float(res.angle_exponent))
            gains = np.asarray(res.beam_gains, np.float32)
            ctx.response.beam_gains = jit_array(mi.Float, gains)
        else:
            info["fixed"] = "the paper's cos/d^2 response"
        # Per-Gaussian LiDAR albedo from the regression where a Gaussian was hit.
        rho = _surface_rho(res, S)
        if rho is not None:
            ids, values = rho
            scale = np.percentile(values, 99) if values.size else 1.0
            scale = max(scale, 1e-6)
            allrho = np.concatenate([ctx.model.nodes[n].numpy("lidar_albedo") for n in ctx.model.nodes])
            allrho[ids] = np.clip(values / scale, 0, 1)
            if cfg.fit_response:
                ctx.response.beam_gains = ctx.response.beam_gains * float(scale)
            info["albedo_scale"] = float(scale)
            start = 0
            for name, node in ctx.model.nodes.items():
                node.values["lidar_albedo"] = jit_array(mi.Float, allrho[start:start + node.count])
                start += node.count
    ctx.selection["response_init"] = info
    ctx.times["material init"] = time.perf_counter() - t
    ctx.log("[fit] LiDAR response init: %s (%.1f s)" % (
        ", ".join("%s %.3g" % (k, v) for k, v in info.items() if isinstance(v, float)),
        ctx.times["material init"]))


def _surface_rho(res, surface_ids):
    """(Gaussian ids, rho) from an estimate_response result, whatever its layout."""
    rho = getattr(res, "rho", None)
    if rho is None:
        return None
    rho = np.asarray(rho, np.float64)
    ids = np.nonzero(np.isfinite(rho))[0]
    return ids, rho[ids]


def _lidar_returns(frames, frozen, offsets, normals):
    """Returns of ``frames``' frozen scans (intensity, distance, incidence
    cosine, beam, dominant Gaussian's global id), or None if there are none."""
    I, D, C, B, S = [], [], [], [], []
    for f in frames:
        if f.lidar is None or f.index not in frozen.lidar:
            continue
        ray, nid, prim, w, tt = dominant_hit(frozen.lidar[f.index])
        hit = (f.lidar.hit.ravel() & f.lidar.valid())[ray] & (w > 0.3)
        ray, nid, prim, tt = ray[hit], nid[hit], prim[hit], tt[hit]
        d = np.stack([np.array(f.lidar.rays.d[k]) for k in range(3)], 1)[ray]
        gid = np.array([offsets[int(i)] for i in nid], np.int64) + prim if len(nid) else prim
        n = normals[gid]
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        I.append(f.lidar.intensity.ravel()[ray])
        D.append(tt + np.array(f.lidar.near)[ray])
        C.append(np.abs(np.sum(n * d, axis=1)))
        B.append(np.array(f.lidar.row)[ray])
        S.append(gid)
    if not I:
        return None
    return tuple(map(np.concatenate, (I, D, C, B, S)))


def _prediction_rmse(res, returns):
    """RMSE of ``res``'s predicted intensity on ``returns`` whose Gaussian the
    training returns saw (NaN if none)."""
    if returns is None:
        return float("nan")
    I, D, C, B, S = returns
    rho = np.asarray(res.rho, np.float64)
    ok = (S < rho.size) & np.isfinite(I) & (D > 0)
    ok[ok] = np.isfinite(rho[S[ok]])
    if not ok.any():
        return float("nan")
    pred = res.predict(rho[S[ok]], D[ok], np.maximum(C[ok], MIN_COS), B[ok])
    return float(np.sqrt(np.mean((pred - I[ok]) ** 2)))
