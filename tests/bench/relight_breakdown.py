"""Where a fitted street's relighting error comes from (synthetic street).

    python tests/bench/relight_breakdown.py FIT_DIR [FIT_DIR ...] [--frames held-out]

``eval`` relights a fit by setting its sky and sun to the ground truth's
time-B light and scores the render against the truth's time-B image. The
fitted albedo carries whatever the fitted light left it: where the fit's
sun came out weaker against its sky than the truth's, the albedo of
sunlit surfaces is too bright, and every relit pixel there too. This script
renders each held-out frame five times through ``eval``'s own pipeline:
under the fit's own light; the same with the sun's shadows traced through
the Gaussians instead of read from the learned visibility field; under the
truth's time-A light (the time of day the fit was made at), set the way
``eval`` sets time B, with traced shadows; under time B; and under the
fitted light edited to time B as ``eval``'s ``relight_edit_psnr`` edits it
(the sun turned, sky and sun scaled by the truth's B / A ratios). For each
it prints:

- the PSNR as ``eval`` scores it;
- the least-squares scale per channel (linear radiance, pooled over the
  frames) that brings the render nearest the truth, and the PSNR after it:
  what a correct light level alone would buy;
- per ground-truth material: its share of the pixels, its share of the
  squared (sRGB) error, and the ratio of fitted to true mean luminance,
  which shows surfaces that come out too dark or too bright under one
  light and not under the other (say, shadowed at time A, sunlit at B);
- per material, where the time-B sun reaches: the share of its pixels the
  truth's meshes leave sunlit and the share the fitted Gaussians leave
  sunlit (shadow rays from SHADOW_OFFSET above the true surface point of
  each pixel, towards the time-B sun, through the truth's
  ``scene_time_b.xml`` and through the fitted Gaussians; ``eval`` traces
  from above each Gaussian's centre instead, and where the fitted surface
  stands in front of the true one by more than the offset, as the street's
  sunlit facades do (``surface_offset.py``), these rays start behind it and
  overstate its shadows), and the share on which
  the two disagree. Shadow casters the fit lacks show as sunlit pixels the
  truth has in shadow; casters it has and the truth does not (walls the
  import extended above a lower roof) as shadowed pixels the truth lights.
  The truth's
  moving car stands where ``scene_time_b.xml`` puts it, so its own pixels
  and the shadow it casts are left out of that comparison.
"""

import sys as _sys, pathlib as _pathlib
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parents[1]))
import variant_choice  # noqa: E402  (--variant NAME, default $MI_INVRGBL_VARIANT or llvm_ad_rgb)
variant_choice.from_argv()

import argparse  # noqa: E402
import json  # noqa: E402
from collections import namedtuple  # noqa: E402

import numpy as np  # noqa: E402
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402,F401

import mi_invrgbl  # noqa: E402,F401
from mi_invrgbl.eval import metrics as M  # noqa: E402
from mi_invrgbl.eval.ground_truth import gt_alignment, load_lights, source_number  # noqa: E402
from mi_invrgbl.eval.inputs import read_channels, read_map  # noqa: E402
from mi_invrgbl.eval.rendering import SkySwap, find_sky, integrator_like, render_camera  # noqa: E402
from mi_invrgbl.eval.scoring import EVAL_SPP, edit_ratios  # noqa: E402
from mi_invrgbl.physics.colour import LUMINANCE  # noqa: E402
from mi_invrgbl.physics import hits as hitlib  # noqa: E402
from mi_invrgbl.physics.host_arrays import jit_array  # noqa: E402
# Shadow rays leave the true surface as the integrator's leave a Gaussian.
from mi_invrgbl.physics.lighting import SHADOW_OFFSET, transmittance  # noqa: E402
from mi_invrgbl.scene.posing import set_frame  # noqa: E402
from mi_invrgbl.synthetic.groundtruth import camera_rays, rows  # noqa: E402
from street_truth import open_fit, refuse_existing, scene_from_truth  # noqa: E402

