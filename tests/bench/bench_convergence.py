"""Quality against compute: fits at increasing time budgets, one row each.

Run from the repository root::

    python tests/bench/bench_convergence.py                       # street + KITTI, 2 8 30 60 min
    python tests/bench/bench_convergence.py --budgets 2 --cases street
    python tests/bench/bench_convergence.py --variant cuda_ad_rgb --work out/bench_gpu

For each case (``street``: the seeded synthetic street of ``make-scene
street``, imported with ``--max-points 60000 --no-triangulate --roughness 0.85`` and fitted with
``--diffuse-fresnel --weights lidar2rgb=1``, as in the README's main job; ``kitti``: the KITTI raw
excerpt imported with ``--image-scale 0.25 --max-points 60000``) the bench
imports once, then for every budget runs a real ``mi-invrgbl fit`` and
``mi-invrgbl eval`` on the held-out frames and prints one row: held-out PSNR
and SSIM, the PSNR of the camera's lookup baseline (the nearest training
image shown unchanged; a fit below it has not learnt the scene), albedo RMSE, normal error, relighting PSNR (street only: it has
ground truth), LiDAR intensity RMSE of the fit and of the nearest-neighbour
baseline (every training point), on the range image and on the raw held-out
points along their own rays, the fit's peak memory and its wall time. The rows go to
``WORK/convergence.md`` and ``WORK/convergence.json``, and a plot of error
against wall time to ``WORK/convergence.png`` (drawn with OpenCV).

Budgets. When ``fit`` has ``--budget MINUTES`` the bench passes it on.
Otherwise it maps a budget to iterations with a calibration fit per case
(``--calibration`` iterations per stage, its times kept in
``WORK/CASE/calibration.json``): the fixed cost (loading, selections,
caching, outputs) is the calibration's wall time less its two stages, and
the remaining budget is split evenly in time between the stages at the
calibration's seconds per iteration. A budget below the fixed cost gets
``--min-iterations`` per stage and is marked ``over`` in the table: the row
then shows the cheapest fit, not one that met the budget.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, asdict
import json
import math
import os
from pathlib import Path
import subprocess
import sys
import time

ROOT = Path(__file__).resolve().parents[2]
KITTI = ROOT.parent / "shared" / "data" / "kitti-raw-excerpt"

CASES = {
    "street": dict(import_args=["--max-points", "60000", "--no-triangulate", "--roughness", "0.85"],
                   fit_args=["--diffuse-fresnel", "--weights", "lidar2rgb=1"]),
    "kitti": dict(import_args=["--image-scale", "0.25", "--max-points", "60000"], fit_args=[]),
}


@dataclass
class Row:
    case: str
    budget_min: float
    stage1: int
    stage2: int
    #: The fit ran past its budget (calibrated iterations below the fixed
    #: cost, or a ``--budget`` fit more than OVER_TOLERANCE over).
    over_budget: bool = False
    psnr: float | None = None
    ssim: float | None = None
    albedo_rmse: float | None = None
    normal_deg: float | None = None
    relight_psnr: float | None = None
    intensity_rmse: float | None = None
    nn_intensity_rmse: float | None = None
    peak_mb: float | None = None
    wall_s: float | None = None
    variant: str = ""
    #: The camera's lookup baseline: the nearest training image, unchanged.
    nn_psnr: float | None = None
    #: Held-out PSNR as trained (``log.csv``): stage 1's best, stage 2's last.
    stage1_peak_psnr: float | None = None
    stage2_end_psnr: float | None = None
    #: LiDAR intensity RMSE on the raw held-out points along their own rays
    #: (the fit's, and the nearest neighbour over every training point on the
    #: points the fit returns): stricter than the range-image score above.
    raw_intensity_rmse: float | None = None
    nn_raw_intensity_rmse: float | None = None
    #: What the row's run changed, for rows kept in docs/bench (not tabulated).
    note: str = ""

    @property
    def stage2_gain(self):
        """Stage 2's last held-out PSNR less stage 1's best (the fit may
        trail stage 1 by at most 1 dB)."""
        if self.stage1_peak_psnr is None or self.stage2_end_psnr is None:
            return None
        return self.stage2_end_psnr - self.stage1_peak_psnr


def cli(variant, *args):
    return [sys.executable, "-m", "mi_invrgbl_main", "--variant", variant, *map(str, args)]


def _env():
    # The checkout first, then whatever the caller's PYTHONPATH holds (a
    # machine may have the dependencies only there).
    return dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))


def run(cmd, log):
    env = _env()
    with open(log, "a") as f:
        f.write("$ " + " ".join(cmd) + "\n")
        f.flush()
        t = time.perf_counter()
        proc = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, env=env, cwd=ROOT)
        f.write("# exit %d after %.1f s\n" % (proc.returncode, time.perf_counter() - t))
    if proc.returncode != 0:
        raise SystemExit("failed (exit %d): %s; see %s" % (proc.returncode, " ".join(cmd), log))


def has_budget_option(variant) -> bool:
    out = subprocess.run(cli(variant, "fit", "--help"), capture_output=True, text=True,
                         env=_env(), cwd=ROOT)
    if out.returncode != 0:
        raise SystemExit("mi-invrgbl fit --help failed (exit %d): %s"
                         % (out.returncode, (out.stderr.strip().splitlines() or [""])[-1]))
    return "--budget" in out.stdout


def prepare(case, work: Path, variant, log) -> Path:
    """Import the case once; returns its scene.xml."""
    scene = work / case / "scene.xml"
    if scene.is_file():
        return scene
    if case == "street":
        data = work / "street_data"
        if not (data / "gt").is_dir():
            run(cli(variant, "make-scene", "street", data), log)
    else:
        data = KITTI
        if not data.is_dir():
            raise SystemExit(f"{data}: KITTI excerpt not found (skip it with --cases street)")
    run(cli(variant, "import", data, "-o", scene, *CASES[case]["import_args"]), log)
    return scene


def stage_psnr(log_csv: Path):
    """(stage 1's best, stage 2's last) held-out PSNR as trained, from a
    fit's ``log.csv``; None where a stage logged none."""
    import csv
    by_stage = {"stage 1": [], "stage 2": []}
    if log_csv.is_file():
        for r in csv.DictReader(open(log_csv)):
            v = r.get("heldout_psnr") or ""
            if r["stage"] in by_stage and v not in ("", "nan"):
                by_stage[r["stage"]].append(float(v))
    s1, s2 = by_stage["stage 1"], by_stage["stage 2"]
    return (max(s1) if s1 else None), (s2[-1] if s2 else None)


