"""The albedo and normal errors' floors on a fitted street's geometry: the
per-Gaussian albedo (or normal) that matches the truth's maps best, by least
squares through the fitted scene's own pixel hit lists (synthetic street).

    python tests/bench/albedo_floor.py FIT_DIR [--map albedo|normal] [--grid 2] [--write] [--json OUT]

``eval``'s albedo map of a pixel is the fitted Gaussians' albedo blended
with their weights along the pixel's rays and divided by the pixel's
opacity: linear in the albedo, with weights the geometry alone sets. So the
albedo that scores best on a set of frames is a linear least-squares
problem. Each frame is traced once at a ``--grid`` x ``--grid`` stratified
set of positions per pixel (``freeze_pixels``, the box filter ``eval``
renders with), its objects placed at the frame's pose, and every Gaussian's
albedo, the moving objects' included, is solved for (CGLS from the fitted
albedo, per channel) against the truth's albedo maps on the pixels ``eval``
scores (a true surface, opacity above ``ALPHA_MIN``). Printed, as ``eval``
scores the held-out frames (per-channel scale fit, mean over frames):

- ``fitted``: the fit's own albedo through the same hit lists (checks the
  hit-list score against ``eval``'s number);
- ``solved on training``: the best albedo for the training and validation
  frames, clipped to [0, 1], scored on the held-out frames (what a perfect
  material fit from the frames the fit sees reaches on this geometry);
- ``solved on held-out``: the best albedo for the held-out frames
  themselves, unclipped: the floor (to the solver's convergence). No
  albedo on this geometry scores lower; where it is above a target, the
  geometry, not the materials, holds the target.

Per truth material, the share of the floor's squared error says which
surfaces the geometry cannot draw. With ``--write`` the training-solved
albedo is written beside the fit (``FIT_DIR_albedo_floor``; background and
object clouds) for ``mi-invrgbl eval`` to score; an existing folder of that
name is left alone and the run stops.

``--map normal`` does the same for the normal map, whose pixels blend the
Gaussians' unit world normals the same way: the background's normals are
solved for (the moving objects' turn with their poses and are kept), the
score is ``eval``'s mean angle to the truth's normal in degrees, and the
solve (:func:`descend_normals`) descends on the angle's stand-in with every
normal kept unit length, as the shape keeps them. The angle is not convex
in the normals, so the held-out solve is the lowest this solver finds, not
a proven floor; the training solve is a set of normals the geometry can
carry and its held-out score is reached.
"""

import sys as _sys, pathlib as _pathlib
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parents[1]))
import variant_choice  # noqa: E402  (--variant NAME, default $MI_INVRGBL_VARIANT or llvm_ad_rgb)
variant_choice.from_argv()

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import time  # noqa: E402
import types  # noqa: E402

import numpy as np  # noqa: E402
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

import mi_invrgbl  # noqa: E402,F401
from mi_invrgbl.eval.ground_truth import ALPHA_MIN, source_number  # noqa: E402
from mi_invrgbl.eval import metrics as M  # noqa: E402
from mi_invrgbl.fit.render import freeze_pixels  # noqa: E402
from mi_invrgbl.physics import hits as hitlib  # noqa: E402
from mi_invrgbl.scene.posing import set_frame  # noqa: E402
from street_truth import open_fit, truth_map, truth_to_scene  # noqa: E402
from normal_oracle import variant_folder, write_edited  # noqa: E402

NAMES = {"albedo": "albedo floor", "normal": "normal floor"}


