"""Do an import's camera poses agree with its images? Photo-consistency of LiDAR points.

    python tests/bench/pose_consistency.py IMPORT_DIR [--frames 0 10 20] [--later 1 3 6]

Each listed frame's LiDAR points (``observations/points_NNNN.npy``, world
frame) are projected into its own image and into the images of frames
``--later`` steps on, with the poses of ``frames.json``. For each pair the
script prints the median colour difference of the points both cameras see
and the integer pixel shift (searched over +-3 pixels) of the second
projection that minimises it: with right poses the best shift is 0 (moving
vehicles and occlusions raise the difference, not the shift). It also prints
each frame's mean image level, to see exposure changes. Only the files of
the named frames are read; nothing is written.
"""

import argparse
import json
from pathlib import Path

import cv2
import numpy as np


def project(points, cam_to_world, K, size):
    """Pixel coordinates and depth of world ``points`` in an OpenCV-convention camera."""
    w2c = np.linalg.inv(cam_to_world)
    pc = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = pc[:, :2] / z[:, None] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    w, h = size
    ok = (z > 1.0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    return uv, ok


def sample(image, uv):
    h, w = image.shape[:2]
    u = np.clip(uv[:, 0].astype(int), 0, w - 1)
    v = np.clip(uv[:, 1].astype(int), 0, h - 1)
    return image[v, u]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("import_dir")
    ap.add_argument("--frames", nargs="+", type=int, default=[0, 10, 20])
    ap.add_argument("--later", nargs="+", type=int, default=[1, 3, 6])
    ap.add_argument("--search", type=int, default=3, help="pixel shift searched (+-)")
    args = ap.parse_args(argv)
    root = Path(args.import_dir)
    meta = json.loads((root / "frames.json").read_text())
    cam = meta["camera"]
    K = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1.0]])
    size = (cam["width"], cam["height"])
    recs = {f["index"]: f for f in meta["frames"]}

    def image(i):
        return cv2.imread(str(root / recs[i]["image"]))[..., ::-1].astype(np.float64) / 255.0

    for i in args.frames:
        if i not in recs:
            raise SystemExit("%s: no frame %d" % (root / "frames.json", i))
        pts = np.load(root / recs[i]["points"])[:, :3].astype(np.float64)
        uv, ok = project(pts, np.array(recs[i]["camera_to_world"]), K, size)
        img_i = image(i)
        print("frame %d: %d points in view, mean image level %s"
              % (i, ok.sum(), np.round(img_i.mean(axis=(0, 1)), 3).tolist()))
        for step in args.later:
            j = i + step
            if j not in recs:
                continue
            uv_j, ok_j = project(pts, np.array(recs[j]["camera_to_world"]), K, size)
            both = ok & ok_j
            a = sample(img_i, uv[both])
            img_j = image(j)
            best = min((float(np.median(np.abs(a - sample(img_j, uv_j[both] + [du, dv])).mean(1))),
                        du, dv)
                       for du in range(-args.search, args.search + 1)
                       for dv in range(-args.search, args.search + 1))
            at_zero = float(np.median(np.abs(a - sample(img_j, uv_j[both])).mean(1)))
            print("  -> frame %d: median |colour difference| %.3f at zero shift; best shift "
                  "(%d, %d) px with %.3f" % (j, at_zero, best[1], best[2], best[0]))


if __name__ == "__main__":
    main()
