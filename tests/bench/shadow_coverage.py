"""How much of the true sun shadow a fitted scene models as shadow (synthetic street).

    python tests/bench/shadow_coverage.py out/street_fit3 fit_full [fit_other ...]

For every 4th training frame, the sun visibility each fitted Gaussian gets
(the stored ``sun_visibility`` field when the fitted scene.xml says
``sun_visibility = attribute``, else traced to the fitted sun) is blended
along the camera rays and compared, on ground pixels (ground-truth normal
within 25 degrees of up), with the ground truth's ``sun_visibility`` map.
Prints the share of truly shadowed pixels modelled as sunlit (>= 0.5) and of
truly sunlit pixels modelled as shadowed.
"""

import sys as _sys, pathlib as _pathlib
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parents[1]))
import variant_choice  # noqa: E402  (--variant NAME, default $MI_INVRGBL_VARIANT or llvm_ad_rgb)
variant_choice.from_argv()

import os
import sys

import numpy as np
import cv2
import mitsuba as mi

from street_truth import ground_truth, source_number, truth_map
import drjit as dr  # noqa: E402
import mi_invrgbl  # noqa: E402,F401
from mi_invrgbl.physics import hits as hitlib  # noqa: E402
from mi_invrgbl.physics.lighting import GaussianLighting, LightingCache  # noqa: E402



def blended_visibility(scene, sensor, nodes, per_gaussian, table):
    W, H = sensor.film().size()
    y, x = np.mgrid[0:H, 0:W]
    uv = mi.Point2f(((x.ravel() + 0.5) / W).astype(np.float32), ((y.ravel() + 0.5) / H).astype(np.float32))
    rays, _ = sensor.sample_ray(0.0, 0.5, uv, mi.Point2f(0.5))
    hl = hitlib.trace(scene, rays, 32, 1e-2, nodes)
    g = hitlib.eval_gaussian_hits(nodes, rays, hl)
    w, _ = hitlib.blend_weights(g)
    if per_gaussian is None:
        v = hitlib.gather_attribute(nodes, "sun_visibility", g.node_ids, g.prims, g.active)
    else:
        v = dr.gather(mi.Float, per_gaussian, table.global_index(g.node_ids, g.prims), g.active)
    vis = np.array(hitlib.composite(g, w, v)).reshape(H, W)
    alpha = np.array(hitlib.composite(g, w, mi.Float(1.0))).reshape(H, W)
    return vis / np.maximum(alpha, 1e-3), alpha


def coverage(root, variant, meta, gt):
    path = os.path.join(root, variant, "scene.xml")
    stored = 'name="sun_visibility" value="attribute"' in open(path).read()
    scene = mi.load_file(path)
    nodes = hitlib.gaussian_nodes(scene)
    lighting = GaussianLighting(scene, nodes, 1, LightingCache(), trace_sun=not stored)
    traced = None if stored else lighting.cache.light_visibility[0]
    sensors = {s.id(): s for s in scene.sensors()}
    counts = np.zeros((2, 2))
    for f in meta["frames"][::4]:
        if f.get("held_out"):
            continue
        i = f["index"]
        n = source_number(f)
        vmap, alpha = blended_visibility(scene, sensors["camera_%04d" % i], nodes, traced, lighting.table)
        truth = truth_map(gt, "sun_visibility", n)
        normal = truth_map(gt, "normal", n)[..., :3]
        if truth.shape != vmap.shape:
            vmap = cv2.resize(vmap, truth.shape[::-1], interpolation=cv2.INTER_NEAREST)
            alpha = cv2.resize(alpha, truth.shape[::-1])
        ground = (normal[..., 2] > np.cos(np.radians(25))) & (alpha > 0.5)
        for row, mask in enumerate((truth < 0.5, truth >= 0.5)):
            m = ground & mask
            counts[row] += [(vmap[m] < 0.5).sum(), (vmap[m] >= 0.5).sum()]
    return stored, counts[0, 1] / max(counts[0].sum(), 1), counts[1, 0] / max(counts[1].sum(), 1)


def main():
    root = sys.argv[1]
    variants = sys.argv[2:] or sorted(d for d in os.listdir(root) if d.startswith("fit"))
    meta, gt = ground_truth(root)
    print("| fit | sun visibility | true shadow modelled sunlit | true sun modelled shadowed |")
    print("|---|---|---|---|")
    for v in variants:
        stored, missed, invented = coverage(root, v, meta, gt)
        print("| %s | %s | %.0f %% | %.0f %% |" % (v, "stored (learned)" if stored else "traced",
                                                   100 * missed, 100 * invented))


if __name__ == "__main__":
    main()
