"""How much sky each surface sees through the fitted Gaussians, against the truth (synthetic street).

    python tests/bench/sky_view.py FIT_DIR [FIT_DIR ...] [--frames held-out] [--directions 32] [--json OUT]

A surface out of the sun is lit by the sky it sees (and by what the
surfaces around it reflect). Under the truth's light the fitted street
draws its never-sunlit walls 1.4-2x too bright (``relight_breakdown.py``),
with the albedo right or not. This bench measures the sky half of that,
with the truth's own surface points and normals so that neither the
fitted normals nor the fitted albedo enter: for every pixel of the
selected frames where the truth sees a surface, ``--directions``
cosine-weighted directions about the true normal (the integrator's
Fibonacci set, turned at random per pixel) leave SHADOW_OFFSET above the true surface point, as the
integrator's shadow rays leave a Gaussian, and are traced through the
truth's meshes (open or blocked) and through the fitted Gaussians
(their transmittance). The mean over the directions is the share of the
sky's cosine-weighted irradiance that reaches the point: its *sky view*.

Printed per true material (pixel share, the truth's sky view, the fit's,
their ratio), then where the directions disagree: the share of the
truth's blocked directions the fit leaves open, and the height (world z
above the camera) and distance of what blocks them in the truth, split
by whether that blocker is within the vertical field of view of some
training camera (its image could have shown it) or above every one.
"""

import sys as _sys, pathlib as _pathlib
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parents[1]))
import variant_choice  # noqa: E402  (--variant NAME, default $MI_INVRGBL_VARIANT or llvm_ad_rgb)
variant_choice.from_argv()

import argparse  # noqa: E402
import json  # noqa: E402

import numpy as np  # noqa: E402
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

import mi_invrgbl  # noqa: E402,F401
from mi_invrgbl.eval.ground_truth import gt_alignment, source_number  # noqa: E402
from mi_invrgbl.eval.inputs import read_map  # noqa: E402
from mi_invrgbl.physics import hits as hitlib  # noqa: E402
from mi_invrgbl.physics.lighting import SHADOW_OFFSET, fibonacci_direction, transmittance  # noqa: E402
from street_truth import open_fit, refuse_existing, scene_from_truth, write_json  # noqa: E402
from relight_breakdown import MIN_SHARE, true_surface, vector3f  # noqa: E402


def cosine_directions(count):
    """The integrator's ``count`` cosine-weighted Fibonacci directions about +z, unturned."""
    local = fibonacci_direction(dr.arange(mi.Float, count), count, mi.Float(0.0))
    return np.array(local, np.float64).T     # (3, count) -> (count, 3)


