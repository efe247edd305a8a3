"""Does a fitted street's surface stand where the truth's does? Per material,
along the true normal (synthetic street).

    python tests/bench/surface_offset.py FIT_DIR [--spp 32]

The fitted scene is rendered on ``eval``'s held-out frames as ``eval``
renders them; per pixel the distance its depth AOV shows (divided by the
alpha, so a blend of the Gaussians the ray meets) minus the truth's along
the same pixel-centre ray, times the cosine between that ray and the true
normal: the offset along the normal, negative where the fitted surface
stands in front of the true one. Pixels at least 90 % covered by the fit
and showing a true surface are scored; per material it prints the median
offset and the shares more than :data:`MARGIN` in front and behind.

Why: ``relight_breakdown.py`` traces the time-B sun from ``SHADOW_OFFSET``
(0.1 m) above each pixel's *true* surface point through the fitted
Gaussians. Where the fitted surface stands further in front, that ray
starts behind it and the fit's own surface shadows it, which ``eval``'s
relighting (traced from above each Gaussian) does not do.
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
from mi_invrgbl.eval.scoring import EVAL_SPP  # noqa: E402
from mi_invrgbl.physics.lighting import SHADOW_OFFSET  # noqa: E402
from mi_invrgbl.scene.posing import set_frame  # noqa: E402
from depth_normals import rendered_and_true  # noqa: E402
from street_truth import open_fit  # noqa: E402

#: Offsets beyond this (m) are counted: the shadow rays' start above a surface.
MARGIN = SHADOW_OFFSET
#: Pixels at least this opaque in the fitted render are scored.
COVERED = 0.9


def offsets(fit, spp):
    """Material name -> offsets along the true normal (m) of its scored pixels."""
    frames, gt, positions, scene = open_fit(fit)
    R = gt_alignment(frames, positions, gt)
    names = {m["mesh_id"]: m["name"] for m in json.loads((gt / "materials.json").read_text())["meshes"]}
    out = {}
    for k in positions:
        sensor, _ = set_frame(scene, frames, k)
        cam, mesh, true_n, d, dist, true_dist = rendered_and_true(
            scene, sensor, gt, source_number(frames[k]), R, spp)
        alpha = cam["alpha"]
        along = (dist - true_dist) * np.abs(np.sum(d * true_n, -1))
        scored = (mesh >= 0) & (alpha > COVERED) & np.isfinite(along)
        for i in np.unique(mesh[scored]):
            out.setdefault(names.get(int(i), str(i)), []).append(along[scored & (mesh == i)])
    return {n: np.concatenate(v) for n, v in out.items()}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("fit", help="a fitted scene folder of the synthetic street")
    ap.add_argument("--spp", type=int, default=EVAL_SPP,
                    help="camera samples per pixel (default: eval's, %d)" % EVAL_SPP)
    args = ap.parse_args(argv)
    rows = offsets(args.fit, args.spp)
    print("| material | pixels | median offset along the normal [m] | in front by > %.2g m | behind by > %.2g m |"
          % (MARGIN, MARGIN))
    print("|---|---|---|---|---|")
    for name, v in sorted(rows.items(), key=lambda kv: -kv[1].size):
        print("| %s | %d | %+.3f | %.2f | %.2f |" % (name, v.size, np.median(v), np.mean(v < -MARGIN),
                                                     np.mean(v > MARGIN)))
    return rows


if __name__ == "__main__":
    main()
