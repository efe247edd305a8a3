"""Where a fitted street's albedo and normal error come from (synthetic street).

    python tests/bench/albedo_breakdown.py FIT_DIR [FIT_DIR ...] [--frames held-out]

Each fitted scene is rendered through the evaluation's own pipeline on the
held-out frames (``mi-invrgbl eval``'s selection, its alpha mask and its
alignment with the ground truth). The albedo is scaled per channel by one
least-squares factor over all scored pixels pooled (``eval`` fits one per
frame), then the error is split by the ground truth's mesh: each material's
share of pixels, its true and fitted (scaled) mean albedo, its RMSE, its share
of the squared error, its median normal error and share of the summed normal
error, its true and fitted median roughness, and the true sun visibility
there. Before the table, the normal error is split into pixels at the
truth's edges (next to another mesh or a turn of the normal), tree crowns
and the rest, each with its share of the mean, and the error on other
meshes next to the moving objects (where a car's own Gaussians could draw
its shadow on the road). A row whose fitted albedo
is far darker than the truth while the truth says the material is in
shadow is shading the fit credits to the wrong light; a constant albedo
(every pixel at the true mean) is printed for scale.
"""

import sys as _sys, pathlib as _pathlib
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parents[1]))
import variant_choice  # noqa: E402  (--variant NAME, default $MI_INVRGBL_VARIANT or llvm_ad_rgb)
variant_choice.from_argv()

import argparse  # noqa: E402
import json  # noqa: E402

import numpy as np  # noqa: E402
import mitsuba as mi  # noqa: E402,F401

import mi_invrgbl  # noqa: E402,F401
from mi_invrgbl.eval.ground_truth import ALPHA_MIN, gt_alignment, source_number  # noqa: E402
from mi_invrgbl.eval import metrics as M  # noqa: E402
from mi_invrgbl.eval.inputs import read_map, read_png  # noqa: E402
from mi_invrgbl.eval.rendering import integrator_like, render_camera  # noqa: E402
from mi_invrgbl.scene.posing import set_frame  # noqa: E402
from street_truth import open_fit  # noqa: E402

#: Materials below this share of the scored pixels are pooled into "other".
MIN_SHARE = 0.01
#: A normal turning by more than this between neighbouring pixels of the
#: truth marks an edge (a box's corner turns by 90).
EDGE_TURN_DEG = 20.0
#: Pixels of other meshes within this many pixels of a moving object count
#: as next to it (where a car's own Gaussians could draw its shadow).
NEAR_MOVING_PX = 15


def first_channel(x):
    return x[..., 0] if x is not None and x.ndim == 3 else x


def truth_edges(mesh, normal, turn_deg=EDGE_TURN_DEG):
    """Pixels on either side of a step in the truth's maps: another mesh
    or a normal turned by more than ``turn_deg`` in the next pixel across or
    down. There a pixel's footprint straddles two surfaces, and a fit whose
    Gaussians blend the two sides pays up to the angle between them."""
    cos_max = np.cos(np.radians(turn_deg))
    edge = np.zeros(mesh.shape, bool)
    for axis in (0, 1):
        a = [slice(None)] * 2
        b = [slice(None)] * 2
        a[axis], b[axis] = slice(1, None), slice(None, -1)
        a, b = tuple(a), tuple(b)
        step = (mesh[a] != mesh[b]) | (np.sum(normal[a] * normal[b], axis=-1) < cos_max)
        edge[a] |= step
        edge[b] |= step
    return edge


def near_moving(mesh, moving_ids, px=NEAR_MOVING_PX):
    """Pixels of other meshes within ``px`` pixels (a square) of a moving mesh."""
    import cv2
    on = np.isin(mesh, list(moving_ids))
    near = cv2.dilate(on.astype(np.uint8), np.ones((2 * px + 1, 2 * px + 1), np.uint8)) > 0
    return near & ~on


