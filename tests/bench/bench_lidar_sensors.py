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

``--response-transfer DIR`` (an imported scene, e.g. of the KITTI excerpt:
``mi-invrgbl import data/kitti-raw-excerpt -o DIR/scene.xml --image-scale 0.25
--max-points 100000``) measures the response model alone on real data: the
response is fitted on the raw points of the training frames among the first 30
(surfaces: 0.2 m voxels of the accumulated points, normals by PCA), with and
without the sensor kind's priors and with the angle exponent held at 1 or
free, and predicts the intensities of frames 32-39 (metres further on),
against the lookup on the same points.
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


def response_transfer(scene_dir, train_end=30, new=range(32, 40), voxel=0.2):
    """Rows of the ``--response-transfer`` measurement (see the module docstring)."""
    import numpy as np
    import mitsuba as mi
    mi.set_variant(os.environ.get("MI_INVRGBL_VARIANT", "llvm_ad_rgb"))
    sys.path.insert(0, ROOT)
    from mi_invrgbl.io import init_gaussians as ig
    from mi_invrgbl.io.range_image import assign_beams
    from mi_invrgbl.fit.response import estimate_response, prior_for
    from mi_invrgbl.eval.baselines import NearestNeighbourIntensity
    fj = json.load(open(os.path.join(scene_dir, "frames.json")))
    frames, kind = fj["frames"], fj["lidar"].get("intensity", "raw")

    def load(i):
        f = frames[i]
        T = np.array(f["lidar_to_world"])
        p = np.load(os.path.join(scene_dir, f["points"]))
        v = p[:, :3] - T[:3, 3]
        d = np.linalg.norm(v, axis=1)
        return dict(xyz=p[:, :3].astype(np.float64), I=p[:, 3].astype(np.float64), d=d,
                    dir=v / d[:, None], beam=assign_beams(v @ T[:3, :3], fj["lidar"]["beams"])[0])

    train = [i for i in range(min(train_end, len(frames))) if not frames[i]["held_out"]]
    new = [i for i in new if i < len(frames)]
    obs = {i: load(i) for i in train + new}
    allxyz = np.concatenate([obs[i]["xyz"] for i in train])
    keys = np.floor(allxyz / voxel).astype(np.int64)
    uk, inv = np.unique(keys, axis=0, return_inverse=True)
    cent = ig.group_mean(allxyz, inv.ravel(), len(uk)).astype(np.float32)
    normals = ig.pca_frames(cent, ig.knn(cent, 12)[0])[0]
    kt = np.ascontiguousarray(uk).view([("a", np.int64), ("b", np.int64), ("c", np.int64)]).ravel()
    order = np.argsort(kt)
    kts = kt[order]

    def stack(fs):
        S = {k: np.concatenate([obs[i][k] for i in fs]) for k in ("xyz", "I", "d", "dir", "beam")}
        k = np.ascontiguousarray(np.floor(S["xyz"] / voxel).astype(np.int64)).view(kt.dtype).ravel()
        pos = np.clip(np.searchsorted(kts, k), 0, len(kts) - 1)
        S["sid"] = np.where(kts[pos] == k, order[pos], -1)
        S["cos"] = np.abs(np.sum(normals[np.maximum(S["sid"], 0)] * S["dir"], axis=1))
        return S

    tr, nv = stack(train), stack(new)
    m = tr["sid"] >= 0
    rows = []
    for name, kw in (("no prior, a = 1", dict(fit_angle=False)), ("no prior, a free", {}),
                     ("prior (%s), a = 1" % kind, dict(fit_angle=False, prior=prior_for(kind))),
                     ("prior (%s), a free" % kind, dict(prior=prior_for(kind)))):
        r = estimate_response(tr["I"][m], tr["d"][m], tr["cos"][m], tr["beam"][m], tr["sid"][m],
                              fj["lidar"]["beams"], n_surfaces=len(uk), **kw)
        rho = r.rho[np.maximum(nv["sid"], 0)]
        sel = (nv["sid"] >= 0) & np.isfinite(rho) & (nv["I"] > 0) & (nv["cos"] > 0.05)
        pred = r.predict(rho[sel], nv["d"][sel], nv["cos"][sel], nv["beam"][sel])
        rows.append({"fit": name, "range_exponent": r.range_exponent, "angle_exponent": r.angle_exponent,
                     "gains": [float(r.beam_gains.min()), float(r.beam_gains.max())],
                     "residual": float(r.residual_rms), "rmse": float(np.sqrt(np.mean((pred - nv["I"][sel]) ** 2))), "points": int(sel.sum())})
    nn = NearestNeighbourIntensity(np.c_[tr["xyz"], tr["I"]])
    rows.append({"fit": "lookup (every training point)", "points": int(sel.sum()),
                 "rmse": float(np.sqrt(np.mean((nn.predict(nv["xyz"][sel]) - nv["I"][sel]) ** 2)))})
    print("| response fit | range exp. b | angle exp. a | beam gains | training residual | "
          "new-pose intensity RMSE |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print("| %s | %s | %s | %s | %s | %.4f |" % (
            r["fit"], _f(r.get("range_exponent"), "%.3f"), _f(r.get("angle_exponent"), "%.3f"),
            "%.2f-%.2f" % tuple(r["gains"]) if "gains" in r else "—", _f(r.get("residual")),
            r["rmse"]))
    return rows


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
    ap.add_argument("--out", default=None, help="work folder (created; streets are reused)")
    ap.add_argument("--size", choices=sorted(SIZES), default="small")
    ap.add_argument("--sensors", default=",".join(SENSORS))
    ap.add_argument("--kinds", default=",".join(KINDS))
    ap.add_argument("--no-ablation", action="store_true", help="skip the lambertian re-fit")
    ap.add_argument("--report", action="store_true", help="only re-print the table")
    ap.add_argument("--response-transfer", metavar="DIR",
                    help="only the response-transfer measurement on an imported scene DIR")
    args = ap.parse_args(argv)
    if args.response_transfer:
        return response_transfer(args.response_transfer)
    if not args.out:
        ap.error("--out is required")
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
