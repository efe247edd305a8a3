"""Is a fitted street's geometry where the truth's is, and would normals
taken from its rendered depth beat its learned ones? (synthetic street)

    python tests/bench/depth_normals.py FIT_DIR [--spp 32] [--json OUT.json]

The fitted scene is rendered on ``eval``'s held-out frames as ``eval``
renders them (its samples per pixel; depth and normal AOVs divided by the
alpha). Pixels are split as ``albedo_breakdown.py`` splits the normal error:
at the truth's edges, tree crowns off the edges, and the rest.

* **Where the surface is.** Per pixel the distance the render shows (the
  depth AOV, a distance along the pixel's centre ray) over the truth's
  (its depth map is camera z, turned into a distance along the same ray):
  the share within 10 %, nearer, farther, and uncovered (alpha at most 0.5).
  A crown "missing from the geometry" shows the facade behind it: farther.
* **Normals from the depth.** The normal of the surface through each
  pixel's rendered point and its four neighbours' (central differences,
  turned towards the camera), where all five are covered (alpha above 0.9)
  and no neighbour's distance differs from the pixel's by more than 5 %;
  scored against the truth's normals next to the fit's own normal AOV on
  the same pixels. A prior map of this kind is what the paper's
  ``L_nor`` would get in place of its diffusion prior.
"""

import sys as _sys, pathlib as _pathlib
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parents[1]))
import variant_choice  # noqa: E402  (--variant NAME, default $MI_INVRGBL_VARIANT or llvm_ad_rgb)
variant_choice.from_argv()

import argparse  # noqa: E402
import json  # noqa: E402

import numpy as np  # noqa: E402

import mi_invrgbl  # noqa: E402,F401
from mi_invrgbl.eval.ground_truth import gt_alignment, source_number  # noqa: E402
from mi_invrgbl.eval.inputs import read_map  # noqa: E402
from mi_invrgbl.eval.rendering import render_camera  # noqa: E402
from mi_invrgbl.eval.scoring import EVAL_SPP  # noqa: E402
from mi_invrgbl.synthetic.groundtruth import camera_rays, rows as as_rows  # noqa: E402
from mi_invrgbl.scene.posing import set_frame  # noqa: E402
from albedo_breakdown import first_channel, truth_edges  # noqa: E402
from normal_oracle import z_per_unit_distance  # noqa: E402
from street_truth import open_fit  # noqa: E402

#: A neighbour farther than this fraction of the pixel's distance is across
#: a silhouette: no depth normal there.
DEPTH_STEP = 0.05
#: Pixels at least this opaque (and their four neighbours) get a depth normal.
COVERED = 0.9


def depth_normals(points, alpha):
    """(H, W, 3) unit normals of the surface through ``points`` (camera-centred,
    (H, W, 3)) from central differences, towards the camera, and (H, W) where
    they are defined (see :data:`DEPTH_STEP`, :data:`COVERED`)."""
    h, w, _ = points.shape
    n = np.zeros_like(points)
    ok = np.zeros((h, w), bool)
    c = np.cross(points[1:-1, 2:] - points[1:-1, :-2], points[2:, 1:-1] - points[:-2, 1:-1])
    c /= np.maximum(np.linalg.norm(c, axis=-1, keepdims=True), 1e-12)
    centre = points[1:-1, 1:-1]
    c = np.where((np.sum(c * centre, -1) > 0)[..., None], -c, c)
    dist = np.linalg.norm(points, axis=-1)
    mid = dist[1:-1, 1:-1]
    good = alpha[1:-1, 1:-1] > COVERED
    for sl in ((slice(1, -1), slice(2, None)), (slice(1, -1), slice(None, -2)),
               (slice(2, None), slice(1, -1)), (slice(None, -2), slice(1, -1))):
        good &= (alpha[sl] > COVERED) & (np.abs(dist[sl] - mid) < DEPTH_STEP * mid)
    n[1:-1, 1:-1] = c
    ok[1:-1, 1:-1] = good
    return n, ok