class Rows:
    """One frame's scored pixels as rows of a sparse system: pixel ``p``'s
    value (albedo, or normal) is ``sum(val[rows == p] * x[col[rows == p]])``
    over the Gaussians solved for, plus ``fixed[p]`` from the others."""

    def __init__(self, rows, cols, vals, target, mask, material, fixed=None, kind="albedo"):
        self.rows, self.cols, self.vals = rows, cols, vals
        self.target = target          # (n, 3) truth's map on the scored pixels
        self.mask = mask              # (H, W) scored pixels
        self.material = material      # (n,) truth mesh id of each scored pixel
        #: (n, 3) what the hits of Gaussians not solved for add (or None).
        self.fixed = fixed
        self.kind = kind

    def apply(self, x, fixed=True):
        """The (n, 3) rendered map of the scored pixels (``fixed``: with the
        contribution of the Gaussians not solved for)."""
        n = len(self.target)
        out = np.stack([np.bincount(self.rows, self.vals * x[self.cols, c], minlength=n)
                        for c in range(3)], axis=1)
        return out + self.fixed if fixed and self.fixed is not None else out

    def residual(self, x):
        """What the solved Gaussians have left to explain: target - map."""
        return self.target - self.apply(x)

    def pixel_errors(self, x):
        """Each scored pixel's error: its squared albedo error, or its normal's
        angle in degrees (what ``score`` sums, as shares go)."""
        pred = self.apply(x)
        if self.kind == "normal":
            cos = np.sum(pred * self.target, axis=1) / np.maximum(
                np.linalg.norm(pred, axis=1) * np.linalg.norm(self.target, axis=1), 1e-12)
            return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
        return np.sum((pred - self.target) ** 2, axis=1)

    def score(self, x):
        """``eval``'s score of this frame: albedo RMSE after the per-channel
        scale fit, or the normals' mean angle in degrees."""
        h, w = self.mask.shape
        pred = np.zeros((h, w, 3))
        truth = np.zeros((h, w, 3))
        pred[self.mask], truth[self.mask] = self.apply(x), self.target
        if self.kind == "normal":
            return M.angular_error_deg(pred, truth, self.mask)
        return M.albedo_rmse_scaled(pred, truth, self.mask)


def frame_rows(scene, frames, k, gt, offsets, grid, kind="albedo", R=np.eye(3)):
    """:class:`Rows` of frame position ``k``: its hit lists merged per pixel,
    weights divided by the pixel's opacity, on the pixels ``eval`` scores.
    ``offsets``: ``{node id: first column}`` of the nodes solved for; the
    other nodes' hits add their current normals (``kind`` normal) to
    ``Rows.fixed``. ``R`` turns the truth's normals into the scene's."""
    sensor, _ = set_frame(scene, frames, k)
    w, h = (int(v) for v in sensor.film().crop_size())
    fh = freeze_pixels(scene, types.SimpleNamespace(sensor=sensor, width=w, height=h, rays=None),
                       grid=grid)
    ray, node, prim, weight = (np.array(a) for a in (fh.ray, fh.node_ids, fh.prims, fh.weight))
    keep = node != 0
    ray, node, prim, weight = ray[keep], node[keep], prim[keep], weight[keep].astype(np.float64)
    alpha = np.bincount(ray, weight, minlength=w * h)
    number = source_number(frames[k])
    mesh = truth_map(gt, "mesh_id", number)
    mesh = (mesh[..., 0] if mesh.ndim == 3 else mesh).ravel()
    mask = (mesh >= 0) & (alpha > ALPHA_MIN)
    row_of = np.full(w * h, -1, np.int64)
    row_of[mask] = np.arange(mask.sum())
    solved = np.isin(node, list(offsets))
    on = mask[ray] & solved
    col = prim[on].astype(np.int64)
    for node_id, first in offsets.items():          # a few nodes, a million hits: by node
        col[node[on] == node_id] += first
    target = truth_map(gt, kind, number).reshape(-1, 3)[mask].astype(np.float64)
    fixed = None
    if kind == "normal":
        target = target @ np.asarray(R, np.float64).T
        other = mask[ray] & ~solved
        fixed = np.zeros((int(mask.sum()), 3))
        for node_ in hitlib.gaussian_nodes(scene):      # world normals at this frame's pose
            hit = other & (node == node_.id)
            if hit.any():
                n = np.array(node_.attributes["normal"], np.float64).reshape(-1, 3)[prim[hit]]
                share = (weight[hit] / alpha[ray[hit]])[:, None]
                for c in range(3):
                    fixed[:, c] += np.bincount(row_of[ray[hit]], share[:, 0] * n[:, c],
                                               minlength=len(fixed))
    return Rows(row_of[ray[on]], col, weight[on] / alpha[ray[on]], target, mask.reshape(h, w),
                np.rint(mesh[mask]).astype(np.int64), fixed, kind)


