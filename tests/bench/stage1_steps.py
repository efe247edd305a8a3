"""Stage 1 alone for a fixed number of steps: validation PSNR and where the error sits.

    python tests/bench/stage1_steps.py SCENE.xml OUT.png [--steps 200] [--lidar-batch N]
        [--camera-only] [--only-frame K] [--set FIELD=VALUE ...] [--score-every 50]
        [--position-decay] [--validation K,K,...] [--train-also K,K,...] [--overwrite]

Runs ``fit``'s own stage 1 (:class:`mi_invrgbl.fit.stage1.Stage1`, with its
densification) on an imported scene for ``--steps`` iterations, without the
budget, the lighting choice or stage 2, and prints the validation frames'
PSNR (every counted pixel) every 50 steps with the time the steps took. At
the end it prints, per second validation frame, the PSNR, the share of the
squared error on pixels no Gaussian covers (alpha < 0.5) and in each third
of the image (top, middle, bottom), and the training frames' PSNR (every 4th
pixel: a stage that scores its training frames no higher than its
validation frames underfits), and writes OUT.png: observed image,
stage-1 render and error (|error| x 2) stacked per frame; an existing
OUT.png is replaced only with ``--overwrite``.

``--camera-only`` drops the LiDAR terms; ``--only-frame K`` trains on frame
K alone and scores it (how far one view gets with all the steps);
``--set`` changes a :class:`~mi_invrgbl.fit.config.FitConfig` field;
``--position-decay`` lets the centres' learning rate (and the object poses')
decay over the steps as a budgeted fit's does (:func:`~mi_invrgbl.fit.budget.
position_lr_factor`), so that long runs settle as ``fit --budget`` would.
``--validation`` scores only these validation frames and ``--train-also``
trains on these validation frames too: with the same ``--validation`` in
both, two runs compare training on more frames on frames neither trained on. The
"KITTI: far below replaying the recording" numbers in docs/measurements.md come from this
script. Held-out frames are never read.
"""

import sys as _sys, pathlib as _pathlib
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parents[1]))
import variant_choice  # noqa: E402  (--variant NAME, default $MI_INVRGBL_VARIANT or llvm_ad_rgb)
variant_choice.from_argv()

import argparse  # noqa: E402
import os  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import drjit as dr  # noqa: E402

from mi_invrgbl.eval.metrics import linear_to_srgb  # noqa: E402
from mi_invrgbl.fit.budget import position_lr_factor  # noqa: E402
from mi_invrgbl.fit.config import FitConfig  # noqa: E402
from mi_invrgbl.fit.evaluate import score_stage1  # noqa: E402
from mi_invrgbl.fit.init import load_state  # noqa: E402
from mi_invrgbl.fit.render import camera_unlit  # noqa: E402
from mi_invrgbl.fit.stage1 import Stage1, moves_with_positions  # noqa: E402


def config_from(pairs) -> FitConfig:
    cfg = FitConfig()
    for kv in pairs:
        key, _, value = kv.partition("=")
        if not hasattr(cfg, key):
            raise SystemExit("--set %s: FitConfig has no field %r" % (kv, key))
        old = getattr(cfg, key)
        setattr(cfg, key, value in ("1", "true", "True") if isinstance(old, bool) else type(old)(value))
    return cfg


def error_split(state, frame, cfg):
    """(observed sRGB, render sRGB, per-pixel squared error, alpha) of one frame."""
    state.model.push(frame.poses, stage=1)
    with dr.suspend_grad():
        rgb, alpha, _ = camera_unlit(state.scene, frame.camera.rays, cfg.max_hits,
                                     cfg.min_transmittance)
    h, w = frame.camera.height, frame.camera.width
    img = np.stack([np.array(rgb[c]) for c in range(3)], 1)
    srgb = lambda x: np.clip(linear_to_srgb(x.reshape(h, w, 3)), 0, 1)  # noqa: E731
    obs, pred = srgb(frame.camera.image.reshape(-1, 3)), srgb(img)
    err = ((pred - obs) ** 2).mean(-1) * frame.camera.valid().reshape(h, w)
    return obs, pred, err, np.array(alpha).reshape(h, w)


