"""Do a moving object's poses agree with the images? A diagnostic.

    python tests/bench/object_pose_check.py DIR OBJECT [--step 2] [--search 0.5] [--all-frames]

``DIR`` is an imported scene's folder or a fit folder (its ``frames.json``
and ``OBJECT.ply``, e.g. ``object_1000``). For each pair of frames ``step``
apart (training and validation frames; ``--all-frames`` adds the held-out
ones), the object's Gaussian centres are projected into both images at the
listed poses and the second frame's pose is shifted along the object's
heading (its x axis) over +-``search`` metres: where the colours sampled in
the two images agree best is printed with the mean colour difference there
and at no shift. Poses that match the images put the best shift near zero;
a registration that slid along the object does not.

The same comparison, within one fit's training frames, starts the fit's
pose corrections (``mi_invrgbl/fit/object_poses.py``).
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dir")
    ap.add_argument("object")
    ap.add_argument("--step", type=int, default=2)
    ap.add_argument("--search", type=float, default=0.5)
    ap.add_argument("--all-frames", action="store_true")
    args = ap.parse_args(argv)

    import cv2
    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    from mi_invrgbl.errors import UserError
    from mi_invrgbl.physics.gaussian_ply import read_ply
    from mi_invrgbl.scene.frames import Frames

    try:
        frames = Frames.load(args.dir)
        ply = os.path.join(args.dir, args.object + ".ply")
        if not os.path.isfile(ply):
            ply = os.path.join(os.path.dirname(str(frames.path)), args.object + ".ply")
        points = read_ply(ply).centers.astype(np.float64)
    except (UserError, OSError) as exc:
        raise SystemExit(str(exc))
    cam = frames.camera
    K = cam.K
    images = {}

    def sample(rec, pose, shift):
        if rec.index not in images:
            images[rec.index] = cv2.imread(str(rec.image), cv2.IMREAD_COLOR)[..., ::-1].astype(np.float32) / 255
        img = images[rec.index]
        q = points + [shift, 0.0, 0.0]
        world = q @ pose[:3, :3].T + pose[:3, 3]
        w2c = np.linalg.inv(rec.camera_to_world)
        p = world @ w2c[:3, :3].T + w2c[:3, 3]
        z = np.maximum(p[:, 2], 1e-6)
        uv = (p / z[:, None]) @ K.T
        h, w = img.shape[:2]
        ok = (p[:, 2] > 0.5) & (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
        c = cv2.remap(img, uv[:, 0].astype(np.float32)[None], uv[:, 1].astype(np.float32)[None],
                      cv2.INTER_LINEAR)[0]
        return c, ok

    use = [r for r in frames if (args.all_frames or not r.held_out) and args.object in r.objects
           and r.image is not None]
    by_index = {r.index: r for r in use}
    shifts = np.arange(-args.search, args.search + 1e-9, 0.02)
    best_all = []
    print("%-10s %10s %14s %14s %8s" % ("frames", "best [m]", "diff at 0", "diff at best", "points"))
    for r in use:
        other = by_index.get(r.index + args.step)
        if other is None:
            continue
        ca, oa = sample(r, r.objects[args.object], 0.0)
        diffs, counts = [], []
        for s in shifts:
            cb, ob = sample(other, other.objects[args.object], s)
            m = oa & ob
            diffs.append(np.abs(ca[m] - cb[m]).mean() if m.sum() >= 100 else np.nan)
            counts.append(int(m.sum()))
        diffs = np.array(diffs)
        if np.all(np.isnan(diffs)):
            continue
        k = int(np.nanargmin(diffs))
        zero = int(np.argmin(np.abs(shifts)))
        best_all.append(shifts[k])
        print("%-10s %+10.2f %14.4f %14.4f %8d" % ("%d->%d" % (r.index, other.index), shifts[k],
                                                   diffs[zero], diffs[k], counts[k]))
    if best_all:
        print("median |best shift| %.2f m over %d pairs" % (np.median(np.abs(best_all)), len(best_all)))
    else:
        print("no pair of frames sees %s in both images" % args.object)


if __name__ == "__main__":
    main()