def cgls(frames_rows, x0, iterations):
    """Least squares ``min |A x - b|`` over every frame's rows (all channels
    at once), from ``x0``: conjugate gradients on the normal equations.
    Columns no row touches keep ``x0``."""
    n = len(x0)

    def A(x):
        return [r.apply(x, fixed=False) for r in frames_rows]

    def At(res):
        return np.stack([sum(np.bincount(r.cols, r.vals * q[r.rows, c], minlength=n)
                             for r, q in zip(frames_rows, res)) for c in range(3)], axis=1)

    x = x0.astype(np.float64).copy()
    res = [r.residual(x) for r in frames_rows]
    s = At(res)
    p, gamma = s.copy(), np.sum(s * s, axis=0)
    for _ in range(iterations):
        q = A(p)
        qq = sum(np.sum(v * v, axis=0) for v in q)
        step = gamma / np.maximum(qq, 1e-30)
        x += step * p
        res = [r - step * v for r, v in zip(res, q)]
        s = At(res)
        new = np.sum(s * s, axis=0)
        p = s + (new / np.maximum(gamma, 1e-30)) * p
        gamma = new
    return x


def descend_normals(frames_rows, x0, steps, rate):
    """Unit normals whose blends point along the truth's: Adam on the mean of
    ``1 - cos`` between each pixel's blend and the truth's normal (the
    angle's smooth stand-in; a least-squares fit of the vectors themselves
    would weigh a blend's length, which the angle does not see), the
    gradient kept tangent to each normal's sphere and the normal made unit
    length after every step."""
    x = unit(np.asarray(x0, np.float64))
    n = len(x)
    m, v = np.zeros_like(x), np.zeros_like(x)
    truth = [unit(r.target) for r in frames_rows]
    for it in range(1, steps + 1):
        grad = np.zeros_like(x)
        for r, t in zip(frames_rows, truth):
            p = r.apply(x)
            length = np.maximum(np.linalg.norm(p, axis=1, keepdims=True), 1e-9)
            ph = p / length
            dp = -(t - np.sum(ph * t, axis=1, keepdims=True) * ph) / length   # d(1 - cos)/dp
            for c in range(3):
                grad[:, c] += np.bincount(r.cols, r.vals * dp[r.rows, c], minlength=n)
        grad -= np.sum(grad * x, axis=1, keepdims=True) * x
        m = 0.9 * m + 0.1 * grad
        v = 0.999 * v + 0.001 * grad * grad
        step = (m / (1 - 0.9 ** it)) / (np.sqrt(v / (1 - 0.999 ** it)) + 1e-12)
        x = unit(x - rate * step)
    return x


def unit(x):
    """Each row made unit length, as the shape does with its normals on loading."""
    return x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)


