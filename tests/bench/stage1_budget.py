"""Stage 1 under a time budget: which settings learn most per second.

    python tests/bench/stage1_budget.py SCENE.xml SECONDS [--try NAME:FIELD=VALUE,... ...]

Runs ``fit``'s own budgeted stage 1 (:func:`mi_invrgbl.fit.runner.fit_geometry`
with a :class:`~mi_invrgbl.fit.budget.Budget` whose stage-1 share is
SECONDS: the batch probe, the plan, the schedules that follow the stage's
time, densification, the validation stop and the return to the best
validation state, then the removal of sky look-alikes) once per setting,
each in its own process, one after another, and prints a table: steps run,
Gaussians at the end, PSNR on the validation frames (what to choose by)
and on the held-out frames (reported only), and the wall time. ``--try``
names a setting and the :class:`~mi_invrgbl.fit.config.FitConfig` fields it
changes (default: ``base:``, the defaults alone), for example::

    python tests/bench/stage1_budget.py out/bench_convergence/kitti/scene.xml 300 \\
        --try base: b8192:batch_rays=8192,lidar_batch_rays=2048 \\
              b2048:batch_rays=2048,lidar_batch_rays=512 dens08:densify_fraction=0.08 lr2:lr_scale=2

The "Stage 1 per second" table in docs/measurements.md comes from this script. Run it on
an otherwise idle machine: a budgeted stage plans from measured speed.
"""

import sys as _sys, pathlib as _pathlib
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parents[1]))
import variant_choice  # noqa: E402  (--variant NAME, default $MI_INVRGBL_VARIANT or llvm_ad_rgb)
variant_choice.from_argv()

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402


def one(scene, seconds, fields):
    """Run one setting in this process; returns its result row."""
    from stage1_steps import config_from
    from mi_invrgbl.fit import runner
    from mi_invrgbl.fit.budget import SHARES, Budget
    from mi_invrgbl.fit.evaluate import score_stage1
    from mi_invrgbl.fit.init import load_state
    from mi_invrgbl.fit.progress import SpeedErrorLog

    cfg = config_from(fields)
    t0 = time.perf_counter()
    state = load_state(scene, cfg, lambda *a: None)
    state.t_start = t0
    with tempfile.TemporaryDirectory() as tmp:
        state.speed_log = SpeedErrorLog(os.path.join(tmp, "log.csv"))
        budget = Budget(seconds / 60.0 / SHARES["stage 1"], time.perf_counter())
        runner.fit_geometry(state, 0, None, lambda *a, **k: None, budget)
    wall = time.perf_counter() - t0
    return {"steps": state.iterations.get("stage 1", 0), "gaussians": state.model.total,
            "validation_psnr": score_stage1(state, state.validation_frames),
            "heldout_psnr": score_stage1(state, state.held_out_frames), "wall_s": wall,
            "batch": state.selection.get("budget", {}).get("stage 1", {}).get("batch_scale", 1)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("seconds", type=float, help="stage 1's share of the budget, in seconds")
    ap.add_argument("--try", dest="tries", nargs="*", default=[], metavar="NAME:FIELD=VALUE,...")
    ap.add_argument("--one", help=argparse.SUPPRESS)      # internal: run one setting, print JSON
    args = ap.parse_args(argv)
    if args.one is not None:
        fields = [f for f in args.one.split(",") if f]
        print("RESULT " + json.dumps(one(args.scene, args.seconds, fields)), flush=True)
        return
    settings = []
    for item in args.tries or ["base:"]:
        name, _, fields = item.partition(":")
        settings.append((name, fields))
    rows = []
    for name, fields in settings:
        # (The variant travels in MI_INVRGBL_VARIANT, which from_argv exported.)
        cmd = [_sys.executable, __file__, args.scene, str(args.seconds), "--one", fields]
        out = subprocess.run(cmd, capture_output=True, text=True)
        line = [x for x in out.stdout.splitlines() if x.startswith("RESULT ")]
        if out.returncode or not line:
            raise SystemExit("%s: stage 1 failed (exit %d): %s" % (
                name, out.returncode, (out.stderr.strip().splitlines() or [""])[-1]))
        row = json.loads(line[0][len("RESULT "):])
        rows.append((name, fields or "-", row))
        print("%s done: %s" % (name, row), flush=True)
    print("\n| setting | fields | steps | batch scale | Gaussians | validation PSNR [dB] | "
          "held-out PSNR [dB] | wall [s] |\n|---|---|---|---|---|---|---|---|")
    for name, fields, r in rows:
        print("| %s | %s | %d | %d | %d | %.2f | %.2f | %.0f |" % (
            name, fields, r["steps"], r["batch"], r["gaussians"], r["validation_psnr"],
            r["heldout_psnr"], r["wall_s"]))


if __name__ == "__main__":
    main()