def rendered_and_true(scene, sensor, gt, number, R, spp):
    """One held-out frame rendered as ``eval`` renders it, beside the
    truth's maps: the render's channels, the truth's mesh ids and normals
    (turned into the scene's world by ``R``), the pixel-centre ray
    directions (H, W, 3), and the distance along them to the fitted surface
    (depth AOV over alpha) and to the true one (its camera z turned into a
    distance)."""
    cam = render_camera(scene, sensor, spp)
    h, w = cam["rgb"].shape[:2]
    base = str(gt / "maps" / ("%06d" % number))
    mesh = first_channel(read_map(base + "_mesh_id.exr"))
    true_n = read_map(base + "_normal.exr") @ R.T
    true_z = first_channel(read_map(base + "_depth.exr"))
    dist = cam["depth"] / np.maximum(cam["alpha"], 1e-6)
    d = as_rows(camera_rays(sensor, w, h).d).reshape(h, w, 3)
    true_dist = true_z / np.maximum(z_per_unit_distance(sensor, w, h, d), 1e-6)
    return cam, mesh, true_n, d, dist, true_dist


def angle(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, -1), -1.0, 1.0)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("fit")
    ap.add_argument("--spp", type=int, default=EVAL_SPP)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    frames, gt, positions, scene = open_fit(args.fit)
    R = gt_alignment(frames, positions, gt)
    names = {m["mesh_id"]: m["name"] for m in json.loads((gt / "materials.json").read_text())["meshes"]}
    crown_ids = [i for i, n in names.items() if n == "tree_crown"]
    regions = ("at the truth's edges", "tree crowns off the edges", "the rest")
    cols = {r: {"ratio": [], "fit": [], "depth": [], "has_depth": []} for r in regions}
    for k in positions:
        sensor, _ = set_frame(scene, frames, k)
        cam, mesh, true_n, d, dist, true_dist = rendered_and_true(
            scene, sensor, gt, source_number(frames[k]), R, args.spp)
        alpha = cam["alpha"]
        ratio = np.where(alpha > 0.5, dist / np.maximum(true_dist, 1e-6), np.inf)
        fitted = cam["normal"] / np.maximum(np.linalg.norm(cam["normal"], axis=-1, keepdims=True), 1e-9)
        from_depth, has = depth_normals(d * dist[..., None], alpha)
        scored = (mesh >= 0) & (alpha > 0.5)
        edge = truth_edges(mesh, true_n)
        crown = np.isin(mesh, crown_ids)
        for r, m in zip(regions, (edge, crown & ~edge, ~edge & ~crown)):
            cols[r]["ratio"].append(ratio[(mesh >= 0) & m])
            m = m & scored
            cols[r]["fit"].append(angle(fitted, true_n)[m])
            cols[r]["depth"].append(angle(from_depth, true_n)[m])
            cols[r]["has_depth"].append(has[m])
    rows = []
    print("| pixels | share | at the true distance (10 %) | nearer | farther | uncovered | fitted normals [deg] "
          "| with a depth normal | fitted normals there | depth normals there |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    total = sum(np.concatenate(c["fit"]).size for c in cols.values())
    for r in regions:
        c = {k: np.concatenate(v) for k, v in cols[r].items()}
        q, has = c["ratio"], c["has_depth"]
        row = {"region": r, "share": c["fit"].size / max(total, 1),
               "true_distance": float(np.mean(np.abs(q - 1) <= 0.1)), "nearer": float(np.mean(q < 0.9)),
               "farther": float(np.mean((q > 1.1) & np.isfinite(q))), "uncovered": float(np.mean(~np.isfinite(q))),
               "fit_deg": float(c["fit"].mean()), "with_depth_normal": float(has.mean()),
               "fit_deg_there": float(c["fit"][has].mean()), "depth_deg_there": float(c["depth"][has].mean())}
        rows.append(row)
        print("| %s | %.3f | %.3f | %.3f | %.3f | %.3f | %.2f | %.2f | %.2f | %.2f |" % (
            r, row["share"], row["true_distance"], row["nearer"], row["farther"], row["uncovered"],
            row["fit_deg"], row["with_depth_normal"], row["fit_deg_there"], row["depth_deg_there"]))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"fit": args.fit, "spp": args.spp, "rows": rows}, f, indent=1)
    return rows


if __name__ == "__main__":
    main()