def iterations_run(log_csv: Path) -> dict:
    """Last iteration of each stage in a fit's ``log.csv`` (fits that predate
    the ``iterations`` entry of metrics.json)."""
    import csv
    out = {}
    if log_csv.is_file():
        for r in csv.DictReader(open(log_csv)):
            out[r["stage"]] = max(out.get(r["stage"], 0), int(r["iteration"]))
    return out


def fit_metrics(out: Path) -> dict:
    with open(out / "metrics.json") as f:
        return json.load(f)


@dataclass
class Calibration:
    stage1: int
    stage2: int
    stage1_s: float
    stage2_s: float
    fixed_s: float

    def iterations(self, budget_s, minimum):
        """Stage iterations that fill ``budget_s``; (n1, n2, over budget)."""
        left = budget_s - self.fixed_s
        n1 = int(0.5 * left / (self.stage1_s / self.stage1)) if left > 0 else 0
        n2 = int(0.5 * left / (self.stage2_s / self.stage2)) if left > 0 else 0
        over = n1 < minimum or n2 < minimum
        return max(n1, minimum), max(n2, minimum), over


def calibrate(case, scene: Path, variant, iters, log) -> Calibration:
    path = scene.parent / "calibration.json"
    if path.is_file():
        c = Calibration(**json.loads(path.read_text()))
        if c.stage1 == iters:
            return c
    out = scene.parent / "fit_calibration"

    def times():
        # fit writes its times at the top of metrics.json; eval moves them under "fit"
        if not (out / "metrics.json").is_file():
            return None
        m = fit_metrics(out)
        m = m.get("fit", m)
        cfg = m.get("config", {})
        if cfg.get("stage1_iterations") != iters or cfg.get("stage2_iterations") != iters:
            return None
        return m

    fit = times()
    if fit is None:
        run(cli(variant, "fit", scene, "-o", out, "--stage1", iters, "--stage2", iters,
                *CASES[case]["fit_args"]), log)
        fit = times()
    if fit is None or "times_s" not in fit:
        raise SystemExit(f"{out}: no metrics.json with the fit's times")
    t = fit["times_s"]
    c = Calibration(iters, iters, float(t["stage 1"]), float(t["stage 2"]),
                    float(fit["wall_s"]) - float(t["stage 1"]) - float(t["stage 2"]))
    path.write_text(json.dumps(asdict(c), indent=1))
    return c


