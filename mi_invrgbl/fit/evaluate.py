"""Scores the fit reports while it runs: PSNR of the images and RMSE of the
LiDAR intensities on a list of frames (held-out frames for the progress log,
validation frames for model selection), over the pixels and beams that
count (:meth:`~.observations.Masked.valid`: motion masks left out)."""

from __future__ import annotations

import numpy as np
import drjit as dr

from ..eval.metrics import psnr
from .render import camera_unlit


def score_stage1(state, frames):
    """PSNR (sRGB) of the unlit stage-1 colour on ``frames``."""
    vals = []
    with dr.suspend_grad():
        for f in frames:
            if f.camera is None:
                continue
            state.model.push(f.poses, stage=1)
            rgb, _, _ = camera_unlit(state.scene, f.camera.rays, state.config.max_hits,
                                     state.config.min_transmittance)
            img = np.stack([np.array(rgb[c]) for c in range(3)], axis=1)
            vals.append(psnr(img, f.camera.image.reshape(-1, 3), mask=f.camera.valid()[:, None],
                             srgb=True))
    return float(np.mean(vals)) if vals else float("nan")


def score_stage2(stage2, frames, vals=None, **render):
    """(PSNR of the shaded images, LiDAR intensity RMSE) on ``frames`` from the
    frozen caches. ``vals`` (default: the stage's current variables) and
    ``render`` (e.g. ``samples``, ``caches``) go to :meth:`Stage2.render_frame`."""
    ps, errs, counts = [], 0.0, 0
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