def by_material(rows, positions, x, names):
    """``{truth material: share}`` of the summed pixel errors of ``x`` over
    frame positions ``positions`` (the buildings' materials as one); an
    albedo is first scaled per channel to the truth's level, as scored."""
    if rows[positions[0]].kind == "albedo":
        pred = np.concatenate([rows[k].apply(x) for k in positions])
        truth = np.concatenate([rows[k].target for k in positions])
        x = x * (np.sum(pred * truth, axis=0) / np.maximum(np.sum(pred * pred, axis=0), 1e-12))
    err = np.concatenate([rows[k].pixel_errors(x) for k in positions])
    mat = np.concatenate([rows[k].material for k in positions])
    by = {}
    for m in np.unique(mat):
        label = names.get(int(m), str(m))
        label = "building" if label.startswith("building_") else label
        by[label] = by.get(label, 0.0) + float(err[mat == m].sum())
    total = max(sum(by.values()), 1e-30)
    return {n: v / total for n, v in sorted(by.items(), key=lambda kv: -kv[1])}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("fit", help="fitted scene folder (fit/)")
    ap.add_argument("--map", choices=("albedo", "normal"), default="albedo", help="which map to solve for")
    ap.add_argument("--grid", type=int, default=2, help="rays per pixel side (eval's box filter)")
    ap.add_argument("--iterations", type=int, default=80, help="albedo: CGLS iterations per solve")
    ap.add_argument("--steps", type=int, default=300, help="normals: Adam steps per solve")
    ap.add_argument("--rate", type=float, default=0.01, help="normals: Adam's step size")
    ap.add_argument("--write", action="store_true",
                    help="write the training-solved map beside the fit (for eval)")
    ap.add_argument("--json", help="also write the scores and shares to this file")
    args = ap.parse_args()
    kind, name = args.map, NAMES[args.map]
    if args.write and os.path.exists(variant_folder(args.fit, name)):
        raise SystemExit("%s: exists; not overwritten" % variant_folder(args.fit, name))
    t0 = time.time()
    frames, gt, held, scene = open_fit(args.fit, "held-out")
    seen = [k for k in range(len(frames)) if k not in held]
    # Albedo: every node is solved for. Normals: the background only (the
    # moving objects' world normals change with their pose).
    nodes = [n for n in hitlib.gaussian_nodes(scene)
             if kind == "albedo" or n.shape.id() == "background"]
    offsets, start = {}, 0
    for node in nodes:
        offsets[node.id] = start
        start += node.count
    fitted = np.concatenate([np.array(node.attributes[kind], np.float64).reshape(-1, 3)
                             for node in nodes])
    R = truth_to_scene(gt, frames[held[0]])[:3, :3]
    rows = {k: frame_rows(scene, frames, k, gt, offsets, args.grid, kind, R) for k in seen + held}
    print("%s: %d Gaussians' %s solved for (%s); %d training/validation and %d held-out frames "
          "traced at %dx%d rays per pixel (%.0f s)"
          % (args.fit, start, kind, ", ".join(n.shape.id() for n in nodes), len(seen), len(held),
             args.grid, args.grid, time.time() - t0))

    def held_out_score(x):
        return float(np.mean([rows[k].score(x) for k in held]))

    if kind == "normal":
        solved_seen = descend_normals([rows[k] for k in seen], fitted, args.steps, args.rate)
        floor = descend_normals([rows[k] for k in held], fitted, args.steps, args.rate)
        table = {"fitted": held_out_score(fitted),
                 "solved on training (unit normals)": held_out_score(solved_seen),
                 "solved on held-out (unit normals)": held_out_score(floor)}
    else:
        # What a Gaussian can hold: albedo in [0, 1].
        solved_seen = np.clip(cgls([rows[k] for k in seen], fitted, args.iterations), 0.0, 1.0)
        floor = cgls([rows[k] for k in held], fitted, args.iterations)
        table = {"fitted": held_out_score(fitted),
                 "solved on training, clipped to [0, 1]": held_out_score(solved_seen),
                 "solved on held-out": held_out_score(floor),
                 "solved on held-out, clipped to [0, 1]": held_out_score(np.clip(floor, 0.0, 1.0))}
    unit_name = "mean angle [deg]" if kind == "normal" else "RMSE"
    print("| %s | held-out %s %s |\n|---|---|" % (kind, kind, unit_name))
    for label, value in table.items():
        print("| %s | %.4f |" % (label, value))
    names = {d["mesh_id"]: d.get("material", d.get("name"))
             for d in json.loads((gt / "materials.json").read_text())["meshes"]}
    shares = {}
    for label, x in (("fitted", fitted), ("held-out solution", floor)):
        shares[label] = by_material(rows, held, x, names)
        print("the %s's %s by truth material: %s" % (
            label, "angle" if kind == "normal" else "squared error",
            ", ".join("%s %.0f %%" % (n, 100 * v) for n, v in shares[label].items())))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"fit": args.fit, "map": kind, "grid": args.grid, "gaussians": start,
                       "frames_solved": [frames[k].index for k in seen],
                       "held_out": [frames[k].index for k in held], "held_out_scores": table,
                       "shares_by_material": shares}, f, indent=1)
    print("(%.0f s)" % (time.time() - t0))
    if args.write:
        field = "normals" if kind == "normal" else "albedo"

        def edit_for(node):
            part = solved_seen[offsets[node.id]:offsets[node.id] + node.count].astype(np.float32)

            def edit(cloud):
                setattr(cloud, field, part)
            return edit
        print("wrote %s" % write_edited(args.fit, name, {
            "%s.ply" % n.shape.id(): edit_for(n) for n in nodes}))


if __name__ == "__main__":
    main()
