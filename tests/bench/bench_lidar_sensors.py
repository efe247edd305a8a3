"""LiDAR novel view per sensor kind, against the lookup baseline.

For each sensor (``hdl64``, ``vlp32``, ``os128``, an explicit solid-state
``rays`` pattern) and intensity kind (``raw``, ``reflectivity``), run from the
repository root::

    python tests/bench/bench_lidar_sensors.py --out /tmp/lidar_bench            # small size
    python tests/bench/bench_lidar_sensors.py --out /tmp/lidar_bench --report   # re-print

each row is a real pipeline: ``make-scene street --lidar K --intensity I``,
``import``, ``fit`` (``--lidar-model pbr``, which also fits and writes the
ray-drop model) and the raw-point scoring of
:mod:`mi_invrgbl.eval.lidar_novel_view` on the held-out frames: intensity RMSE
of the scene and of the lookup (nearest training point, every training point,
handed the true point; scored on the returns the scene also returns), range
MAE, ray-drop accuracy and F1 (no-return class) of both, and the range-image
intensity RMSE beside the raw-point one. The ablation re-fits the same import
with ``--lidar-model lambertian`` (no specular LiDAR lobe) and scores it the
same way. Everything is written under ``--out`` (``results.json``, ``table.md``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SENSORS = ("hdl64", "vlp32", "os128", "rays")
KINDS = ("raw", "reflectivity")
SIZES = {
    # frames, width, height, azimuth steps, import points, stage 1, stage 2
    "small": dict(frames=10, width=64, height=24, az=512, points=20000, s1=30, s2=40),
    "medium": dict(frames=20, width=160, height=48, az=1024, points=80000, s1=100, s2=100),
}


def _cli(args, cwd, log):
    env = dict(os.environ, PYTHONPATH=ROOT)
    t = time.time()
    r = subprocess.run([sys.executable, "-m", "mi_invrgbl_main", *args], cwd=cwd, env=env,
                       capture_output=True, text=True)
    with open(log, "a") as f:
        f.write("$ mi-invrgbl %s\n%s%s(%.1f s, rc %d)\n" % (" ".join(args), r.stdout, r.stderr,
                                                         time.time() - t, r.returncode))
    if r.returncode:
        raise RuntimeError("mi-invrgbl %s failed: %s" % (args[0], (r.stdout + r.stderr)[-1500:]))
    return r.stdout


def run_one(out, sensor, kind, size, ablation=True):
    import numpy as np
    import mitsuba as mi
    mi.set_variant(os.environ.get("MI_INVRGBL_VARIANT", "llvm_ad_rgb"))
    sys.path.insert(0, ROOT)
    from mi_invrgbl.eval.lidar_novel_view import score_scene
    from mi_invrgbl.synthetic.sensors import solid_state_rays
    cfg = SIZES[size]
    name = "%s_%s" % (sensor, kind)
    work = os.path.join(out, name)
    os.makedirs(work, exist_ok=True)
    log = os.path.join(work, "log.txt")
    lidar, pattern = sensor, None
    if sensor == "rays":
        rays = solid_state_rays()
        np.save(os.path.join(work, "rays.npy"), rays)
        lidar, pattern = "rays:" + os.path.join(work, "rays.npy"), rays[:, 3:6]
    t0 = time.time()
    if not os.path.isdir(os.path.join(work, "street")):
        _cli(["make-scene", "street", "street", "--frames", str(cfg["frames"]), "--width",
              str(cfg["width"]), "--height", str(cfg["height"]), "--spp", "2", "--azimuth-steps",
              str(cfg["az"]), "--lidar", lidar, "--intensity", kind, "--no-night"], work, log)
    imp = _cli(["import", "street", "-o", "imp/scene.xml", "--max-points", str(cfg["points"]),
                "--azimuth-steps", str(cfg["az"]), "--overwrite"], work, log)
    layout = next((ln.split("LiDAR: ", 1)[1] for ln in imp.splitlines() if "[import] LiDAR:" in ln), "")
    row = {"sensor": sensor, "intensity": kind, "layout": layout}
    for model in ("pbr", "lambertian") if ablation else ("pbr",):
        fit_dir = os.path.join(work, "imp", "fit_" + model)
        _cli(["fit", "imp/scene.xml", "-o", fit_dir, "--stage1", str(cfg["s1"]), "--stage2",
              str(cfg["s2"]), "--width", str(cfg["width"]), "--lidar-columns", str(cfg["az"] // 2),
              "--batch", "2048", "--samples", "4", "--render-samples", "4", "--eval-every", "1000",
              "--lidar-model", model], work, log)
        res = score_scene(os.path.join(fit_dir, "scene.xml"), pattern=pattern, log=lambda *a: None)
        row[model] = res
    row["wall_s"] = time.time() - t0
    return row


def _f(v, fmt="%.4f"):
    return "—" if v is None or v != v else fmt % v


def _layout(text):
    import re
    m = re.search(r"(\d+ rays in \d+ beam\(s\)|\d+ beams), (non-uniform|uniform)", text)
    return "%s, %s" % m.groups() if m else text[:40]


def table(rows) -> str:
    head = ("| sensor | intensity | beams found | intensity RMSE scene / lookup (ratio) | "
            "range-image RMSE scene / lookup | range MAE scene / lookup [m] | "
            "ray-drop acc scene / lookup | ray-drop F1 scene / lookup | lambertian RMSE |")
    lines = [head, "|" + "---|" * 9]
    for r in rows:
        p = r["pbr"]["raw_points"]
        m, b = p["model"], p["baseline"]
        ri = r["pbr"].get("range_image")
        lam = r.get("lambertian", {}).get("raw_points", {}).get("model", {}).get("intensity_rmse")
        base_i = b.get("intensity_rmse_on_model_returns")
        lines.append("| %s | %s | %s | %s / %s (%s) | %s | %s / %s | %s / %s | %s / %s | %s |" % (
            r["sensor"], r["intensity"], _layout(r["layout"]),
            _f(m["intensity_rmse"]), _f(base_i), _f(m["intensity_rmse"] / base_i, "%.2f"),
            ("%s / %s" % (_f(ri["model"]["intensity_rmse"]), _f(ri["baseline"]["intensity_rmse"])))
            if ri else "—",
            _f(m["range_mae"], "%.3f"), _f(b["range_mae"], "%.3f"),
            _f(m["drop_accuracy"], "%.3f"), _f(b["drop_accuracy"], "%.3f"),
            _f(m["drop_f1"], "%.3f"), _f(b["drop_f1"], "%.3f"), _f(lam)))
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", required=True, help="work folder (created; streets are reused)")
    ap.add_argument("--size", choices=sorted(SIZES), default="small")
    ap.add_argument("--sensors", default=",".join(SENSORS))
    ap.add_argument("--kinds", default=",".join(KINDS))
    ap.add_argument("--no-ablation", action="store_true", help="skip the lambertian re-fit")
    ap.add_argument("--report", action="store_true", help="only re-print the table")
    args = ap.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, "results.json")
    rows = json.load(open(path)) if os.path.isfile(path) else []
    if not args.report:
        for sensor in args.sensors.split(","):
            for kind in args.kinds.split(","):
                row = run_one(args.out, sensor, kind, args.size, not args.no_ablation)
                rows = [r for r in rows if (r["sensor"], r["intensity"]) != (sensor, kind)] + [row]
                with open(path, "w") as f:
                    json.dump(rows, f, indent=1)
                print("[bench] %s %s done in %.0f s" % (sensor, kind, row["wall_s"]), flush=True)
    text = table(rows)
    with open(os.path.join(args.out, "table.md"), "w") as f:
        f.write(text + "\n")
    print(text)
    return rows


if __name__ == "__main__":
    main()
