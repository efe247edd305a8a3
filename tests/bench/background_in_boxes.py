"""Background Gaussians where a moving object passes: a diagnostic of the import's split.

    python tests/bench/background_in_boxes.py IMPORT_DIR [--write NEW_DIR]

``IMPORT_DIR`` is an imported scene's folder (``frames.json``,
``background.ply``). For each moving object the script counts the
background Gaussians whose centre lies in the object's box, by the
import's own test (:func:`mi_invrgbl.io.objects.in_box`: the box grown by
0.25 m, less 0.15 m above its bottom), at any frame of its labelled span.
A moving object's returns go to the object only inside its box and only in
those frames, so such Gaussians come from the frames before or after the
span (a queued car that stopped being tracked), from parts of a vehicle the
box does not hold (a tanker's cab), or from a static thing the box swept.

``--margin`` and ``--clearance`` change the box's growth and the height
left out above its bottom. ``--write NEW_DIR`` copies the import to ``NEW_DIR`` (which must not
exist; written to a temporary folder beside it and renamed into place) with
those Gaussians taken out of ``background.ply``, so that a fit can be run
with and without them (``tests/bench/stage1_steps.py NEW_DIR/scene.xml``).
On the KITTI excerpt's import (the README's recipe) 3 396 of its 60 000
background Gaussians lie in the boxes (3 280 with ``--margin 0.3
--clearance 0.2``); taking those 3 280 out did not help stage 1 (see the
"Densification, annealing and the background in the moving
objects' boxes" in docs/measurements.md).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)


def in_swept_boxes(centres, frames, margin, clearance):
    """Per moving object: a bool per centre (world), True where it lies in
    the object's box at some frame of its labelled span."""
    from mi_invrgbl.io.objects import in_box
    out = {}
    for name, o in frames.objects.items():
        if not o.moving:
            continue
        labelled = o.extra.get("labelled_frames") or []
        if not labelled:
            continue
        h, w, length = o.size_hwl
        half = (length / 2.0, w / 2.0, h / 2.0)
        inside = np.zeros(len(centres), bool)
        for rec in frames:
            if not (labelled[0] <= rec.index <= labelled[-1]) or name not in rec.objects:
                continue
            pose = np.asarray(rec.objects[name], np.float64)
            local = (centres - pose[:3, 3]) @ pose[:3, :3]
            inside |= in_box(local, half, margin, clearance)
        out[name] = inside
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dir")
    ap.add_argument("--write", metavar="NEW_DIR", help="a copy of the import without them")
    ap.add_argument("--margin", type=float, default=None,
                    help="metres the box grows sideways and upwards (default: the import's)")
    ap.add_argument("--clearance", type=float, default=None,
                    help="metres above the box's bottom left out (default: the import's)")
    args = ap.parse_args(argv)

    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    from mi_invrgbl.errors import UserError
    from mi_invrgbl.physics.gaussian_ply import read_ply, write_ply
    from mi_invrgbl.scene.frames import Frames
    from mi_invrgbl.io.objects import BOX_MARGIN, GROUND_CLEARANCE
    margin = BOX_MARGIN if args.margin is None else args.margin
    clearance = GROUND_CLEARANCE if args.clearance is None else args.clearance

    if args.write and os.path.exists(args.write):
        raise SystemExit("%s exists: give a new folder" % args.write)
    try:
        frames = Frames.load(args.dir)
        cloud = read_ply(os.path.join(args.dir, "background.ply"))
    except (UserError, OSError) as exc:
        raise SystemExit(str(exc))
    centres = cloud.centers.astype(np.float64)
    masks = in_swept_boxes(centres, frames, margin, clearance)
    anywhere = np.zeros(len(centres), bool)
    print("%-14s %8s" % ("object", "in box"))
    for name, inside in masks.items():
        anywhere |= inside
        print("%-14s %8d" % (name, int(inside.sum())))
    print("%-14s %8d of %d background Gaussians" % ("any", int(anywhere.sum()), len(centres)))
    if args.write:
        target = os.path.abspath(args.write)
        tmp = tempfile.mkdtemp(prefix=".partial-", dir=os.path.dirname(target))
        for entry in os.listdir(args.dir):
            src = os.path.join(args.dir, entry)
            if entry == "background.ply":
                continue
            if os.path.isdir(src) and entry == "observations":
                shutil.copytree(src, os.path.join(tmp, entry))
            elif os.path.isfile(src) and entry.endswith((".xml", ".json", ".ply")):
                shutil.copy2(src, os.path.join(tmp, entry))
        write_ply(os.path.join(tmp, "background.ply"), cloud.subset(~anywhere))
        os.rename(tmp, target)
        print("wrote %s (%d background Gaussians)" % (target, int((~anywhere).sum())))


if __name__ == "__main__":
    main()