def collect(fit, frames_spec):
    """Per scored pixel: fitted albedo, true albedo, mesh id, normal error, true sun visibility."""
    frames, gt, positions, scene = open_fit(fit, frames_spec)
    integ = integrator_like(scene, None)
    R = gt_alignment(frames, positions, gt)
    meshes = json.loads((gt / "materials.json").read_text())["meshes"]
    moving_ids = {d["mesh_id"] for d in meshes if d.get("dynamic")}
    cols = {k: [] for k in ("fit", "true", "mesh", "angle", "sun", "rough", "true_rough", "edge",
                            "near_moving")}
    # Every pixel's rendered and observed sRGB colour, and whether it lies
    # on or next to a moving object (the image's PSNR split, sky included).
    image_pred, image_obs, image_near = [], [], []
    for k in positions:
        sensor, _ = set_frame(scene, frames, k)
        cam = render_camera(scene, sensor, 0, integ)
        base = str(gt / "maps" / ("%06d_" % source_number(frames[k])))
        mesh = first_channel(read_map(base + "mesh_id.exr"))
        near = near_moving(mesh, moving_ids)
        if frames[k].image is not None:
            image_pred.append(np.clip(M.linear_to_srgb(cam["rgb"]), 0.0, 1.0).reshape(-1, 3))
            image_obs.append(read_png(frames[k].image).reshape(-1, 3))
            image_near.append((near | np.isin(mesh, list(moving_ids))).ravel())
        alpha = cam["alpha"]
        m = (mesh >= 0) & (alpha > ALPHA_MIN)
        normal = cam["normal"][m]
        normal = normal / np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
        true_map = read_map(base + "normal.exr")
        true_n = true_map[m] @ R.T
        cols["edge"].append(truth_edges(mesh, true_map)[m])
        cols["near_moving"].append(near[m])
        sun = read_map(base + "sun_visibility.exr")
        cols["fit"].append(cam["albedo"][m] / alpha[m][:, None])
        cols["true"].append(read_map(base + "albedo.exr")[m])
        cols["mesh"].append(mesh[m].astype(int))
        cols["angle"].append(np.degrees(np.arccos(np.clip(np.sum(normal * true_n, 1), -1, 1))))
        cols["sun"].append(first_channel(sun)[m] if sun is not None else np.full(m.sum(), np.nan))
        cols["rough"].append(first_channel(cam["roughness"])[m] / alpha[m])
        rough = first_channel(read_map(base + "roughness.exr"))
        cols["true_rough"].append(rough[m] if rough is not None else np.full(m.sum(), np.nan))
    names = {d["mesh_id"]: d["name"] for d in meshes}
    out = {k: np.concatenate(v) for k, v in cols.items()}
    if image_pred:
        out["image_pred"], out["image_obs"] = np.concatenate(image_pred), np.concatenate(image_obs)
        out["image_near"] = np.concatenate(image_near)
    return out, names


def label_of(data, names):
    return np.array([names.get(int(i), str(i)) for i in data["mesh"]])


def report(fit, data, names):
    p, t = data["fit"], data["true"]
    scale = np.sum(p * t, 0) / np.maximum(np.sum(p * p, 0), 1e-12)
    ps = p * scale
    err2 = np.sum((ps - t) ** 2, 1)
    const = np.sqrt(np.mean((t - t.mean(0)) ** 2))
    print("\n%s: %d pixels, pooled albedo RMSE %.4f (a constant albedo: %.4f), normal error "
          "mean %.1f, median %.1f deg, scale %s" % (fit, len(p), np.sqrt(err2.mean() / 3), const,
                                                    np.mean(data["angle"]), np.median(data["angle"]),
                                                    np.round(scale, 3)))
    angle = data["angle"]
    label = label_of(data, names)
    edge, crown = data["edge"], label == "tree_crown"
    for what, sel in (("at the truth's edges", edge), ("tree crowns off the edges", crown & ~edge),
                      ("everything else", ~edge & ~crown)):
        print("normal error %s: %.3f of the pixels, mean %.1f deg, %.2f deg of the mean"
              % (what, sel.mean(), np.mean(angle[sel]) if sel.any() else 0.0,
                 angle[sel].sum() / max(len(angle), 1)))
    near = data["near_moving"]
    print("normal error next to the moving objects (other meshes within %d px): %.3f of the pixels, "
          "mean %.1f deg, %.2f deg of the mean" % (NEAR_MOVING_PX, near.mean(),
                                                   np.mean(angle[near]) if near.any() else 0.0,
                                                   angle[near].sum() / max(len(angle), 1)))
    if "image_pred" in data:
        pred, obs, zone = data["image_pred"], data["image_obs"], data["image_near"][:, None]
        # Pooled over every pixel of the frames, at the sensor's own samples
        # per pixel: close to, not the same as, eval's per-frame mean at 32.
        print("PSNR pooled over the frames (sRGB): %.2f dB; on and next to the moving objects "
              "(%.3f of the pixels) %.2f dB, elsewhere %.2f dB"
              % (M.psnr(pred, obs), zone.mean(), M.psnr(pred, obs, mask=zone),
                 M.psnr(pred, obs, mask=~zone)))
    print("| material | pixels | true albedo | fitted (scaled) | RMSE | error share | normal [deg] "
          "| normal share | roughness (true, fitted) | true sun vis |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    kinds = sorted(set(label), key=lambda n: -np.sum(err2[label == n]))
    small = [n for n in kinds if np.mean(label == n) < MIN_SHARE]
    for name in [n for n in kinds if n not in small] + (["other"] if small else []):
        sel = np.isin(label, small) if name == "other" else label == name
        fmt = lambda v: " ".join("%.2f" % x for x in v)  # noqa: E731
        print("| %s | %.3f | %s | %s | %.3f | %.3f | %.1f | %.3f | %.2f %.2f | %.2f |"
              % (name, sel.mean(), fmt(t[sel].mean(0)), fmt(ps[sel].mean(0)),
                 np.sqrt(err2[sel].mean() / 3), err2[sel].sum() / err2.sum(),
                 np.median(angle[sel]), angle[sel].sum() / angle.sum(),
                 np.nanmedian(data["true_rough"][sel]), np.median(data["rough"][sel]),
                 np.nanmean(data["sun"][sel])))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("fits", nargs="+", help="fitted scene folders (fit/)")
    ap.add_argument("--frames", default="held-out", help="frame selection as in eval (default held-out)")
    args = ap.parse_args()
    for fit in args.fits:
        data, names = collect(fit, args.frames)
        report(fit, data, names)


if __name__ == "__main__":
    main()