#: Materials below this share of the pixels are pooled into "other".
MIN_SHARE = 0.01


def truth_image(path):
    ch = read_channels(path, ["r", "g", "b"], "ground truth")
    return np.stack([ch["r"], ch["g"], ch["b"]], -1).astype(np.float64)


def vector3f(a):
    return mi.Vector3f(*[jit_array(mi.Float, np.ascontiguousarray(a[:, i], np.float32))
                         for i in range(3)])


SunRays = namedtuple("SunRays", "hit origin sun_fit to_gt true_vis vis")


def true_surface(scene, frames, k, gt, cams):
    """Per pixel of frame ``k`` (``scene``'s sensor placed there): ``hit``
    (the truth sees a surface), the true surface point in the fitted
    scene's world and in the truth's, the truth's normal (its map, the
    truth's world) and ``to_gt`` (4x4, the fitted scene's world into the
    truth's)."""
    rec, n = frames[k], source_number(frames[k])
    sensor, _ = set_frame(scene, frames, k)
    w, h = sensor.film().size()
    ray = camera_rays(sensor, int(w), int(h))
    d, o = rows(ray.d), rows(ray.o)
    depth = read_map(str(gt / "maps" / ("%06d_depth.exr" % n)))
    depth = (depth[..., 0] if depth.ndim == 3 else depth).reshape(-1)
    normal = read_map(str(gt / "maps" / ("%06d_normal.exr" % n))).reshape(-1, 3)
    # The maps' depth is along the camera's axis; the scene's and the
    # truth's worlds differ by the rigid motion between their camera poses.
    cam = np.asarray(rec.camera_to_world, np.float64)
    p_fit = o + d * (depth / np.maximum(d @ cam[:3, 2], 1e-9))[:, None]
    T = np.linalg.inv(scene_from_truth(rec, cams))
    return depth > 0, p_fit, p_fit @ T[:3, :3].T + T[:3, 3], normal, T


def sun_rays(scene, gt_scene, frames, k, gt, cams, sun_gt, R):
    """Per pixel of frame ``k``, shadow rays towards the sun ``sun_gt`` from
    SHADOW_OFFSET above the true surface point: ``hit`` (the truth sees a
    surface), ``origin`` and ``sun_fit`` (the rays in the fitted scene's
    world), ``to_gt`` (4x4, the fitted scene's world into the truth's),
    ``true_vis`` (bool: facing the sun and open to it through the truth's
    meshes) and ``vis`` (the fitted Gaussians' transmittance, 0 where the
    surface faces away)."""
    hit, p_fit, p_gt, normal, T = true_surface(scene, frames, k, gt, cams)
    sun_fit = R @ sun_gt
    facing = (normal @ sun_gt) > 0
    shadow = mi.Ray3f(vector3f(p_gt + SHADOW_OFFSET * normal), vector3f(np.tile(sun_gt, (len(p_gt), 1))))
    true_vis = facing & ~np.array(gt_scene.ray_test(shadow), bool)
    origin = p_fit + SHADOW_OFFSET * normal @ R.T
    vis = np.array(transmittance(scene, vector3f(origin), vector3f(np.tile(sun_fit, (len(p_fit), 1))),
                                 mi.Float(dr.inf), hitlib.gaussian_nodes(scene)), np.float64)
    vis = np.where(facing, np.clip(vis, 0.0, 1.0), 0.0)
    return SunRays(hit, origin, sun_fit, T, true_vis, vis)


def sun_reach(scene, gt_scene, frames, k, gt, cams, sun_gt, R):
    """Per pixel of frame ``k``: 1 where the truth's meshes leave the true
    surface point open to the sun ``sun_gt``, the same through the fitted
    scene (NaN where the truth sees no surface)."""
    r = sun_rays(scene, gt_scene, frames, k, gt, cams, sun_gt, R)
    return (np.where(r.hit, r.true_vis.astype(np.float64), np.nan), np.where(r.hit, r.vis, np.nan))


