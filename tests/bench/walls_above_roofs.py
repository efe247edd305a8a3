"""Fitted Gaussians standing above the true roofs (synthetic street).

    python tests/bench/walls_above_roofs.py out/street_fit3 fit_a [fit_b ...]

The import extends every facade the LiDAR's top beam cuts by a fixed height;
over roofs lower than that, the extension is wall that is not there. For each
ground-truth building, Gaussians of a fitted ``background.ply`` (opacity above
0.3) within 1 m of its street-side facade and inside its length are counted
above its roof (+0.5 m) and below it (-0.5 m): the first are walls made of
sky, the second the real facade. Ground-truth meshes are mapped into the
scene's world by the first frame's camera pose.
"""

import sys as _sys, pathlib as _pathlib
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parents[1]))
import variant_choice  # noqa: E402  (--variant NAME, default $MI_INVRGBL_VARIANT or llvm_ad_rgb)
variant_choice.from_argv()

import glob
import os
import sys

import numpy as np
import trimesh

import street_truth  # noqa: F401  (sets the Mitsuba variant)
from mi_invrgbl.physics.gaussian_ply import read_ply  # noqa: E402
from mi_invrgbl.scene.frames import Frames  # noqa: E402


def gt_from_scene(root, gt_dir):
    """4x4 transform from the scene's world into the ground truth's."""
    import json
    frames = Frames.load(os.path.join(root, "scene.xml"))
    cams = json.load(open(os.path.join(gt_dir, "trajectory.json")))["world_from_cam"]
    return np.linalg.inv(street_truth.scene_from_truth(frames[0], cams))


def main():
    root, variants = sys.argv[1], sys.argv[2:]
    frames = Frames.load(os.path.join(root, "scene.xml"))
    gt_dir = frames.ground_truth
    if not gt_dir or not os.path.isdir(gt_dir):
        sys.exit("%s: frames.json names no ground truth" % root)
    T = gt_from_scene(root, gt_dir)
    boxes = [trimesh.load(p).bounds for p in sorted(glob.glob(os.path.join(gt_dir, "meshes", "building_*.ply")))]
    print("| fit | Gaussians above true roofs | below (real facade) | buildings |")
    print("|---|---|---|---|")
    for v in variants:
        cloud = read_ply(os.path.join(root, v, "background.ply"))
        c = cloud.centers.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
        solid = cloud.opacities > 0.3
        above = below = 0
        for b in boxes:
            street_side = b[0, 1] if b[0, 1] > 0 else b[1, 1]
            near = solid & (c[:, 0] > b[0, 0] + 0.5) & (c[:, 0] < b[1, 0] - 0.5) \
                & (np.abs(c[:, 1] - street_side) < 1.0)
            above += int(np.sum(near & (c[:, 2] > b[1, 2] + 0.5)))
            below += int(np.sum(near & (c[:, 2] < b[1, 2] - 0.5)))
        print("| %s | %d | %d | %d |" % (v, above, below, len(boxes)))


if __name__ == "__main__":
    main()
