"""Scores the fit reports while it runs: PSNR of the images and RMSE of the
LiDAR intensities on a list of frames (held-out frames for the progress log,
validation frames for model selection), over the pixels and beams that
count (:meth:`~.observations.Masked.valid`: motion masks left out)."""

from __future__ import annotations

import numpy as np
import drjit as dr
import mitsuba as mi

from ..eval.metrics import psnr
from .render import camera_unlit


def _grid_offsets(grid):
    """Sub-pixel positions of a ``grid`` x ``grid`` stratified box filter."""
    ticks = (np.arange(grid) + 0.5) / grid
    return [(u, v) for v in ticks for u in ticks]


def score_stage1(state, frames, stride=None, grid=1):
    """PSNR (sRGB) of the unlit stage-1 colour on ``frames``, over every
    ``stride``-th pixel that counts (default ``config.score_stride``).

    Stage 1 traces every pixel it scores: on the KITTI excerpt (8 validation
    frames, scored every 19 steps, plus the held-out log) a 50-step stretch
    of an 8-minute fit took 51 s at stride 1, its steps 28 s. A fixed subset scores
    every evaluation on the same pixels, so early stopping compares like with
    like. ``grid`` > 1 averages a ``grid`` x ``grid`` set of rays over each
    pixel, as ``eval`` renders (several samples per pixel, box filter)."""
    stride = max(1, int(state.config.score_stride if stride is None else stride))
    vals = []
    with dr.suspend_grad():
        for f in frames:
            if f.camera is None:
                continue
            idx = np.nonzero(f.camera.valid())[0][::stride]
            if idx.size == 0:
                continue
            state.model.push(f.poses, stage=1)
            img = 0.0
            for u, v in _grid_offsets(grid):
                offset = None if grid == 1 else np.tile([[u, v]], (idx.size, 1))
                rgb, _, _ = camera_unlit(state.scene, f.camera.pixel_rays(idx, offset),
                                         state.config.max_hits, state.config.min_transmittance)
                img = img + np.stack([np.array(rgb[c]) for c in range(3)], axis=1) / grid ** 2
            vals.append(psnr(img, f.camera.image.reshape(-1, 3)[idx], srgb=True))
    return float(np.mean(vals)) if vals else float("nan")


def score_stage2(stage2, frames, vals=None, refresh=False, **render):
    """(PSNR of the shaded images, LiDAR intensity RMSE) on ``frames`` from the
    frozen caches. ``vals`` (default: the stage's current variables) and
    ``render`` (e.g. ``samples``, ``caches``) go to :meth:`Stage2.render_frame`.

    With ``refresh`` the lighting caches first follow the normals the stage
    has learned (:meth:`Stage2.refresh_lighting`): the score is then the
    fitted scene's as the integrator renders it. The scores that choose
    (early stopping) refresh; a score for the log alone need not pay for it."""
    ps, errs, counts = [], 0.0, 0
    if refresh and vals is None and "caches" not in render:
        stage2.refresh_lighting()
    with dr.suspend_grad():
        vals = stage2.values() if vals is None else vals
        for f in frames:
            out = stage2.render_frame(f, vals, **render)
            if "camera" in out:
                c = out["camera"]["rgb"]
                img = np.stack([np.array(c[k]) for k in range(3)], axis=1)
                ps.append(psnr(img, f.camera.image.reshape(-1, 3), mask=f.camera.valid()[:, None],
                               srgb=True))
            if "lidar" in out:
                pred = np.array(out["lidar"]["intensity"])
                hit = f.lidar.hit.ravel() & f.lidar.valid()
                errs += float(np.sum((pred[hit] - f.lidar.intensity.ravel()[hit]) ** 2))
                counts += int(hit.sum())
    return (float(np.mean(ps)) if ps else float("nan"),
            float(np.sqrt(errs / counts)) if counts else float("nan"))
