"""How far the lighting selection's sun lands from the truth (synthetic street).

    python tests/bench/sun_search.py SCENE [--budget 8] [--draws 4] [--json OUT.json]
                                     [fit options, e.g. --diffuse-fresnel]

Runs ``mi-invrgbl fit SCENE --budget B`` into a temporary folder up to the
lighting selection after stage 1 and there, instead of one search on one
random draw of the seen Gaussians (``FitConfig.sun_gaussians``), searches
the sun on ``--draws`` draws of that many, and on all of them: each search
as the fit makes it (``selection.select_sun``: 48 directions through the
Gaussians, the best refined) and, where it uses or tries the sun,
sharpened as ``fit --sharpen-sun`` does (``selection.sharpen_sun``: a scan of many directions through a share of
the Gaussians, its best peaks refined through all). Prints per search the
angle to the truth's time-A sun and the gain (share of the within-surface
shading explained) before and after sharpening, the alternatives' angles
and the seconds each part took. Stage 1 runs once; the differences are
the draws' and the search's. The fit stops there: nothing is written but
the JSON asked for.
"""

import sys as _sys, pathlib as _pathlib
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parents[1]))
import variant_choice  # noqa: E402  (--variant NAME, default $MI_INVRGBL_VARIANT or llvm_ad_rgb)
variant_choice.from_argv()

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from mi_invrgbl.physics.directions import angle_deg  # noqa: E402


class Recorded(Exception):
    """Ends the fit once the searches are recorded."""


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--budget", default="8")
    ap.add_argument("--draws", type=int, default=4)
    ap.add_argument("--json")
    args, fit_options = ap.parse_known_args()      # (variant_choice took --variant out)

    from mi_invrgbl import cli
    from mi_invrgbl.eval.ground_truth import gt_alignment, load_lights
    from mi_invrgbl.fit import model_selection, runner, selection
    from mi_invrgbl.scene.frames import Frames

    frames = Frames.load(args.scene)
    if not frames.ground_truth:
        _sys.exit("%s: frames.json names no ground truth" % args.scene)
    R = gt_alignment(frames, range(len(frames)), frames.ground_truth)
    truth = R @ np.asarray(load_lights(frames.ground_truth)["time_a"]["sun_direction"], np.float64)
    rows = []
    drawn = {}

    def search(scene, centers, normals, lum, wts, candidates=48, **kw):
        kw["sharpen_gain"] = model_selection.SUN_TRIAL_GAIN     # as fit --sharpen-sun
        G = len(lum)
        n = min(drawn["n"], G)
        rng = np.random.default_rng(0)
        picks = [("all %d" % G, np.arange(G))] + [
            ("draw %d of %d" % (i + 1, n), rng.choice(G, n, replace=False)) for i in range(args.draws)]
        for label, p in picks:
            t = time.perf_counter()
            r = selection.select_sun(scene, centers[p], normals[p], lum[p], wts[p], candidates, **kw)
            total = time.perf_counter() - t
            scan = r.get("scan", {})
            found = scan.get("found", {"direction": r["direction"], "gain": r["gain"]})
            row = {"gaussians": label, "use_sun": r["use_sun"],
                   "found_deg": angle_deg(found["direction"], truth), "found_gain": found["gain"],
                   "sharpened_deg": angle_deg(r["direction"], truth),
                   "gain": max([found["gain"]] + [q["gain"] for q in scan.get("peaks", [])]),
                   "moved": scan.get("moved"),
                   "alternatives_deg": [angle_deg(a, truth) for a in r["alternatives"]],
                   "peaks": [(angle_deg(q["direction"], truth), q["gain"]) for q in scan.get("peaks", [])],
                   "seconds": total, "sharpen_seconds": scan.get("seconds", 0.0)}
            rows.append(row)
            print("[sun] %-16s search %5.1f deg gain %.4f -> sharpened %5.1f deg gain %.4f  "
                  "alternatives %s  peaks %s  %.0f s (sharpening %.0f s)" % (
                      label, row["found_deg"], row["found_gain"], row["sharpened_deg"], row["gain"],
                      [round(a) for a in row["alternatives_deg"]],
                      [(round(a), round(g, 3)) for a, g in row["peaks"]], total,
                      row["sharpen_seconds"]), flush=True)
        raise Recorded()

    original = runner.choose_lighting

    def choose(ctx):
        # Every seen Gaussian reaches the search; it draws its own shares.
        drawn["n"] = ctx.config.sun_gaussians
        ctx.config.sun_gaussians = 1 << 40
        return original(ctx)

    runner.choose_lighting = choose
    model_selection.select_sun = search
    with tempfile.TemporaryDirectory() as tmp:
        try:
            cli.main(["fit", args.scene, "-o", os.path.join(tmp, "fit"), "--budget", args.budget]
                     + fit_options)
        except Recorded:
            pass
    if not rows:
        _sys.exit("the fit ended before the lighting selection")
    print("\n| Gaussians | sun used | search [deg] | gain | sharpened [deg] | gain | "
          "alternatives [deg] | s | of it sharpening |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print("| %s | %s | %.1f | %.4f | %.1f | %.4f | %s | %.0f | %.0f |" % (
            r["gaussians"], "yes" if r["use_sun"] else "no", r["found_deg"], r["found_gain"],
            r["sharpened_deg"], r["gain"], ", ".join("%.0f" % a for a in r["alternatives_deg"]),
            r["seconds"], r["sharpen_seconds"]))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"scene": args.scene, "budget": args.budget, "fit_options": fit_options,
                       "truth_direction": truth.tolist(), "searches": rows}, f, indent=1)


if __name__ == "__main__":
    main()
