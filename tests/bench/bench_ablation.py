"""Ablation table: the full method against switched-off parts, on one imported scene.

Run from the repository root on an imported scene (``mi-invrgbl import``)::

    python tests/bench/bench_ablation.py out/street_fit/scene.xml --stage1 100 --stage2 150
    python tests/bench/bench_ablation.py out/kitti_fit/scene.xml --stage1 100 --stage2 100

Each variant is a real ``mi-invrgbl fit`` into ``DIR/fit_<variant>`` (the
stage-1 result is *not* shared: every row pays its own geometry fit, so rows
differ also by run-to-run noise of stage 1), followed by ``mi-invrgbl eval``
on the held-out frames. Variants:

* ``full``: all losses at the paper's weights, selection on ``auto``;
* ``no consistency``: ``--weights rgb2lidar=0,lidar2rgb=0``;
* ``lambertian``: ``--lidar-model lambertian`` (no specular LiDAR lobe);
* ``rgb only``: ``--weights lidar=0,rgb2lidar=0,lidar2rgb=0`` (stage 2 never
  sees LiDAR intensity; its LiDAR albedo stays at the import/regression
  initialisation);
* ``nn baseline``: the intensity of the nearest accumulated training point
  (from the ``full`` row's eval; no fit of its own).

Prints a markdown table (held-out PSNR, SSIM, LiDAR intensity RMSE, range
error, ray-drop accuracy; albedo RMSE, roughness MAE, normal error,
relighting PSNR and sun direction error where the scene has ground truth;
fit wall time from its log) and writes it to ``DIR/ablation.md``.
``--report`` only re-prints the table from existing outputs.
"""

from __future__ import annotations

import sys as _sys, pathlib as _pathlib
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parents[1]))
import variant_choice  # noqa: E402  (--variant NAME, default $MI_INVRGBL_VARIANT or llvm_ad_rgb)
variant_choice.from_argv()

import argparse
import json
import os
import subprocess
import sys

VARIANTS = [
    ("full", []),
    ("no consistency", ["--weights", "rgb2lidar=0,lidar2rgb=0"]),
    ("lambertian", ["--lidar-model", "lambertian"]),
    ("rgb only", ["--weights", "lidar=0,rgb2lidar=0,lidar2rgb=0"]),
]

COLUMNS = [("psnr", "PSNR [dB]", "%.2f"), ("ssim", "SSIM", "%.3f"),
           ("lidar_intensity_rmse", "intensity RMSE", "%.4f"),
           ("range_error", "range err [m]", "%.3f"), ("ray_drop_accuracy", "ray-drop acc", "%.3f"),
           ("albedo_rmse", "albedo RMSE", "%.3f"), ("lidar_albedo_rmse_scaled", "LiDAR albedo RMSE", "%.3f"),
           ("roughness_mae", "roughness MAE", "%.3f"),
           ("normal_angle_deg", "normal err [deg]", "%.1f"), ("relight_psnr", "relight PSNR [dB]", "%.2f")]


def _cli():
    # The console script installed next to this interpreter (it sets the variant).
    return [os.path.join(os.path.dirname(sys.executable), "mi-invrgbl")]


def run_variant(scene, name, extra, stage1, stage2, seed):
    out = os.path.join(os.path.dirname(os.path.abspath(scene)), "fit_" + name.replace(" ", "_"))
    subprocess.run(_cli() + ["fit", scene, "-o", out, "--stage1", str(stage1), "--stage2", str(stage2),
                             "--seed", str(seed)] + extra, check=True)
    subprocess.run(_cli() + ["eval", out], check=True)
    return read_variant(scene, name)


def fit_seconds(out, metrics=None):
    """Wall time of the fit: as ``fit`` reported it (kept by ``eval`` under
    "fit"), else the last row of its speed-versus-error log."""
    import csv
    wall = ((metrics or {}).get("fit") or {}).get("wall_s")
    if wall is not None:
        return float(wall)
    with open(os.path.join(out, "log.csv")) as f:
        rows = list(csv.DictReader(f))
    return float(rows[-1]["wall_s"]) if rows else None


def read_variant(scene, name):
    out = os.path.join(os.path.dirname(os.path.abspath(scene)), "fit_" + name.replace(" ", "_"))
    with open(os.path.join(out, "metrics.json")) as f:
        metrics = json.load(f)
    return out, fit_seconds(out, metrics), metrics


def table(rows):
    head = ["variant"] + [c[1] for c in COLUMNS] + ["sun err [deg]", "fit [s]"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, fit_s, mean, lighting in rows:
        cells = [name]
        for key, _, fmt in COLUMNS:
            v = mean.get(key)
            cells.append(fmt % v if isinstance(v, (int, float)) and v == v else "-")
        if lighting and lighting.get("sun_used"):
            cells.append("%.1f" % lighting["sun_direction_error_deg"])
        else:
            cells.append("no sun" if lighting else "-")
        cells.append("%.0f" % fit_s if fit_s else "-")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--stage1", type=int, default=100)
    ap.add_argument("--stage2", type=int, default=150)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--only", default="", help="comma-separated variant names")
    ap.add_argument("--fit-args", default="",
                    help="extra 'fit' arguments for every variant, e.g. '--sun on'")
    ap.add_argument("--report", action="store_true",
                    help="only print the table from the variants' existing outputs")
    args = ap.parse_args()
    only = {s.strip() for s in args.only.split(",") if s.strip()}
    rows = []
    for name, extra in VARIANTS:
        if only and name not in only:
            continue
        if args.report:
            try:
                out, fit_s, metrics = read_variant(args.scene, name)
            except OSError:
                continue
        else:
            out, fit_s, metrics = run_variant(args.scene, name, extra + args.fit_args.split(),
                                              args.stage1, args.stage2, args.seed)
        if "mean" not in metrics:     # fitted but not evaluated yet
            continue
        mean = metrics["mean"]
        rows.append((name, fit_s, mean, metrics.get("lighting")))
        if name == "full":
            nn = {"lidar_intensity_rmse": mean.get("baseline_intensity_rmse")}
            if nn["lidar_intensity_rmse"] is not None:
                rows.append(("nn baseline", None, nn, None))
        print(table(rows), flush=True)
    text = table(rows)
    path = os.path.join(os.path.dirname(os.path.abspath(args.scene)), "ablation.md")
    with open(path, "w") as f:
        f.write(text + "\n")
    print(text)
    print("written to %s" % path)


if __name__ == "__main__":
    main()
