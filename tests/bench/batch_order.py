"""Stage 1's random batches traced in draw order against sorted order.

    python tests/bench/batch_order.py SCENE.xml [--batches 10] [--steps 30]

SCENE.xml is an imported scene (``mi-invrgbl import``) or a fitted one. Prints
one table, both orders measured in this process on the same batches:

* camera batch: ``camera_unlit`` on ``batch_rays`` random pixels of a
  training frame (forward only), the frames taken in turn;
* LiDAR batch: ``lidar_return``'s beams on ``lidar_batch_rays`` random
  beams of the same frames;
* stage-1 step: :meth:`Stage1.iteration` (forward, backward, Adam), the
  stage's own batches, ``--steps`` steps per order, alternating blocks of
  ten (no densification).

Times are medians over batches (steps: the mean per step), after one
warm-up batch per order, with ``dr.sync_thread()`` around each. "changed"
is the share of a batch's rays whose colour (camera) or intensity (LiDAR)
differs between the orders by more than 1e-3, and the largest difference:
the order must change nothing but rounding.
"""

import sys as _sys, pathlib as _pathlib
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parents[1]))
import variant_choice  # noqa: E402  (--variant NAME, default $MI_INVRGBL_VARIANT or llvm_ad_rgb)
variant_choice.from_argv()

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

from mi_invrgbl.fit import stage1 as stage1_module  # noqa: E402
from mi_invrgbl.fit.config import FitConfig  # noqa: E402
from mi_invrgbl.fit.init import load_state  # noqa: E402
from mi_invrgbl.fit.render import batch_order, camera_unlit, gather_rays, lidar_beams  # noqa: E402
from mi_invrgbl.fit.stage1 import Stage1  # noqa: E402


def _timed(fn):
    dr.sync_thread()
    t = time.perf_counter()
    out = fn()
    dr.sync_thread()
    return out, time.perf_counter() - t


def _camera(state, frame, index):
    rays = gather_rays(frame.camera.rays, mi.UInt32(index.astype(np.uint32)))
    rgb, alpha, depth = camera_unlit(state.scene, rays, state.config.max_hits,
                                     state.config.min_transmittance)
    dr.eval(rgb, alpha, depth)
    return np.stack([np.array(rgb[c]) for c in range(3)], 1)


def _lidar(state, frame, index):
    lid = frame.lidar
    idx = mi.UInt32(index.astype(np.uint32))
    ch = lidar_beams(state.lidar_integrator, state.scene, gather_rays(lid.rays, idx),
                     dr.gather(mi.UInt32, lid.row, idx), dr.gather(mi.Float, lid.near, idx))
    dr.eval(ch)
    return np.array(ch[0])[:, None]


def batch_rows(state, n_batches, rng):
    """(task, rays, draw s, sorted s, changed share, largest change) per batch kind."""
    cfg = state.config
    frames = [f for f in state.train_frames if f.camera is not None and f.lidar is not None]
    if not frames:
        raise SystemExit("the scene has no training frame with both a camera and a LiDAR")
    rows = []
    for task, size, pool_of, render in (
            ("camera batch", cfg.batch_rays, lambda f: f.camera.valid_index(), _camera),
            ("LiDAR batch", cfg.lidar_batch_rays, lambda f: f.lidar.valid_index(), _lidar)):
        times = {False: [], True: []}
        changed, largest = [], 0.0
        for b in range(n_batches + 1):
            f = frames[b % len(frames)]
            state.model.push(f.poses, stage=1)
            pool = pool_of(f)
            drawn = pool[rng.integers(0, len(pool), min(size, len(pool)))]
            order = np.argsort(drawn, kind="stable")
            out_d, t_d = _timed(lambda: render(state, f, drawn))
            out_s, t_s = _timed(lambda: render(state, f, batch_order(drawn)))
            if b == 0:
                continue                      # warm-up: kernels compile
            times[False].append(t_d)
            times[True].append(t_s)
            diff = np.abs(out_s - out_d[order]).max(axis=1)
            changed.append(float(np.mean(diff > 1e-3)))
            largest = max(largest, float(diff.max()))
        rows.append((task, size, float(np.median(times[False])), float(np.median(times[True])),
                     float(np.mean(changed)), largest))
    return rows


def step_row(state, n_steps):
    """Stage-1 steps in blocks of ten, draw order and sorted in turn."""
    s1 = Stage1(state)
    per = {False: [0.0, 0], True: [0.0, 0]}
    it = 0
    for sort in (False, True):                # warm-up, one step each
        stage1_module.batch_order = batch_order if sort else (lambda index: index)
        it += 1
        s1.iteration(it)
    block = 10
    for k in range(2 * max(1, n_steps // block)):
        sort = bool(k % 2)
        stage1_module.batch_order = batch_order if sort else (lambda index: index)
        for _ in range(block):
            it += 1
            _, t = _timed(lambda: s1.iteration(it))
            per[sort][0] += t
            per[sort][1] += 1
    stage1_module.batch_order = batch_order
    return ("stage-1 step", state.config.batch_rays + state.config.lidar_batch_rays,
            per[False][0] / per[False][1], per[True][0] / per[True][1], float("nan"), float("nan"))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--batches", type=int, default=10)
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--variant", default=None)
    args = ap.parse_args(argv)
    state = load_state(args.scene, FitConfig(seed=args.seed), log=lambda *a: None)
    rng = np.random.default_rng(args.seed)
    rows = batch_rows(state, args.batches, rng) + [step_row(state, args.steps)]
    print("%s: %d Gaussians, %s" % (args.scene, state.model.total, mi.variant()))
    print("| task | rays | draw order [s] | sorted [s] | speed-up | rays changed > 1e-3 | largest change |")
    print("|---|---|---|---|---|---|---|")
    for task, n, t_d, t_s, share, big in rows:
        extra = ("-", "-") if np.isnan(share) else ("%.2f %%" % (100 * share), "%.4f" % big)
        print("| %s | %d | %.3f | %.3f | %.2fx | %s | %s |" % (task, n, t_d, t_s, t_d / t_s, *extra))


if __name__ == "__main__":
    main()
