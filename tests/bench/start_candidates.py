"""How stage 2's start ranks suns it is offered (synthetic street).

    python tests/bench/start_candidates.py SCENE [--budget 8] [--json OUT.json]

Runs ``mi-invrgbl fit SCENE --budget B`` into a temporary folder up to
stage 2's start and, instead of the fit's own candidates alone, makes the
start (``Stage2.start_under``) under each sun direction the lighting
selection kept, the ground truth's time-A direction, and the truth turned
by 10 and 30 degrees (towards the horizon, and about the vertical), each
with the facings' irradiance, with the selection's level where the facings
disagree with it, and with a quarter of the facings' (a weak sun). For each
start it prints the angle to the truth, the sun's irradiance (luminance;
truth's in the header), the validation PSNR stage 2's start is scored
with, and the albedo spread within LiDAR-albedo groups
(``shading_init.albedo_spread``); then which start the validation PSNR
alone keeps and which ``shading_init.choose_start`` keeps. The fit stops
there: nothing is written but the JSON asked for.
"""

import sys as _sys, pathlib as _pathlib
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parents[1]))
import variant_choice  # noqa: E402  (--variant NAME, default $MI_INVRGBL_VARIANT or llvm_ad_rgb)
variant_choice.from_argv()

import argparse
import json
import os
import tempfile

import numpy as np

from mi_invrgbl.physics.directions import angle_deg


class Recorded(Exception):
    """Ends the fit once the starts are recorded."""


def turned(d, degrees, about_vertical):
    """``d`` turned by ``degrees``: about the vertical, or towards the horizon."""
    d = np.asarray(d, np.float64) / np.linalg.norm(d)
    t = np.radians(degrees)
    if about_vertical:
        c, s = np.cos(t), np.sin(t)
        out = np.array([c * d[0] - s * d[1], s * d[0] + c * d[1], d[2]])
    else:
        h = np.array([d[0], d[1], 0.0])
        h = h / max(np.linalg.norm(h), 1e-9)
        elev = np.arcsin(np.clip(d[2], -1, 1)) - t
        out = np.cos(elev) * h + np.sin(elev) * np.array([0.0, 0.0, 1.0])
    return (out / np.linalg.norm(out)).tolist()


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--budget", default="8")
    ap.add_argument("--json")
    args = ap.parse_args()      # (variant_choice took --variant out)

    import drjit as dr
    from mi_invrgbl import cli
    from mi_invrgbl.eval.ground_truth import gt_alignment, load_lights
    from mi_invrgbl.fit import shading_init
    from mi_invrgbl.fit.stage2 import Stage2
    from mi_invrgbl.physics.colour import LUMINANCE
    from mi_invrgbl.scene.frames import Frames

    frames = Frames.load(args.scene)
    if not frames.ground_truth:
        _sys.exit("%s: frames.json names no ground truth" % args.scene)
    R = gt_alignment(frames, range(len(frames)), frames.ground_truth)
    light = load_lights(frames.ground_truth)["time_a"]
    truth = (R @ np.asarray(light["sun_direction"], np.float64)).tolist()
    true_level = float(np.asarray(light["sun_irradiance"]) @ LUMINANCE)
    rows = []
    original = shading_init.reconcile_sun_irradiance

    def record(self):
        ctx = self.ctx
        sky = np.array(dr.detach(ctx.params[ctx.sky_key]), np.float32)
        own = ctx.selection.get("sun", {}).get("alternatives") or [
            np.array(dr.detach(ctx.params[ctx.sun_dir_key]), np.float64).ravel().tolist()]
        offered = [("selection #%d" % (i + 1), d) for i, d in enumerate(own)] + [("truth", truth)] + [
            ("truth %+d deg %s" % (a, "azimuth" if v else "elevation"), turned(truth, a, v))
            for a in (10, 30) for v in (False, True)]
        for label, d in offered:
            for level in ("facings", "selection", "weak"):
                if level == "weak":
                    shading_init.reconcile_sun_irradiance = \
                        lambda e, s, keep=None: (original(e, s, keep)[0] * 0.25, "facings x 0.25")
                try:
                    rep = self.start_under(sky, d, None if level == "selection" else "facings")
                finally:
                    shading_init.reconcile_sun_irradiance = original
                source = rep.get("sun_irradiance_from", "")
                if level == "selection" and not shading_init.facings_overruled(source):
                    continue     # (the same start as the facings')
                rows.append({"offered": label, "level": level, "source": source,
                             "direction": list(map(float, d)), "angle_deg": angle_deg(d, truth),
                             "irradiance": float(np.asarray(rep["sun_irradiance"]) @ LUMINANCE),
                             "psnr": float(self._start_score(rep)),
                             "spread": rep.get("albedo_spread")})
                print("[start] %-26s %-9s %5.1f deg  sun %5.2f  %6.2f dB  spread %s" % (
                    label, level, rows[-1]["angle_deg"], rows[-1]["irradiance"], rows[-1]["psnr"],
                    "-" if rows[-1]["spread"] is None else "%.4f" % rows[-1]["spread"]), flush=True)
        raise Recorded()

    Stage2.init_shading = record
    with tempfile.TemporaryDirectory() as tmp:
        try:
            cli.main(["fit", args.scene, "-o", os.path.join(tmp, "fit"), "--budget", args.budget])
        except Recorded:
            pass
    if not rows:
        _sys.exit("the fit ended before stage 2's start")
    own = [i for i, r in enumerate(rows) if r["offered"].startswith("selection")]
    by_psnr = max(own, key=lambda i: rows[i]["psnr"])
    by_rule = own[shading_init.choose_start([rows[i]["psnr"] for i in own],
                                            [rows[i]["spread"] for i in own])]
    every_psnr = max(range(len(rows)), key=lambda i: rows[i]["psnr"])
    every_rule = shading_init.choose_start([r["psnr"] for r in rows], [r["spread"] for r in rows])
    print("\ntruth's sun irradiance (luminance) %.2f; albedo spread within LiDAR-albedo groups; "
          "validation PSNR of the start" % true_level)
    print("| offered | level | angle to truth [deg] | sun (luminance) | start PSNR [dB] | spread |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print("| %s | %s | %.1f | %.2f | %.2f | %s |" % (
            r["offered"], r["level"], r["angle_deg"], r["irradiance"], r["psnr"],
            "-" if r["spread"] is None else "%.4f" % r["spread"]))
    for what, i in (("the selection's candidates, PSNR alone", by_psnr),
                    ("the selection's candidates, choose_start", by_rule),
                    ("every start, PSNR alone", every_psnr), ("every start, choose_start", every_rule)):
        r = rows[i]
        print("%-42s keeps %s, %s: %.1f deg off, sun %.2f" % (what, r["offered"], r["level"],
                                                               r["angle_deg"], r["irradiance"]))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"scene": args.scene, "budget": args.budget, "truth_direction": truth,
                       "truth_irradiance": true_level, "starts": rows,
                       "kept": {"selection_psnr": by_psnr, "selection_rule": by_rule,
                                "every_psnr": every_psnr, "every_rule": every_rule}}, f, indent=1)


if __name__ == "__main__":
    main()
