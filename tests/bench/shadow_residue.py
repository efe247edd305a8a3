"""How much cast shadow is left in fitted albedo maps (synthetic street).

    python tests/bench/shadow_residue.py out/street_fit2 [fit_full fit_no_consistency ...]

On ground pixels (ground-truth normal within 25 degrees of up) of every
training frame, the ratio of fitted to true albedo luminance is averaged
separately over pixels in the sun's shadow and in sunlight (ground-truth
``sun_visibility``). ``shadow/lit`` = 1 means the shadows were removed from
the albedo; the same ratio for the observed image (radiance / true albedo)
shows how dark the shadows are to begin with.
"""

import sys as _sys, pathlib as _pathlib
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parents[1]))
import variant_choice  # noqa: E402  (--variant NAME, default $MI_INVRGBL_VARIANT or llvm_ad_rgb)
variant_choice.from_argv()

import os
import sys

import numpy as np
import cv2

from street_truth import (LUM, fitted_map, ground_truth, observed_linear, source_number,
                          truth_map)


def main():
    root = sys.argv[1]
    variants = sys.argv[2:] or sorted(d for d in os.listdir(root) if d.startswith("fit"))
    meta, gt = ground_truth(root)
    rows = {}
    for v in ["observed"] + variants:
        num = {"shadow": [], "lit": []}
        for f in meta["frames"]:
            if f.get("held_out"):
                continue
            i, n = f["index"], source_number(f)
            a_gt = truth_map(gt, "albedo", n)[..., :3] @ LUM
            nrm = truth_map(gt, "normal", n)[..., :3]
            vis = truth_map(gt, "sun_visibility", n)
            if v == "observed":
                a_fit = observed_linear(root, i) @ LUM
            else:
                a_fit = fitted_map(root, v, i, "albedo")
                if a_fit is None:
                    continue
                a_fit = a_fit[..., :3] @ LUM
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