def collect(fit, frames_spec, spp):
    """Per pixel of every selected frame: fitted and true linear RGB at time
    A (the fit's own light) and time B (the truth's relighting), and mesh id."""
    frames, gt, positions, scene = open_fit(fit, frames_spec)
    sky = find_sky(scene)
    lights = load_lights(gt)
    if sky is None or "time_b" not in lights:
        raise SystemExit("%s: no shsun emitter or no time-B light to relight with" % fit)
    R = gt_alignment(frames, positions, gt)
    cols = {k: [] for k in ("fit_a", "true_a", "fit_b", "true_b", "mesh", "albedo", "vis_true_b",
                            "vis_fit_b")}
    gt_scene = mi.load_file(str(gt / "scene_time_b.xml"))
    cams = json.loads((gt / "trajectory.json").read_text())["world_from_cam"]
    sun_b = np.asarray(lights["time_b"]["sun_direction"], np.float64)
    own = integrator_like(scene, None)
    for k in positions:
        sensor, _ = set_frame(scene, frames, k)
        n = source_number(frames[k])
        cols["fit_a"].append(render_camera(scene, sensor, spp, own)["rgb"].reshape(-1, 3))
        cols["true_a"].append(truth_image(gt / "time_a" / ("%06d.exr" % n)).reshape(-1, 3))
        cols["true_b"].append(truth_image(gt / "time_b" / ("%06d.exr" % n)).reshape(-1, 3))
        mesh = read_map(str(gt / "maps" / ("%06d_mesh_id.exr" % n)))
        cols["mesh"].append((mesh[..., 0] if mesh.ndim == 3 else mesh).reshape(-1).astype(int))
        vt, vf = sun_reach(scene, gt_scene, frames, k, gt, cams, sun_b, R)
        cols["vis_true_b"].append(vt)
        cols["vis_fit_b"].append(vf)
        cols["albedo"].append(read_map(str(gt / "maps" / ("%06d_albedo.exr" % n))).reshape(-1, 3))
    swap = SkySwap(sky)
    traced = integrator_like(scene, None, "trace")
    # The fit's own light with the sun's shadows traced: what the learned
    # visibility field alone changes.
    cols["fit_ot"] = []
    for k in positions:
        sensor, _ = set_frame(scene, frames, k)
        cols["fit_ot"].append(render_camera(scene, sensor, spp, traced)["rgb"].reshape(-1, 3))
    ratios = edit_ratios(lights, gt / "lights.json")
    if ratios is None:
        raise SystemExit("%s: lights.json lacks time A's or time B's levels" % gt)
    direction_b = R @ np.asarray(lights["time_b"].get("sun_direction", [0, 0, 1]), np.float64)
    try:
        for key in ("fit_at", "fit_b", "fit_be"):
            if key == "fit_be":
                # Edits the fitted light SkySwap saved, not the one set last.
                swap.edit(ratios[0], direction_b, ratios[1])
            else:
                swap.put(lights["time_a" if key == "fit_at" else "time_b"], R)
            cols[key] = []
            for k in positions:
                sensor, _ = set_frame(scene, frames, k)
                cols[key].append(render_camera(scene, sensor, spp, traced)["rgb"].reshape(-1, 3))
    finally:
        swap.restore()
    names = {d["mesh_id"]: d["name"] for d in json.loads((gt / "materials.json").read_text())["meshes"]}
    names[-1] = "sky"
    return {k: np.concatenate(v) for k, v in cols.items()}, names


def psnr(fit, true):
    """PSNR of sRGB [0, 1] images, as ``eval`` scores them (pooled MSE)."""
    a = np.clip(M.linear_to_srgb(fit), 0.0, 1.0)
    b = np.clip(M.linear_to_srgb(true), 0.0, 1.0)
    return 10.0 * np.log10(1.0 / max(float(np.mean((a - b) ** 2)), 1e-12))