def frames_to_world(normal, turn):
    """Per-point orthonormal frames whose z is ``normal``, turned by ``turn`` about it."""
    helper = np.where(np.abs(normal[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    t = np.cross(helper, normal)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    b = np.cross(normal, t)
    c, s = np.cos(turn)[:, None], np.sin(turn)[:, None]
    return c * t + s * b, -s * t + c * b


def training_cameras(frames, cams):
    """The training cameras' (centre, forward, up) in the truth's world."""
    out = []
    for rec in frames.frames:
        if rec.held_out:
            continue
        T = np.linalg.inv(scene_from_truth(rec, cams))
        c2w = np.asarray(rec.camera_to_world, np.float64)
        centre = c2w[:3, 3] @ T[:3, :3].T + T[:3, 3]
        fwd = T[:3, :3] @ c2w[:3, 2]
        down = T[:3, :3] @ c2w[:3, 1]
        out.append((centre, fwd, -down))
    return out


def seen_vertically(points, cams, tan_half):
    """True where some training camera's vertical field reaches the point (in front, not above the top row)."""
    seen = np.zeros(len(points), bool)
    for centre, fwd, up in cams:
        v = points - centre
        z = v @ fwd
        seen |= (z > 0) & (v @ up <= tan_half * np.maximum(z, 1e-9))
    return seen


def collect(fit, frames_spec, count):
    frames, gt, positions, scene = open_fit(fit, frames_spec)
    R = gt_alignment(frames, positions, gt)
    gt_scene = mi.load_file(str(gt / "scene_time_b.xml"))
    cams = json.loads((gt / "trajectory.json").read_text())["world_from_cam"]
    names = {d["mesh_id"]: d["name"] for d in json.loads((gt / "materials.json").read_text())["meshes"]}
    local = cosine_directions(count)
    rng = np.random.default_rng(0)
    nodes = hitlib.gaussian_nodes(scene)
    cols = {k: [] for k in ("mesh", "true", "fit", "missed_height", "missed_distance", "missed_seen")}
    cameras = training_cameras(frames, cams)
    # The vertical half field above the axis, from the intrinsics (any resolution).
    tan_half = float(frames.camera.cy) / float(frames.camera.fy)
    for k in positions:
        n = source_number(frames[k])
        hit, p_fit, p_gt, normal, T = true_surface(scene, frames, k, gt, cams)
        normal = normal.astype(np.float64)
        mesh = read_map(str(gt / "maps" / ("%06d_mesh_id.exr" % n)))
        mesh = (mesh[..., 0] if mesh.ndim == 3 else mesh).reshape(-1).astype(int)
        keep = hit & (np.linalg.norm(normal, axis=1) > 0.5)
        p_fit, p_gt = p_fit[keep], p_gt[keep]
        cam = np.asarray(frames[k].camera_to_world, np.float64)
        nrm = normal[keep] / np.linalg.norm(normal[keep], axis=1, keepdims=True)
        tu, tv = frames_to_world(nrm, rng.uniform(0, 2 * np.pi, len(nrm)))
        o_gt = p_gt + SHADOW_OFFSET * nrm
        o_fit = p_fit + SHADOW_OFFSET * nrm @ R.T
        cam_z = (cam[:3, 3] @ T[:3, :3].T + T[:3, 3])[2]
        true_sum, fit_sum = np.zeros(len(nrm)), np.zeros(len(nrm))
        for a, b, c in local:
            dirs = a * tu + b * tv + c * nrm
            blocked = gt_scene.ray_intersect(mi.Ray3f(vector3f(o_gt), vector3f(dirs)))
            t_hit = np.array(blocked.t, np.float64)
            hit = np.isfinite(t_hit) & np.array(blocked.is_valid(), bool)
            true_sum += ~hit
            vis = np.clip(np.array(transmittance(scene, vector3f(o_fit), vector3f(dirs @ R.T),
                                                 mi.Float(dr.inf), nodes), np.float64), 0.0, 1.0)
            fit_sum += vis
            missed = hit & (vis > 0.5)
            where = o_gt[missed] + dirs[missed] * t_hit[missed][:, None]
            cols["missed_height"].append(where[:, 2] - cam_z)
            cols["missed_distance"].append(t_hit[missed])
            cols["missed_seen"].append(seen_vertically(where, cameras, tan_half))
        cols["mesh"].append(mesh[keep])
        cols["true"].append(true_sum / len(local))
        cols["fit"].append(fit_sum / len(local))
    data = {k: np.concatenate(v) for k, v in cols.items()}
    return data, names


def report(fit, data, names, count):
    label = np.array([names.get(int(i), str(i)) for i in data["mesh"]])
    t, f = data["true"], data["fit"]
    print("\n%s: %d surface pixels, %d directions each" % (fit, len(t), count))
    print("| material | pixels | sky view, truth | sky view, fit | fit / truth |")
    print("|---|---|---|---|---|")
    kinds = sorted(set(label), key=lambda n: -np.mean(label == n))
    small = [n for n in kinds if np.mean(label == n) < MIN_SHARE]
    rows_out = {}
    for name in [n for n in kinds if n not in small] + (["other"] if small else []) + ["all"]:
        sel = np.isin(label, small) if name == "other" else (label == name if name != "all" else
                                                             np.ones(len(label), bool))
        tm, fm = float(t[sel].mean()), float(f[sel].mean())
        rows_out[name] = {"pixels": round(float(sel.mean()), 4), "truth": round(tm, 4), "fit": round(fm, 4)}
        print("| %s | %.3f | %.3f | %.3f | %.2f |" % (name, sel.mean(), tm, fm, fm / max(tm, 1e-9)))
    blocked = np.sum((1.0 - t) * count)
    mh, md, ms = data["missed_height"], data["missed_distance"], data["missed_seen"]
    print("directions the truth blocks and the fit leaves open: %.1f %% of the blocked ones"
          % (100.0 * len(mh) / max(blocked, 1)))
    parts = {}
    for tag, sel in (("within some training camera's vertical field", ms),
                     ("above every training camera's field", ~ms)):
        if not sel.any():
            continue
        q = np.percentile(mh[sel], [10, 50, 90])
        parts[tag] = {"share": round(float(sel.mean()), 4), "height_q10_50_90": np.round(q, 2).tolist(),
                      "distance_median": round(float(np.median(md[sel])), 2)}
        print("  %s: %.0f %% of them; blocker %.1f / %.1f / %.1f m above the camera (10/50/90 %%), "
              "median %.1f m away" % (tag, 100 * sel.mean(), q[0], q[1], q[2], np.median(md[sel])))
    return {"materials": rows_out, "open_in_fit_share": round(float(len(mh) / max(blocked, 1)), 4),
            "missed_blockers": parts}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("fits", nargs="+", help="fitted scene folders (fit/)")
    ap.add_argument("--frames", default="held-out", help="frame selection as in eval (default held-out)")
    ap.add_argument("--directions", type=int, default=32, help="cosine-weighted directions per pixel")
    ap.add_argument("--json", help="write the tables here")
    args = ap.parse_args()
    refuse_existing(args.json)
    record = {}
    for fit in args.fits:
        data, names = collect(fit, args.frames, args.directions)
        record[fit] = report(fit, data, names, args.directions)
    if args.json:
        write_json(args.json, record)


if __name__ == "__main__":
    main()
