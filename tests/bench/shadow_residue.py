"""How much cast shadow is left in fitted albedo maps (synthetic street).

    python tests/bench/shadow_residue.py out/street_fit2 [fit_full fit_no_consistency ...]

On ground pixels (ground-truth normal within 25 degrees of up) of every
training frame, the ratio of fitted to true albedo luminance is averaged
separately over pixels in the sun's shadow and in sunlight (ground-truth
``sun_visibility``). ``shadow/lit`` = 1 means the shadows were removed from
the albedo; the same ratio for the observed image (radiance / true albedo)
shows how dark the shadows are to begin with.
"""

import json
import os
import sys

import numpy as np
import OpenEXR
import cv2

LUM = np.array([0.2126, 0.7152, 0.0722])


def exr(path):
    ch = OpenEXR.File(path).channels()
    return ch["RGB"].pixels if "RGB" in ch else next(iter(ch.values())).pixels


def main():
    root = sys.argv[1]
    variants = sys.argv[2:] or sorted(d for d in os.listdir(root) if d.startswith("fit"))
    meta = json.load(open(os.path.join(root, "frames.json")))
    gt = meta.get("ground_truth")
    gt = gt.get("dir") if isinstance(gt, dict) else gt
    if not gt:
        sys.exit("%s: frames.json names no ground truth" % root)
    if not os.path.isabs(gt):
        gt = os.path.normpath(os.path.join(root, gt))
    rows = {}
    for v in ["observed"] + variants:
        num = {"shadow": [], "lit": []}
        for f in meta["frames"]:
            if f.get("held_out"):
                continue
            i = f["index"]
            n = int(f.get("source_index", f.get("source_frame", i)))
            a_gt = exr(os.path.join(gt, "maps", "%06d_albedo.exr" % n))[..., :3] @ LUM
            nrm = exr(os.path.join(gt, "maps", "%06d_normal.exr" % n))[..., :3]
            vis = exr(os.path.join(gt, "maps", "%06d_sun_visibility.exr" % n))
            vis = vis[..., 0] if vis.ndim == 3 else vis
            if v == "observed":
                img = cv2.imread(os.path.join(root, "observations", "image_%04d.png" % i))[..., ::-1] / 255.0
                img = np.where(img <= 0.04045, img / 12.92, ((img + 0.055) / 1.055) ** 2.4)
                a_fit = img @ LUM
            else:
                p = os.path.join(root, v, "maps", "%04d_albedo.exr" % i)
                if not os.path.isfile(p):
                    continue
                a_fit = exr(p)[..., :3] @ LUM
            if a_fit.shape != a_gt.shape:
                a_fit = cv2.resize(a_fit, a_gt.shape[::-1], interpolation=cv2.INTER_AREA)
            ground = (nrm[..., 2] > np.cos(np.radians(25))) & (a_gt > 0.02) & (a_fit > 0)
            r = a_fit / np.maximum(a_gt, 1e-3)
            num["shadow"].append(r[ground & (vis < 0.5)])
            num["lit"].append(r[ground & (vis >= 0.5)])
        if not num["lit"]:
            continue
        sh, lit = np.concatenate(num["shadow"]), np.concatenate(num["lit"])
        rows[v] = (np.median(sh) / np.median(lit), sh.size, lit.size)
    print("| albedo source | shadow/lit (median ratio to true albedo) | shadow px | lit px |")
    print("|---|---|---|---|")
    for v, (ratio, ns, nl) in rows.items():
        print("| %s | %.2f | %d | %d |" % (v, ratio, ns, nl))


if __name__ == "__main__":
    main()
