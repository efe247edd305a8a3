"""Stage 2's validation-score spacing, paired on the fit tests' small street.

    python tests/bench/stage2_spacing.py OUT [--minutes 8] [--seeds 0 1]

Builds the fit tests' small street (``tests/fit_scene.build``: 10 frames,
128 x 48, 256 LiDAR columns, sunny) in OUT/scene, then fits it under a
budget once per seed with stage 2 scoring its validation frames at most
:data:`~mi_invrgbl.fit.budget.STAGE2_EVAL_INTERVAL` steps apart and once
with that bound out of reach (a twelfth of the plan, the rule before it),
and prints one row per fit: held-out PSNR as trained at stage 2's start and
end, both stages' steps, stage 2's planned steps, score spacing, plateaus
and seconds, whether the lighting test kept a sun, and the wall time. A
budgeted fit's stage 1 depends on its timing, so the two fits of a seed may
choose different lighting; the row says so. OUT must be new or empty.
The numbers on the small street in "Stage 2 stops where its validation
PSNR levels off" (docs/measurements.md) come from this script.
"""

import sys as _sys, pathlib as _pathlib
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parents[1]))
import variant_choice  # noqa: E402  (--variant NAME, default $MI_INVRGBL_VARIANT or llvm_ad_rgb)
variant_choice.from_argv()

import argparse  # noqa: E402
import csv  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from fit_scene import build  # noqa: E402
from mi_invrgbl.fit import runner  # noqa: E402
from mi_invrgbl.fit.runner import FitConfig, run_fit  # noqa: E402

#: The two arms: stage 2's longest score spacing (None: a twelfth of the plan).
ARMS = (("every %d" % runner.STAGE2_EVAL_INTERVAL, runner.STAGE2_EVAL_INTERVAL),
        ("twelfth", 10 ** 9))


def stage2_psnr(log_csv: Path):
    """Held-out PSNR as trained at stage 2's first and last log rows."""
    rows = [r for r in csv.DictReader(open(log_csv)) if r["stage"] == "stage 2"]
    return float(rows[0]["heldout_psnr"]), float(rows[-1]["heldout_psnr"])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out")
    ap.add_argument("--minutes", type=float, default=8.0)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    args = ap.parse_args(argv)
    out = Path(args.out)
    if out.exists() and any(out.iterdir()):
        raise SystemExit("%s: not empty; give a new folder" % out)
    path = build(str(out / "scene"), n_frames=10, width=128, height=48, columns=256, sun=True)
    print("| seed | stage-2 spacing | sun | stage 1 it | stage 2 it / planned | every | plateaus "
          "| stage 2 [s] | held-out as trained, stage 2 start -> end [dB] | wall [s] |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for seed in args.seeds:
        for name, interval in ARMS:
            runner.STAGE2_EVAL_INTERVAL = interval
            fit_dir = out / ("%s_%d" % (name.replace(" ", ""), seed))
            t = time.perf_counter()
            m = run_fit(path, FitConfig(output=str(fit_dir), fit_width=128, lidar_columns=256,
                                        sun_candidates=32, seed=seed,
                                        budget_minutes=args.minutes), log=lambda *a: None)
            wall = time.perf_counter() - t
            b = m["selection"]["budget"]["stage 2"]
            start, end = stage2_psnr(fit_dir / "log.csv")
            print("| %d | %s | %s | %d | %d / %d | %d | %s | %.0f | %.2f -> %.2f | %.0f |" % (
                seed, name, "yes" if m["selection"]["sun"].get("use_sun") else "no",
                m["iterations"]["stage 1"], m["iterations"]["stage 2"], b["iterations"],
                b["eval_every"], ", ".join("%d" % p["at"] for p in b.get("plateaus", [])) or "-",
                m["times_s"]["stage 2"], start, end, wall), flush=True)


if __name__ == "__main__":
    main()