def report(fit_dir, data, names):
    label = np.array([names.get(int(i), str(i)) for i in data["mesh"]])
    print("\n%s: %d pixels" % (fit_dir, len(label)))
    print("| light | PSNR [dB] | best scale per channel | PSNR after the scale [dB] |")
    print("|---|---|---|---|")
    for tag, f, t in (("own (time A)", data["fit_a"], data["true_a"]),
                      ("own, sun's shadows traced", data["fit_ot"], data["true_a"]),
                      ("time A relit (true light, traced sun)", data["fit_at"], data["true_a"]),
                      ("time B (relit)", data["fit_b"], data["true_b"]),
                      ("time B from the fitted light", data["fit_be"], data["true_b"])):
        s = np.sum(f * t, 0) / np.maximum(np.sum(f * f, 0), 1e-12)
        print("| %s | %.2f | %s | %.2f |" % (tag, psnr(f, t), " ".join("%.3f" % v for v in s),
                                             psnr(f * s, t)))
    print("| material | pixels | A: error share | A: fitted/true | A traced: error share "
          "| A traced: fitted/true | A relit: error share | A relit: fitted/true "
          "| B: error share | B: fitted/true | B edited: error share | B edited: fitted/true |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    err = {}
    tags = ("a", "ot", "at", "b", "be")
    truth = {"a": "true_a", "ot": "true_a", "at": "true_a", "b": "true_b", "be": "true_b"}
    for tag in tags:
        a = np.clip(M.linear_to_srgb(data["fit_" + tag]), 0.0, 1.0)
        b = np.clip(M.linear_to_srgb(data[truth[tag]]), 0.0, 1.0)
        err[tag] = np.sum((a - b) ** 2, 1)
    kinds = sorted(set(label), key=lambda n: -np.sum(err["b"][label == n]))
    small = [n for n in kinds if np.mean(label == n) < MIN_SHARE]
    for name in [n for n in kinds if n not in small] + (["other"] if small else []):
        sel = np.isin(label, small) if name == "other" else label == name
        cells = []
        for tag in tags:
            ratio = (np.mean(data["fit_" + tag][sel] @ LUMINANCE)
                     / max(np.mean(data[truth[tag]][sel] @ LUMINANCE), 1e-12))
            cells.append("%.3f | %.2f" % (err[tag][sel].sum() / err[tag].sum(), ratio))
        print("| %s | %.3f | %s |" % (name, sel.mean(), " | ".join(cells)))
    vt, vf = data["vis_true_b"], data["vis_fit_b"]
    scored = np.isfinite(vt) & (label != "moving_car")
    print("| material | time-B sun reaches (truth) | (fit) | fit lit where the truth is shadowed "
          "| fit shadowed where the truth is lit |")
    print("|---|---|---|---|---|")
    for name in [n for n in kinds if n not in small and n not in ("sky", "moving_car")] + ["all"]:
        sel = scored & ((label == name) if name != "all" else True)
        if not sel.any():
            continue
        t, f = vt[sel] > 0.5, vf[sel] > 0.5
        print("| %s | %.3f | %.3f | %.3f | %.3f |" % (name, t.mean(), f.mean(), np.mean(f & ~t),
                                                      np.mean(~f & t)))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("fits", nargs="+", help="fitted scene folders (fit/)")
    ap.add_argument("--frames", default="held-out", help="frame selection as in eval (default held-out)")
    ap.add_argument("--save", help="also write the per-pixel columns to this .npz (one fit)")
    ap.add_argument("--spp", type=int, default=EVAL_SPP,
                    help="camera samples per pixel (default: eval's, %d)" % EVAL_SPP)
    args = ap.parse_args()
    refuse_existing(args.save)
    for fit in args.fits:
        data, names = collect(fit, args.frames, args.spp)
        report(fit, data, names)
        if args.save:
            np.savez_compressed(args.save, **data)


if __name__ == "__main__":
    main()
