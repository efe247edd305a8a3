"""The best held-out PSNR a direct-light model can reach on the synthetic street.

    python tests/bench/direct_light_bound.py out/street_data [--spp 256] [--frames 4,9,14,19]

The street's images are rendered by Mitsuba's ``path`` integrator with
``max_depth`` 4 (light bounces between facades, road and cars); the fit's
stage 2 shades with direct sun and sky light only (:mod:`mi_invrgbl.plugins.invrgbl`),
and stage 1's free colour has no such limit. This bench renders the
ground-truth scene (true geometry, materials, sun and sky) at the given
frames with ``--spp`` samples, once with the dataset's path length and once
with ``max_depth`` 2 (direct light only), and scores both the way ``eval``
scores a fit: sRGB, clipped, peak 1, against the dataset's 8-bit image.

Columns: ``converged`` is the floor any model meets (the dataset's 32-spp
noise and 8-bit rounding); ``direct only`` is the ceiling of a model without
interreflection that gets everything else right; ``x gain`` the same with the
best global brightness (a light level a fit could absorb); ``full/direct`` the
ratio of mean brightness (the share of light that arrives after a bounce).
The default frames are the held-out frames of the README's main job.
"""

import sys as _sys, pathlib as _pathlib
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parents[1]))
import variant_choice  # noqa: E402  (--variant NAME, default $MI_INVRGBL_VARIANT or llvm_ad_rgb)
variant_choice.from_argv()

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import mitsuba as mi  # noqa: E402

from mi_invrgbl.eval.metrics import linear_to_srgb, psnr  # noqa: E402
from mi_invrgbl.synthetic import rgb_frames, trajectory  # noqa: E402

DEPTH_TAG = '<integer name="max_depth" value="%d"'


def srgb(img):
    return np.clip(linear_to_srgb(img), 0.0, 1.0)


def render(root, depth, frames, spp):
    """Linear renders of ``frames`` of the street's day scene at path length ``depth``."""
    gt = os.path.join(root, "gt")
    traj = json.load(open(os.path.join(gt, "trajectory.json")))
    sensors = np.asarray(traj["world_from_cam"]) @ trajectory.KITTI_FROM_MITSUBA
    cars = np.asarray(traj["world_from_moving_car"])
    text = open(os.path.join(gt, "scene_time_a.xml")).read()
    dataset_depth = int(traj["config"]["max_depth"])
    if DEPTH_TAG % dataset_depth not in text:
        raise SystemExit("%s: no max_depth %d integrator" % (os.path.join(gt, "scene_time_a.xml"),
                                                             dataset_depth))
    # The scene names its meshes and textures relative to gt/: the file
    # resolver finds them there while the edited copy lives elsewhere.
    mi.file_resolver().prepend(gt)
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "scene.xml")
        with open(path, "w") as f:
            f.write(text.replace(DEPTH_TAG % dataset_depth, DEPTH_TAG % depth))
        scene = mi.load_file(path)
    poser = rgb_frames.FramePoser(scene, cars, ())
    out = {}
    for i in frames:
        poser.set_frame(i, sensors[i])
        out[i] = np.array(mi.render(scene, spp=spp, seed=1000 + i), np.float32)[..., :3]
    return out, dataset_depth


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", help="a make-scene street output folder")
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--frames", default="4,9,14,19")
    args = ap.parse_args(argv)
    frames = [int(x) for x in args.frames.split(",")]
    t = time.perf_counter()
    direct, depth = render(args.root, 2, frames, args.spp)
    full, _ = render(args.root, depth, frames, args.spp)
    seconds = time.perf_counter() - t
    gains = np.linspace(0.8, 1.6, 81)
    rows = []
    for i in frames:
        png = os.path.join(args.root, "sequences", "00", "image_2", "%06d.png" % i)
        img = cv2.imread(png)
        if img is None:
            raise SystemExit("%s: cannot read" % png)
        target = img[..., ::-1].astype(np.float32) / 255.0
        scores = [psnr(srgb(g * direct[i]), target) for g in gains]
        k = int(np.argmax(scores))
        rows.append((i, psnr(srgb(full[i]), target), psnr(srgb(direct[i]), target), scores[k],
                     gains[k], float(np.mean(full[i]) / np.mean(direct[i]))))
    print("%s, max_depth %d against 2 (direct light only), %d spp, %.0f s"
          % (args.root, depth, args.spp, seconds))
    print("frame  converged [dB]  direct only [dB]  x gain [dB] (gain)  full/direct")
    for r in rows:
        print("%5d  %14.2f  %16.2f  %11.2f (%.2f)  %11.3f" % r)
    m = np.mean([r[1:4] for r in rows], axis=0)
    print("mean   %14.2f  %16.2f  %11.2f" % tuple(m))


if __name__ == "__main__":
    main()