def _indices(text):
    return [int(k) for k in text.split(",") if k.strip()]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("out")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--lidar-batch", type=int, default=0, help="LiDAR beams per step (default: the config's)")
    ap.add_argument("--camera-only", action="store_true")
    ap.add_argument("--only-frame", type=int, default=-1)
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE")
    ap.add_argument("--score-every", type=int, default=50, help="steps between validation scores")
    ap.add_argument("--position-decay", action="store_true",
                    help="decay the centres' learning rate over the steps as fit --budget does")
    ap.add_argument("--validation", default="", metavar="K,K,...",
                    help="score only these validation frames (default: all of them)")
    ap.add_argument("--train-also", default="", metavar="K,K,...",
                    help="validation frames to train on as well (they are then not scored)")
    ap.add_argument("--variant", default=None)
    ap.add_argument("--overwrite", action="store_true", help="replace an existing OUT.png")
    args = ap.parse_args(argv)
    if os.path.exists(args.out) and not args.overwrite:
        raise SystemExit("%s exists: pass --overwrite to replace it" % args.out)
    cfg = config_from(args.set)
    state = load_state(args.scene, cfg, log=lambda *a: None)
    state.t_start = time.perf_counter()
    if args.only_frame >= 0:
        state.train_frames = [f for f in state.train_frames if f.index == args.only_frame]
        if not state.train_frames:
            raise SystemExit("--only-frame %d is not a training frame" % args.only_frame)
        state.validation_frames = list(state.train_frames)
    for flag, text in (("--validation", args.validation), ("--train-also", args.train_also)):
        unknown = set(_indices(text)) - {f.index for f in state.validation_frames}
        if unknown:
            raise SystemExit("%s: %s not validation frames (those are %s)" % (
                flag, sorted(unknown), [f.index for f in state.validation_frames]))
    moved = set(_indices(args.train_also))
    state.train_frames += [f for f in state.validation_frames if f.index in moved]
    state.validation_frames = [f for f in state.validation_frames if f.index not in moved and (
        not args.validation or f.index in _indices(args.validation))]
    if moved and state.object_poses:
        # The moved frames' pose corrections are fitted, not interpolated.
        poses = state.object_poses
        poses.train = sorted({poses.position[f.index] for f in state.train_frames})
    if args.camera_only:
        for f in state.train_frames:
            f.lidar = None
    s1 = Stage1(state)
    if args.lidar_batch:
        s1.batch_lidar = args.lidar_batch
    score = lambda: s1.score(state.validation_frames, stride=1)  # noqa: E731
    print("step 0: validation PSNR %.2f dB" % score(), flush=True)
    spent = 0.0
    for it in range(1, args.steps + 1):
        t = time.perf_counter()
        s1.iteration(it)
        s1.after_step(it, args.steps)
        if args.position_decay:
            s1.opt.scale_learning_rates(position_lr_factor(it / args.steps), moves_with_positions)
        dr.sync_thread()
        spent += time.perf_counter() - t
        if it % args.score_every == 0 or it == args.steps:
            print("step %d: validation PSNR %.2f dB (steps took %.0f s)" % (it, score(), spent),
                  flush=True)
    s1.pull()
    print("validation PSNR at the pixel centres %.2f dB, 2x2 rays per pixel (as eval renders) "
          "%.2f dB" % (score(), score_stage1(state, state.validation_frames, stride=1, grid=2)))
    rows = []
    for f in state.validation_frames[::2]:
        obs, pred, err, alpha = error_split(state, f, cfg)
        h = err.shape[0]
        total = max(err.sum(), 1e-12)
        thirds = [err[i * h // 3:(i + 1) * h // 3].sum() / total for i in range(3)]
        print("frame %d: PSNR %.2f dB; squared error on uncovered pixels %.0f %% (%.0f %% of "
              "the pixels); top/middle/bottom third %s" % (
                  f.index, -10 * np.log10(max(err.mean(), 1e-12)),
                  100 * err[alpha < 0.5].sum() / total, 100 * (alpha < 0.5).mean(),
                  "/".join("%.0f %%" % (100 * v) for v in thirds)))
        rows.append(np.concatenate([obs, pred, np.repeat(np.clip(np.sqrt(err)[..., None] * 2, 0, 1),
                                                            3, -1)], 0))
    if rows:
        cv2.imwrite(args.out, (np.concatenate(rows, 1)[..., ::-1] * 255).astype(np.uint8))
    print("training frames (every 4th pixel): PSNR %.2f dB (against the validation frames: "
          "under- or overfitting)" % s1.score(state.train_frames, stride=4))
    print("Gaussians: %d; picture: %s" % (state.model.total, args.out))


if __name__ == "__main__":
    main()