def _budget_rules():
    """``mi_invrgbl.fit.budget``, loaded from its file: it needs only the
    standard library, while importing the package needs a Mitsuba variant,
    and the bench runs its fits in other processes. The bench marks a row
    "over" by the fit's own rule, not a copy of it."""
    import importlib.util
    spec = importlib.util.spec_from_file_location(
        "_mi_invrgbl_budget_rules", ROOT / "mi_invrgbl" / "fit" / "budget.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod        # (its dataclasses look their module up)
    spec.loader.exec_module(mod)
    return mod


_BUDGET = _budget_rules()
#: A budgeted fit more than this fraction past its budget is marked "over":
#: its fixed costs (loading, the frozen trace of every frame, the lighting
#: choices, the outputs) did not fit the budget.
OVER_TOLERANCE = _BUDGET.OVERRUN_TOLERANCE
ran_over = _BUDGET.over_budget


def fit_budget(case, scene: Path, budget, variant, args, cal, log) -> Row:
    out = scene.parent / ("fit_%gmin" % budget)
    if args.native_budget:
        n1 = n2 = None
        over = False
        cmd = cli(variant, "fit", scene, "-o", out, "--budget", budget, *CASES[case]["fit_args"])
    else:
        n1, n2, over = cal.iterations(60.0 * budget, args.min_iterations)
        cmd = cli(variant, "fit", scene, "-o", out, "--stage1", n1, "--stage2", n2,
                  *CASES[case]["fit_args"])
    if not (args.reuse and (out / "metrics.json").is_file()
            and "mean" in fit_metrics(out)):
        run(cmd, log)
        run(cli(variant, "eval", out), log)
    m = fit_metrics(out)
    mean, fit = m.get("mean", {}), m.get("fit", {})
    if n1 is None:
        # Iterations run (a budgeted stage may stop early), not the configured defaults.
        ran = fit.get("iterations") or iterations_run(out / "log.csv")
        n1, n2 = ran.get("stage 1"), ran.get("stage 2")
    wall = fit.get("wall_s")
    over = over or ran_over(budget, wall)
    s1_peak, s2_end = stage_psnr(out / "log.csv")
    return Row(case, budget, n1, n2, over, mean.get("psnr"), mean.get("ssim"),
               mean.get("albedo_rmse"), mean.get("normal_angle_deg"), mean.get("relight_psnr"),
               mean.get("lidar_intensity_rmse"), mean.get("baseline_intensity_rmse"),
               fit.get("peak_rss_mb"), wall, variant, nn_psnr=mean.get("baseline_psnr"),
               stage1_peak_psnr=s1_peak, stage2_end_psnr=s2_end,
               raw_intensity_rmse=mean.get("raw_intensity_rmse"),
               nn_raw_intensity_rmse=mean.get("raw_baseline_intensity_rmse"))


COLUMNS = [("case", "case", "%s"), ("variant", "variant", "%s"), ("budget_min", "budget [min]", "%g"),
           ("stage1", "stage 1 it", "%d"), ("stage2", "stage 2 it", "%d"),
           ("psnr", "PSNR [dB]", "%.2f"), ("nn_psnr", "NN image PSNR [dB]", "%.2f"),
           ("ssim", "SSIM", "%.3f"), ("stage2_gain", "stage 2 - stage 1 best [dB]", "%+.2f"),
           ("albedo_rmse", "albedo RMSE", "%.3f"), ("normal_deg", "normal err [deg]", "%.1f"),
           ("relight_psnr", "relight PSNR [dB]", "%.2f"),
           ("intensity_rmse", "intensity RMSE", "%.4f"),
           ("nn_intensity_rmse", "NN intensity RMSE", "%.4f"),
           ("raw_intensity_rmse", "raw-point intensity RMSE", "%.4f"),
           ("nn_raw_intensity_rmse", "NN raw-point intensity RMSE", "%.4f"),
           ("peak_mb", "peak mem [MB]", "%.0f"), ("wall_s", "wall [s]", "%.0f")]


def table(rows) -> str:
    lines = ["| " + " | ".join(c[1] for c in COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for r in rows:
        cells = []
        for key, _, fmt in COLUMNS:
            v = getattr(r, key)
            if v is None or (isinstance(v, float) and math.isnan(v)):
                cells.append("-")
            else:
                cells.append(fmt % v + (" (over)" if key == "budget_min" and r.over_budget else ""))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


# ----------------------------------------------------------------------------
# The plot (OpenCV drawing: matplotlib is not a dependency)
# ----------------------------------------------------------------------------

#: One colour per variant (this run's first), BGR; cases are told apart by
#: their place on the axes and the label at each curve's end.
PALETTE = [(190, 80, 10), (20, 110, 235), (40, 150, 40), (150, 40, 150), (110, 110, 110),
           (20, 170, 200), (40, 40, 200), (140, 140, 0), (0, 0, 0), (200, 150, 120)]
#: Width of the legend strip; longer legends wrap onto more lines.
LEGEND_WIDTH = 1080
#: Wall times span a GPU's seconds to the 2-core machine's hour: a log axis.
X_TICKS = [0.5, 1, 2, 5, 10, 20, 50, 100, 200]


@dataclass
class Series:
    label: str               # drawn at the curve's last point
    colour: tuple
    points: list             # [(wall minutes, value or None)]
    baseline: bool = False   # dashed line, hollow markers


def _panel(img, x0, y0, w, h, series, title, ylabel, xlim):
    """Axes at (x0, y0) of size w x h with a log time axis over ``xlim`` (minutes)."""
    import cv2

    ys = [y for s in series for x, y in s.points if y is not None and x]
    if not ys:
        return
    lo, hi = min(ys), max(ys)
    pad = 0.1 * (hi - lo) if hi > lo else max(abs(hi) * 0.1, 0.1)
    lo, hi = lo - pad, hi + pad
    lx0, lx1 = math.log(xlim[0]), math.log(xlim[1])

    def px(x, y):
        return (int(x0 + w * (math.log(x) - lx0) / (lx1 - lx0)),
                int(y0 + h - h * (y - lo) / (hi - lo)))

    black, grey = (0, 0, 0), (90, 90, 90)
    cv2.rectangle(img, (x0, y0), (x0 + w, y0 + h), black, 1)
    for k in range(5):
        y = lo + (hi - lo) * k / 4
        p = px(xlim[0], y)
        cv2.line(img, (x0 - 4, p[1]), (x0, p[1]), black, 1)
        cv2.putText(img, "%.3g" % y, (x0 - 50, p[1] + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.38,
                    black, 1, cv2.LINE_AA)
    for t in X_TICKS:
        if xlim[0] <= t <= xlim[1]:
            q = px(t, lo)
            cv2.line(img, (q[0], y0 + h), (q[0], y0 + h + 4), black, 1)
            cv2.line(img, (q[0], y0 + 1), (q[0], y0 + h - 1), (225, 225, 225), 1)
            cv2.putText(img, "%g" % t, (q[0] - 8, y0 + h + 18), cv2.FONT_HERSHEY_SIMPLEX, 0.38,
                        black, 1, cv2.LINE_AA)
    cv2.putText(img, title, (x0, y0 - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.5, black, 1, cv2.LINE_AA)
    cv2.putText(img, ylabel, (x0 + 4, y0 + 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, grey, 1,
                cv2.LINE_AA)
    cv2.putText(img, "fit wall time [min, log]", (x0 + w // 2 - 80, y0 + h + 36),
                cv2.FONT_HERSHEY_SIMPLEX, 0.45, black, 1, cv2.LINE_AA)
    for s in series:
        pts = [(x, y) for x, y in s.points if y is not None and x]
        for a, b in zip(pts[:-1], pts[1:]):
            if s.baseline:
                n = 12

                def along(f):   # the point a fraction f from a to b, evenly on the log axis
                    return px(a[0] * (b[0] / a[0]) ** f, a[1] + (b[1] - a[1]) * f)
                for k in range(0, n, 2):
                    cv2.line(img, along(k / n), along((k + 1) / n), s.colour, 1, cv2.LINE_AA)
            else:
                cv2.line(img, px(*a), px(*b), s.colour, 2, cv2.LINE_AA)
        for p in pts:
            cv2.circle(img, px(*p), 4, s.colour, 1 if s.baseline else -1, cv2.LINE_AA)
        if pts and s.label:
            q = px(*pts[-1])
            cv2.putText(img, s.label, (min(q[0] + 6, x0 + w - 40), q[1] - 6),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.36, s.colour, 1, cv2.LINE_AA)


def plot(rows, path: Path):
    """Error against wall time: held-out PSNR, LiDAR intensity RMSE and the
    street's materials, one colour per variant, the lookup baselines dashed;
    a legend strip below names the colours."""
    import cv2
    import numpy as np

    variants = list(dict.fromkeys(r.variant for r in rows))
    # The legend's entries, placed left to right and wrapped (one line each 22 px).
    places, x, line = [], 0, 0
    for v in variants:
        width = 40 + 9 * len(v)
        if x and x + width > LEGEND_WIDTH:
            x, line = 0, line + 1
        places.append((70 + x, 385 + 22 * line))
        x += width
    img = np.full((420 + 22 * line, 1180, 3), 255, np.uint8)
    walls = [r.wall_s / 60 for r in rows if r.wall_s]
    xlim = (min(walls + [1.0]) / 1.5, max(walls + [1.0]) * 1.5)
    psnr, intensity, materials = [], [], []
    # In the order the rows came: this run's (or the first --merge file's) first.
    colours = {v: PALETTE[k % len(PALETTE)] for k, v in enumerate(variants)}
    for case in CASES:
        for variant in variants:
            rs = sorted((r for r in rows if r.case == case and r.variant == variant and r.wall_s),
                        key=lambda r: r.wall_s)
            if not rs:
                continue
            c, t = colours[variant], [r.wall_s / 60 for r in rs]
            psnr.append(Series(case, c, list(zip(t, [r.psnr for r in rs]))))
            if any(r.nn_psnr is not None for r in rs):
                psnr.append(Series("", c, list(zip(t, [r.nn_psnr for r in rs])), True))
            intensity.append(Series(case, c, list(zip(t, [r.intensity_rmse for r in rs]))))
            intensity.append(Series("", c, list(zip(t, [r.nn_intensity_rmse for r in rs])), True))
            if any(r.albedo_rmse is not None for r in rs):
                materials.append(Series("albedo", c, list(zip(t, [r.albedo_rmse for r in rs]))))
                materials.append(Series("normal/100", c, list(zip(
                    t, [None if r.normal_deg is None else r.normal_deg / 100 for r in rs]))))
    _panel(img, 70, 40, 300, 270, psnr, "held-out PSNR", "dB", xlim)
    _panel(img, 460, 40, 300, 270, intensity, "LiDAR intensity RMSE", "RMSE", xlim)
    _panel(img, 850, 40, 300, 270, materials, "street: albedo RMSE, normal err [deg]/100",
           "", xlim)
    # Legend strip: the variants' colours, then what the dashed lines are.
    for v, (x, y) in zip(variants, places):
        cv2.line(img, (x, y - 4), (x + 24, y - 4), colours[v], 2, cv2.LINE_AA)
        cv2.putText(img, v, (x + 30, y), cv2.FONT_HERSHEY_SIMPLEX, 0.42, colours[v], 1,
                    cv2.LINE_AA)
    y = 385 + 22 * line
    cv2.putText(img, "dashed, hollow: nearest-neighbour lookup baseline (nearest training image; "
                "every training LiDAR point)", (70, y + 24), cv2.FONT_HERSHEY_SIMPLEX, 0.42,
                (60, 60, 60), 1, cv2.LINE_AA)
    cv2.imwrite(str(path), img)


def write_rows(work: Path, rows) -> str:
    """Write ``convergence.md`` and ``.json`` (each through a temporary file
    renamed into place); returns the table."""
    text = table(rows)
    for name, body in (("convergence.md", text + "\n"),
                       ("convergence.json", json.dumps([asdict(r) for r in rows], indent=1))):
        tmp = work / (name + ".partial")
        tmp.write_text(body)
        os.replace(tmp, work / name)
    return text


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("budgets", nargs="*", type=float, metavar="MINUTES",
                    help="fit budgets in minutes (default 2 8 30 60)")
    ap.add_argument("--budgets", dest="budgets_opt", nargs="+", type=float, metavar="MINUTES")
    ap.add_argument("--variant", default="llvm_ad_rgb")
    ap.add_argument("--cases", default="street,kitti", help="comma-separated: street, kitti")
    ap.add_argument("--work", default=str(ROOT / "out" / "bench_convergence"),
                    help="folder for the scenes, fits, table and plot")
    ap.add_argument("--calibration", type=int, default=20,
                    help="iterations per stage of the calibration fit (default 20)")
    ap.add_argument("--min-iterations", type=int, default=10)
    ap.add_argument("--reuse", action="store_true",
                    help="keep fits that already have an eval (re-print and re-plot)")
    ap.add_argument("--merge", nargs="+", default=[], metavar="JSON",
                    help="also tabulate and plot the rows of earlier runs' convergence.json "
                         "(PATH, e.g. a GPU machine's, or PATH:TAG: TAG names rows without a "
                         "variant and prefixes the others, e.g. 'previous'); with no budgets "
                         "given, run no fit")
    args = ap.parse_args(argv)
    merged = []
    for item in args.merge:
        # PATH or PATH:VARIANT (for rows written before the variant column)
        path, _, variant = item.rpartition(":") if not Path(item).is_file() else (item, "", "")
        try:
            rows_in = [Row(**r) for r in json.loads(Path(path).read_text())]
        except (OSError, ValueError, TypeError) as e:
            raise SystemExit(f"{path}: not a convergence.json ({e})")
        for r in rows_in:
            r.over_budget = bool(r.over_budget or ran_over(r.budget_min, r.wall_s))
            # A tag names rows without a variant, and prefixes those with one
            # (e.g. "previous" for an earlier release's rows beside this one's).
            r.variant = ("%s-%s" % (variant, r.variant) if variant and r.variant
                         else r.variant or variant)
        merged += rows_in
    if merged and not (args.budgets_opt or args.budgets):
        work = Path(args.work).absolute()
        work.mkdir(parents=True, exist_ok=True)
        (work / "convergence.md").write_text(table(merged) + "\n")
        plot(merged, work / "convergence.png")
        print(table(merged))
        print("written: %s, %s" % (work / "convergence.md", work / "convergence.png"))
        return
    budgets = args.budgets_opt or args.budgets or [2, 8, 30, 60]
    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    for c in cases:
        if c not in CASES:
            raise SystemExit(f"--cases: unknown case '{c}' (street, kitti)")
    work = Path(args.work).absolute()
    work.mkdir(parents=True, exist_ok=True)
    log = work / "bench.log"
    args.native_budget = has_budget_option(args.variant)
    print("budgets %s min; %s" % (" ".join("%g" % b for b in budgets),
                                   "fit --budget" if args.native_budget else
                                   "iterations from a calibration fit"), flush=True)
    rows = []
    for case in cases:
        scene = prepare(case, work, args.variant, log)
        cal = None
        if not args.native_budget:
            cal = calibrate(case, scene, args.variant, args.calibration, log)
            print("%s: calibration %d+%d iterations: stage 1 %.2f s/it, stage 2 %.2f s/it, "
                  "fixed %.0f s" % (case, cal.stage1, cal.stage2, cal.stage1_s / cal.stage1,
                                    cal.stage2_s / cal.stage2, cal.fixed_s), flush=True)
        for b in sorted(budgets):
            rows.append(fit_budget(case, scene, b, args.variant, args, cal, log))
            print(table(rows), flush=True)
            # Written after every row: an hour-long bench that is stopped
            # keeps the rows it finished.
            write_rows(work, rows + merged)
    rows += merged
    text = write_rows(work, rows)
    plot(rows, work / "convergence.png")
    print(text)
    print("written: %s, %s, %s" % (work / "convergence.md", work / "convergence.json",
                                   work / "convergence.png"))


if __name__ == "__main__":
    main()
