"""What casts the relit sun's shadows that the truth does not have (synthetic street).

    python tests/bench/shadow_blockers.py FIT_DIR [--frames held-out]

For every pixel of the selected frames whose true surface point the truth's
meshes leave open to the time-B sun but the fitted Gaussians shadow
(transmittance below 0.5; shadow rays as in ``relight_breakdown.py``, from
SHADOW_OFFSET above the true surface point), the hit with the largest blend
weight along the fitted shadow ray is its *blocker*. Printed:

- the share of those rays whose blocker stands within 0.25 m, 0.25-1 m and
  1 m or more of any true surface (the distance is the nearest of six
  axis-aligned rays through the truth's ``scene_time_b.xml``), with the
  quantiles of its distance along the shadow ray and of its height;
- of the distinct background Gaussians blocking from 1 m or more off every
  true surface (made-up geometry), the share inside some training camera's
  image (occlusion not considered), the share a training camera sees with
  no true mesh in between, and of those the share that fall on a pixel the
  image's sky mask (``mi_invrgbl.fit.sky_mask``, from the true time-A image
  without LiDAR returns) marks as sky in some frame: what the images could
  have removed, against what no image shows.
"""

import sys as _sys, pathlib as _pathlib
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parents[1]))
import variant_choice  # noqa: E402  (--variant NAME, default $MI_INVRGBL_VARIANT or llvm_ad_rgb)
variant_choice.from_argv()

import argparse  # noqa: E402
import json  # noqa: E402

import numpy as np  # noqa: E402
import mitsuba as mi  # noqa: E402

import relight_breakdown as rb  # noqa: E402
from mi_invrgbl.eval.ground_truth import gt_alignment, load_lights, source_number  # noqa: E402
from mi_invrgbl.fit.sky_mask import PinholeProjection, sky_mask  # noqa: E402
from mi_invrgbl.physics import hits as hitlib  # noqa: E402
from mi_invrgbl.scene.posing import set_frame  # noqa: E402
from mi_invrgbl.synthetic.groundtruth import camera_rays, rows  # noqa: E402
from street_truth import open_fit, scene_from_truth  # noqa: E402


def frame_geometry(scene, frames, k, gt, cams):
    """Camera rays of frame ``k`` and the rigid map from the scene's world into the truth's."""
    rec, n = frames[k], source_number(frames[k])
    sensor, _ = set_frame(scene, frames, k)
    w, h = [int(v) for v in sensor.film().size()]
    ray = camera_rays(sensor, w, h)
    to_gt = np.linalg.inv(scene_from_truth(rec, cams))
    return sensor, (w, h), rows(ray.o), rows(ray.d), to_gt, n


def nearest_surface(gt_scene, points):
    """Per point: distance to the truth's meshes along the nearest of six axis rays."""
    dist = np.full(len(points), np.inf)
    for axis in np.vstack([np.eye(3), -np.eye(3)]):
        si = gt_scene.ray_intersect(mi.Ray3f(rb.vector3f(points), rb.vector3f(np.tile(axis, (len(points), 1)))))
        t = np.array(si.t, np.float64)
        dist = np.minimum(dist, np.where(np.isfinite(t), t, np.inf))
    return dist


def blockers(scene, gt_scene, frames, positions, gt, cams, sun_gt, R):
    """Per wrongly shadowed pixel: (shape id, prim, distance along the ray,
    distance to the truth, height in the truth's world)."""
    nodes = hitlib.gaussian_nodes(scene)
    out = []
    for k in positions:
        r = rb.sun_rays(scene, gt_scene, frames, k, gt, cams, sun_gt, R)
        wrong = np.nonzero(r.hit & r.true_vis & (r.vis < 0.5))[0]
        if wrong.size == 0:
            continue
        org, sun_fit, to_gt = r.origin, r.sun_fit, r.to_gt
        rays = mi.Ray3f(rb.vector3f(org[wrong]), rb.vector3f(np.tile(sun_fit, (wrong.size, 1))))
        g = hitlib.eval_gaussian_hits(nodes, rays, hitlib.trace(scene, rays, 64, 1e-3, nodes))
        weight = np.array(hitlib.blend_weights(g)[0], np.float64)
        ray = np.array(g.ray, np.int64)
        ok = np.array(g.active, bool) & (ray < wrong.size)
        hit = np.nonzero(ok)[0]
        # The strongest hit per ray: sort by (ray, weight), keep each ray's last.
        hit = hit[np.lexsort((weight[hit], ray[hit]))]
        last = np.r_[ray[hit][1:] != ray[hit][:-1], True]
        best = hit[last]
        t = np.array(g.t, np.float64)[best]
        p = org[wrong][ray[best]] + sun_fit * t[:, None]
        p_gt_b = p @ to_gt[:3, :3].T + to_gt[:3, 3]
        out.append(np.stack([np.array(g.node_ids, np.float64)[best], np.array(g.prims, np.float64)[best], t,
                             nearest_surface(gt_scene, p_gt_b), p_gt_b[:, 2]], 1))
    return np.concatenate(out) if out else np.zeros((0, 5))


