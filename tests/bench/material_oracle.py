"""How far the street's materials hold its relighting: a fit with the
truth's roughness, albedo or both on the Gaussians standing on a true
surface (synthetic street).

    python tests/bench/material_oracle.py FIT_DIR [--off 0.2] [--write]

Every background Gaussian within ``--off`` metres of a true static surface
(points sampled on the truth's meshes, about 400 per square metre) takes
that surface's material from ``materials.json``: its roughness (``true
roughness``), its RGB albedo (``true albedo``; the road's nominal value,
not its texture) or both (``true materials``); the rest keep the fit's.
Printed: the share of Gaussians on a true surface and the fitted against
the true roughness and albedo there. With ``--write`` each variant is
written next to the fit (``FIT_DIR_true_roughness`` and so on: its scene
files with the edited ``background.ply``) for ``mi-invrgbl eval`` to score;
an existing folder of that name is left alone and the run stops. A variant
that relights better than the fit names the material that holds the
relighting back; one that relights worse says the fitted scene's shading
cannot carry the truth's materials (its BRDF and light transport are not
the truth's).
"""

import sys as _sys, pathlib as _pathlib
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parents[1]))
import variant_choice  # noqa: E402  (--variant NAME, default $MI_INVRGBL_VARIANT or llvm_ad_rgb)
variant_choice.from_argv()

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402

import numpy as np  # noqa: E402
import trimesh  # noqa: E402

import mi_invrgbl  # noqa: E402,F401
from mi_invrgbl.physics.gaussian_ply import read_ply  # noqa: E402
from street_truth import nearest_points, open_fit, truth_to_scene  # noqa: E402
from normal_oracle import variant_folder, write_edited  # noqa: E402

#: Points sampled per square metre of the truth's meshes (about 5 cm apart).
DENSITY = 400.0
VARIANTS = {"true roughness": ("roughness",), "true albedo": ("albedo",),
            "true materials": ("roughness", "albedo")}


def sample_materials(gt, density=DENSITY, seed=0):
    """Points on the truth's static meshes (truth's world) with their
    material's ``(roughness (N,), albedo (N, 3))``."""
    mats = json.loads((gt / "materials.json").read_text())
    pts, rough, alb = [], [], []
    for d in mats["meshes"]:
        path = gt / d["file"]
        if d.get("dynamic") or not path.is_file():
            continue
        mesh = trimesh.load(str(path), process=False)
        n = max(100, int(mesh.area * density))
        p, _ = trimesh.sample.sample_surface(mesh, n, seed=seed)
        m = mats["materials"][d["material"]]
        pts.append(p)
        rough.append(np.full(n, float(m["roughness"])))
        alb.append(np.tile(np.asarray(m["albedo"], np.float64), (n, 1)))
    return np.concatenate(pts), np.concatenate(rough), np.concatenate(alb)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("fit", help="fitted scene folder (fit/)")
    ap.add_argument("--off", type=float, default=0.2,
                    help="metres from the closest true surface beyond which a Gaussian keeps its material")
    ap.add_argument("--write", action="store_true", help="write each variant next to the fit (for eval)")
    args = ap.parse_args()
    taken = [variant_folder(args.fit, v) for v in VARIANTS
             if args.write and os.path.exists(variant_folder(args.fit, v))]
    if taken:
        raise SystemExit("%s: exists; not overwritten" % taken[0])
    frames, gt, positions, _ = open_fit(args.fit, "held-out")
    points, rough, alb = sample_materials(gt)
    T = truth_to_scene(gt, frames[positions[0]])
    points = points @ T[:3, :3].T + T[:3, 3]
    cloud = read_ply(os.path.join(args.fit, "background.ply"))
    pick, dist = nearest_points(points, cloud.centers)
    on = dist <= args.off
    fr = cloud.roughness.ravel()
    print("%s: %d background Gaussians, %.3f within %.2f m of a true surface; there the fitted "
          "roughness has median %.2f (truth %.2f), mean absolute error %.3f; the fitted albedo "
          "mean %s (truth %s)" % (args.fit, len(on), on.mean(), args.off, np.median(fr[on]),
                                  np.median(rough[pick][on]), np.mean(np.abs(fr[on] - rough[pick][on])),
                                  np.round(cloud.albedo[on].mean(0), 3), np.round(alb[pick][on].mean(0), 3)))
    if not args.write:
        return
    for name, fields in VARIANTS.items():
        def edit(c, fields=fields):
            if "roughness" in fields:
                c.roughness = np.where(on, rough[pick], c.roughness.ravel()).astype(np.float32).reshape(
                    c.roughness.shape)
            if "albedo" in fields:
                c.albedo = np.where(on[:, None], alb[pick], c.albedo).astype(np.float32)
        print("wrote %s" % write_edited(args.fit, name, edit))


if __name__ == "__main__":
    main()
