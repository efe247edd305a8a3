"""Checkpoints: ``DIR/fit/checkpoints/latest.npz`` holds the model's
variables, Adam's state, the sky, sun and LiDAR response, the RNG, the
choices made so far and the progress log, plus a fingerprint of what the fit
started from, so that ``--resume`` refuses a checkpoint of something else."""

from __future__ import annotations

import hashlib
import json
import os

import numpy as np
import drjit as dr
import mitsuba as mi

from ..errors import UserError
from ..physics.host_arrays import jit_array
from ..outdir import atomic_write
from .config import FitConfig
from .init import sh_mask
from .render import Response
from .state import FitState
from .steps import optimizer_state


def checkpoint_path(ctx: FitState):
    return os.path.join(ctx.fit_dir, "checkpoints", "latest.npz")


def _file_digest(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def fingerprint(ctx: FitState) -> dict:
    """What a checkpoint must match to be resumed: the scene file, its frames
    (``frames.json``), the Gaussian counts the scene loaded with and the
    configuration fields that change the model. Call it right after loading."""
    return {"scene": _file_digest(ctx.scene_path), "frames": _file_digest(ctx.frames.path),
            "gaussians": {n: node.count for n, node in ctx.model.nodes.items()},
            "config": ctx.config.model_fields()}


#: Options a checkpoint may predate whose value then was another option's.
PREDATED = {"lidar_batch_rays": "batch_rays"}
#: Options a checkpoint may predate whose value then was not today's default
#: (the camera loss compared in linear light before ``rgb_space`` existed,
#: and as a squared difference before ``rgb_norm`` did).
PREDATED_VALUES = {"rgb_space": "linear", "rgb_norm": "l2"}


def check_fingerprint(path, saved, current):
    if saved is None:
        raise UserError("%s: checkpoint has no fingerprint of its scene; cannot resume from it" % path)
    differ = []
    for part, what in (("scene", "the scene file"), ("frames", "frames.json"),
                       ("gaussians", "the Gaussian counts")):
        if saved.get(part) != current[part]:
            differ.append(what)
    # An option a checkpoint predates had its default value then, or
    # (PREDATED) the value another option gave it.
    defaults = FitConfig().model_fields()
    was = saved.get("config", {})
    then = {k: was[PREDATED[k]] if k in PREDATED and PREDATED[k] in was
            else PREDATED_VALUES.get(k, defaults.get(k)) for k in current["config"]}
    options = sorted(k for k in current["config"]
                     if json.dumps(was.get(k, then[k])) != json.dumps(current["config"][k]))
    if options:
        differ.append("option(s) %s" % ", ".join(options))
    if differ:
        raise UserError("%s: checkpoint is of another fit (%s differ); remove it or fit into "
                        "another output folder" % (path, "; ".join(differ)))


def save_checkpoint(ctx: FitState, fingerprint: dict, stage, iteration, opt=None, extra=None):
    """Model variables, optimiser moments, RNG and progress, written atomically.
    ``fingerprint`` (:func:`fingerprint`) identifies what the fit started from."""
    path = checkpoint_path(ctx)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    arrays = {"model/" + k: v for k, v in ctx.model.state_dict().items()}
    if opt is not None:
        arrays.update({"opt/" + k: v for k, v in optimizer_state(opt).items()})
    arrays["sky/sh"] = np.array(dr.detach(ctx.params[ctx.sky_key]), np.float32)
    arrays["sky/sun_irradiance"] = np.array(dr.detach(ctx.params[ctx.sun_key]), np.float32).ravel()
    arrays["sky/sun_direction"] = np.array(dr.detach(ctx.params[ctx.sun_dir_key]), np.float32).ravel()
    for k in ("range_exponent", "angle_exponent", "beam_gains"):
        arrays["response/" + k] = np.array(getattr(ctx.response, k), np.float32)
    if ctx.object_poses:
        arrays.update({"poses/" + k: v for k, v in ctx.object_poses.state_dict().items()})
    meta = {"stage": stage, "iteration": iteration, "rng": ctx.rng.bit_generator.state,
            "selection": ctx.selection, "use_sun": ctx.use_sun, "times": ctx.times,
            "log": ctx.speed_log.rows, "config": ctx.config.to_json(),
            "fingerprint": fingerprint, **(extra or {})}
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    atomic_write(path, lambda tmp: np.savez(tmp, **arrays))
    return path


def load_checkpoint(ctx: FitState, fingerprint: dict):
    """Restore a checkpoint into ``ctx``; returns (meta, optimiser state).
    A checkpoint of another scene, other frames or Gaussians, or another
    model configuration is refused with one line."""
    path = checkpoint_path(ctx)
    if not os.path.isfile(path):
        raise UserError("%s: no checkpoint to resume from" % path)
    try:
        data = dict(np.load(path))
        meta = json.loads(bytes(data.pop("meta")).decode())
    except Exception as exc:  # noqa: BLE001  (a truncated or foreign file)
        raise UserError("%s: unreadable checkpoint (%s)" % (path, exc)) from None
    check_fingerprint(path, meta.get("fingerprint"), fingerprint)
    ctx.model.load_state_dict({k[6:]: v for k, v in data.items() if k.startswith("model/")})
    ctx.params[ctx.sky_key] = jit_array(mi.Float, data["sky/sh"])
    ctx.params[ctx.sun_key] = mi.Color3f(*[float(v) for v in data["sky/sun_irradiance"]])
    ctx.params[ctx.sun_dir_key] = mi.Vector3f(*[float(v) for v in data["sky/sun_direction"]])
    ctx.params.update()
    ctx.response = Response(jit_array(mi.Float, data["response/range_exponent"]),
                            jit_array(mi.Float, data["response/angle_exponent"]),
                            jit_array(mi.Float, data["response/beam_gains"]))
    if ctx.object_poses:
        # Corrections fitted before the checkpoint (stage 2 renders the frames with them).
        ctx.object_poses.load_state_dict({k[6:]: v for k, v in data.items() if k.startswith("poses/")})
        ctx.object_poses.bake()
    ctx.rng.bit_generator.state = meta["rng"]
    ctx.selection = meta.get("selection", {})
    # The SH order chosen before the checkpoint still holds: without it a
    # resumed stage 2 would free every coefficient up to the emitter's order.
    order = ctx.selection.get("sh", {}).get("order")
    if order is not None:
        ctx.sh_order, ctx.sh_mask = int(order), sh_mask(order, ctx.sky_emitter.order)
    ctx.use_sun = meta.get("use_sun", True)
    ctx.times.update(meta.get("times", {}))
    ctx.speed_log.rows = meta.get("log", [])
    opt_state = {k[4:]: v for k, v in data.items() if k.startswith("opt/")}
    return meta, opt_state