def seen_by_training(scene, gt_scene, frames, gt, cams, centres):
    """Per centre: (inside some training image, seen with no true mesh in
    between, seen on a sky-mask pixel)."""
    inside = np.zeros(len(centres), bool)
    seen = np.zeros(len(centres), bool)
    on_sky = np.zeros(len(centres), bool)
    for k in frames.train_indices():
        sensor, (w, h), _, d, to_gt, n = frame_geometry(scene, frames, k, gt, cams)
        T = np.array(sensor.world_transform().matrix, np.float64).reshape(4, 4)
        proj = PinholeProjection(T, d, w, h)
        local = (centres - proj.o) @ proj.R
        front = local[:, 2] > 0.1
        z = np.where(front, local[:, 2], 1.0)
        col = proj.cx[0] * local[:, 0] / z + proj.cx[1]
        row = proj.cy[0] * local[:, 1] / z + proj.cy[1]
        here = front & (col >= 0) & (col < w) & (row >= 0) & (row < h)
        inside |= here
        o_gt = to_gt[:3, :3] @ proj.o + to_gt[:3, 3]
        v = centres @ to_gt[:3, :3].T + to_gt[:3, 3] - o_gt
        dist = np.linalg.norm(v, axis=1)
        ray = mi.Ray3f(rb.vector3f(np.tile(o_gt, (len(centres), 1))), rb.vector3f(v / dist[:, None]),
                       mi.Float(np.maximum(dist - 0.3, 0.0).astype(np.float32)))
        clear = here & ~np.array(gt_scene.ray_test(ray), bool)
        seen |= clear
        mask = sky_mask(rb.truth_image(gt / "time_a" / ("%06d.exr" % n)), proj)
        on_sky |= clear & mask[np.clip(row.astype(int), 0, h - 1), np.clip(col.astype(int), 0, w - 1)]
    return inside, seen, on_sky


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("fit", help="a fitted scene folder (fit/)")
    ap.add_argument("--frames", default="held-out", help="frame selection as in eval (default held-out)")
    args = ap.parse_args()
    frames, gt, positions, scene = open_fit(args.fit, args.frames)
    lights = load_lights(gt)
    R = gt_alignment(frames, positions, gt)
    gt_scene = mi.load_file(str(gt / "scene_time_b.xml"))
    cams = json.loads((gt / "trajectory.json").read_text())["world_from_cam"]
    sun_gt = np.asarray(lights["time_b"]["sun_direction"], np.float64)
    b = blockers(scene, gt_scene, frames, positions, gt, cams, sun_gt, R)
    print("%s: %d pixels the truth lights and the fit shadows, with a blocker" % (args.fit, len(b)))
    if not len(b):
        return
    print("| blocker's distance to the truth | share of rays | along the ray [m] (10/50/90 %) | height [m] (10/50/90 %) |")
    print("|---|---|---|---|")
    for lo, hi in ((0.0, 0.25), (0.25, 1.0), (1.0, np.inf)):
        m = (b[:, 3] >= lo) & (b[:, 3] < hi)
        if m.any():
            print("| %g-%g m | %.3f | %s | %s |" % (lo, hi, m.mean(),
                  " / ".join("%.2f" % v for v in np.percentile(b[m, 2], [10, 50, 90])),
                  " / ".join("%.2f" % v for v in np.percentile(b[m, 4], [10, 50, 90]))))
    node = [n for n in hitlib.gaussian_nodes(scene) if n.shape.id() == "background"][0]
    far = np.unique(b[(b[:, 3] >= 1.0) & (b[:, 0] == node.id), 1].astype(np.int64))
    if far.size:
        # The background is static: its stored centres are world positions.
        centres = np.array(node.data, np.float64).reshape(-1, 10)[far, :3]
        inside, seen, on_sky = seen_by_training(scene, gt_scene, frames, gt, cams, centres)
        print("background Gaussians blocking from >= 1 m off the truth: %d; inside a training image "
              "%.3f; seen with no true mesh in between %.3f; of those on a sky-mask pixel %.3f"
              % (far.size, inside.mean(), seen.mean(), on_sky[seen].mean() if seen.any() else 0.0))


if __name__ == "__main__":
    main()
