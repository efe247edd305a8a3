"""How far the street's materials hold its relighting: a fit with the
truth's roughness, albedo or both on the Gaussians standing on a true
surface (synthetic street).

    python tests/bench/material_oracle.py FIT_DIR [--off 0.2] [--nominal] [--fit-scale] [--write]

Every background Gaussian within ``--off`` metres of a true static surface
(points sampled on the truth's meshes, about 400 per square metre) takes
that surface's material from ``materials.json``: its roughness (``true
roughness``), its RGB albedo (``true albedo``; where the material has an
``albedo_texture``, as the road has its lane markings, the texture read by
Mitsuba's own ``bitmap`` at the sampled point's UV, as the truth's renders
read it; ``--nominal`` takes the material's single value instead) or both
(``true materials``); the rest keep the fit's.
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
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

import mi_invrgbl  # noqa: E402,F401
from mi_invrgbl.physics.gaussian_ply import read_ply  # noqa: E402
from street_truth import nearest_points, open_fit, truth_to_scene  # noqa: E402
from normal_oracle import variant_folder, write_edited  # noqa: E402

#: Points sampled per square metre of the truth's meshes (about 5 cm apart).
DENSITY = 400.0
VARIANTS = {"true roughness": ("roughness",), "true albedo": ("albedo",),
            "true materials": ("roughness", "albedo")}


def texture_values(path, uv):
    """Linear RGB of the image at ``path`` at ``uv`` (N, 2), read by Mitsuba's
    ``bitmap`` texture with the truth's settings (bilinear, repeat, sRGB
    decoded), so the orientation and wrapping are Mitsuba's, not ours."""
    tex = mi.load_dict({"type": "bitmap", "filename": str(path), "filter_type": "bilinear"})
    si = dr.zeros(mi.SurfaceInteraction3f, len(uv))
    si.uv = mi.Point2f(np.ascontiguousarray(uv[:, 0], np.float32), np.ascontiguousarray(uv[:, 1], np.float32))
    rgb = tex.eval(si)
    return np.stack([np.asarray(rgb[k], np.float64) for k in range(3)], axis=1)


def surface_uv(mesh, points, faces):
    """UV of ``points`` lying on ``mesh``'s triangles ``faces`` (barycentric)."""
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[faces], points)
    return np.einsum("nk,nkj->nj", bary, mesh.visual.uv[mesh.faces[faces]])


def sample_materials(gt, density=DENSITY, seed=0, textures=True):
    """Points on the truth's static meshes (truth's world) with their
    material's ``(roughness (N,), albedo (N, 3))``; with ``textures`` a
    material's ``albedo_texture`` gives the albedo where the mesh has UVs."""
    mats = json.loads((gt / "materials.json").read_text())
    pts, rough, alb = [], [], []
    for d in mats["meshes"]:
        path = gt / d["file"]
        if d.get("dynamic") or not path.is_file():
            continue
        mesh = trimesh.load(str(path), process=False)
        n = max(100, int(mesh.area * density))
        p, faces = trimesh.sample.sample_surface(mesh, n, seed=seed)
        m = mats["materials"][d["material"]]
        pts.append(p)
        rough.append(np.full(n, float(m["roughness"])))
        texture = m.get("albedo_texture") if textures else None
        if texture and getattr(mesh.visual, "uv", None) is not None:
            alb.append(texture_values(gt / texture, surface_uv(mesh, p, faces)))
        else:
            alb.append(np.tile(np.asarray(m["albedo"], np.float64), (n, 1)))
    return np.concatenate(pts), np.concatenate(rough), np.concatenate(alb)


def channel_scale(fitted, truth):
    """Per-channel factor ``s`` minimising ``|fitted - s * truth|²`` (the
    level that light and albedo trade freely in a fit)."""
    return np.sum(fitted * truth, axis=0) / np.maximum(np.sum(truth * truth, axis=0), 1e-12)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("fit", help="fitted scene folder (fit/)")
    ap.add_argument("--off", type=float, default=0.2,
                    help="metres from the closest true surface beyond which a Gaussian keeps its material")
    ap.add_argument("--write", action="store_true", help="write each variant next to the fit (for eval)")
    ap.add_argument("--nominal", action="store_true",
                    help="each material's single albedo, its texture (the road's markings) left out")
    ap.add_argument("--fit-scale", action="store_true",
                    help="scale the truth's albedo per channel to the fitted albedo's level (least "
                         "squares over the Gaussians on a true surface), so that the fit's light, "
                         "which sets that level, is not what the variant is scored on")
    args = ap.parse_args()
    taken = [variant_folder(args.fit, v) for v in VARIANTS
             if args.write and os.path.exists(variant_folder(args.fit, v))]
    if taken:
        raise SystemExit("%s: exists; not overwritten" % taken[0])
    frames, gt, positions, _ = open_fit(args.fit, "held-out")
    points, rough, alb = sample_materials(gt, textures=not args.nominal)
    T = truth_to_scene(gt, frames[positions[0]])
    points = points @ T[:3, :3].T + T[:3, 3]
    cloud = read_ply(os.path.join(args.fit, "background.ply"))
    pick, dist = nearest_points(points, cloud.centers)
    on = dist <= args.off
    fr = cloud.roughness.ravel()
    true_albedo = alb[pick]
    if args.fit_scale:
        scale = channel_scale(cloud.albedo[on], true_albedo[on])
        true_albedo = np.clip(true_albedo * scale, 0.0, 1.0)
        print("the truth's albedo scaled by %s per channel" % np.round(scale, 3))
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
                c.albedo = np.where(on[:, None], true_albedo, c.albedo).astype(np.float32)
        print("wrote %s" % write_edited(args.fit, name, edit))


if __name__ == "__main__":
    main()
