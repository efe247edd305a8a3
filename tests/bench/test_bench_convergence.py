"""The convergence bench's budget arithmetic, table and plot (no fit runs)."""

import json
import pathlib
import sys

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))

import bench_convergence as bc  # noqa: E402


def test_budget_to_iterations():
    cal = bc.Calibration(stage1=20, stage2=20, stage1_s=40.0, stage2_s=20.0, fixed_s=100.0)
    # 10 min: 500 s left, half per stage at 2 s/it and 1 s/it.
    assert cal.iterations(600.0, 10) == (125, 250, False)
    # Below the fixed cost: the minimum, flagged.
    assert cal.iterations(60.0, 10) == (10, 10, True)


def test_table_and_plot(tmp_path):
    import cv2

    rows = [bc.Row("street", 2, 10, 10, True, 20.1, 0.5, 0.3, 17.0, 19.0, 0.1, 0.12, 3000, 200),
            bc.Row("street", 8, 200, 300, False, 23.4, 0.6, 0.2, 15.0, 21.0, 0.08, 0.12, 3100, 480),
            bc.Row("kitti", 8, 150, 150, False, 13.0, 0.3, None, None, None, 0.13, 0.16, 3700, 470)]
    text = bc.table(rows)
    lines = text.splitlines()
    assert len(lines) == 2 + len(rows)
    assert "2 (over)" in lines[2] and "| - |" in lines[4]
    rows.append(bc.Row("kitti", 8, 1984, 1158, False, 19.2, 0.6, None, None, None, 0.12, 0.16,
                       1200, 188, "cuda_ad_rgb"))
    bc.plot(rows, tmp_path / "p.png")
    img = cv2.imread(str(tmp_path / "p.png"))
    assert img is not None and img.shape == (420, 1180, 3)
    # Each variant's colour was drawn (rows without a variant are one variant).
    for bgr in bc.PALETTE[:2]:
        assert np.any(np.all(img == np.array(bgr, np.uint8), axis=2))


def test_plot_legend_wraps_and_keeps_colours_apart(tmp_path):
    # Nine merged variants (a release's own and eight tagged records): each
    # gets its own colour, and the legend wraps onto a second line, which
    # the image grows to hold, instead of running off its right edge.
    import cv2

    names = ["llvm_ad_rgb"] + ["tag%d-llvm_ad_rgb" % k for k in range(8)]
    rows = [bc.Row("street", 8, 200, 300, False, 23.0 + 0.1 * k, 0.6, 0.2, 15.0, 21.0, 0.08,
                   0.12, 3100, 480 + 10 * k, v) for k, v in enumerate(names)]
    assert len(set(bc.PALETTE[:len(names)])) == len(names)
    bc.plot(rows, tmp_path / "p.png")
    img = cv2.imread(str(tmp_path / "p.png"))
    assert img is not None and img.shape[0] > 420 and img.shape[1] == 1180
    # The last variant's legend entry sits on the added line.
    last = np.all(img[420 - 20:, :] == np.array(bc.PALETTE[len(names) - 1], np.uint8), axis=2)
    assert np.any(last)


def test_over_budget_marks_only_runs_past_the_tolerance():
    assert not bc.ran_over(2, 120.0 * (1 + bc.OVER_TOLERANCE) - 1)
    assert bc.ran_over(2, 252.0)          # KITTI at 2 minutes on 2 cores
    assert not bc.ran_over(8, None)       # a fit without a wall time is not judged


def test_rows_written_whole_and_marked(tmp_path):
    rows = [bc.Row("kitti", 2, 130, 5, bc.ran_over(2, 252.0), psnr=15.57, wall_s=252.0,
                   variant="llvm_ad_rgb"),
            bc.Row("street", 8, 640, 846, bc.ran_over(8, 453.0), psnr=25.81, wall_s=453.0,
                   variant="llvm_ad_rgb")]
    text = bc.write_rows(tmp_path, rows)
    assert (tmp_path / "convergence.md").read_text() == text + "\n"
    lines = text.splitlines()
    assert "2 (over)" in lines[2] and "(over)" not in lines[3]
    back = json.loads((tmp_path / "convergence.json").read_text())
    assert [r["case"] for r in back] == ["kitti", "street"]
    assert not list(tmp_path.glob("*.partial"))


def test_merged_rows_are_judged_by_their_wall_time(tmp_path):
    old = tmp_path / "old.json"
    # A row written before the mark existed: over_budget False, wall 2.1x the budget.
    old.write_text(json.dumps([dict(case="kitti", budget_min=2, stage1=130, stage2=5,
                                    psnr=15.5, wall_s=252.0, variant="llvm_ad_rgb")]))
    bc.main(["--merge", "%s:earlier" % old, "--work", str(tmp_path / "w")])
    md = (tmp_path / "w" / "convergence.md").read_text()
    assert "earlier-llvm_ad_rgb | 2 (over)" in md


def test_stage_psnr_reads_stage1_best_and_stage2_last(tmp_path):
    log = tmp_path / "log.csv"
    log.write_text("wall_s,stage,iteration,heldout_psnr\n"
                   "1,stage 1,0,10.4\n2,stage 1,50,25.14\n3,stage 1,100,24.9\n4,stage 1,150,nan\n"
                   "5,stage 2,0,24.15\n6,stage 2,50,\n7,stage 2,100,25.83\n")
    assert bc.stage_psnr(log) == (25.14, 25.83)
    assert bc.stage_psnr(tmp_path / "missing.csv") == (None, None)
    row = bc.Row("street", 8, 640, 846, psnr=25.81, stage1_peak_psnr=25.14, stage2_end_psnr=25.83)
    assert abs(row.stage2_gain - 0.69) < 1e-9 and "| +0.69 |" in bc.table([row])
    assert bc.Row("kitti", 8, 1, 1).stage2_gain is None


def test_row_reads_both_lidar_scores_from_eval(tmp_path):
    """A reused fit's row takes the range-image and the raw-point intensity
    scores (the fit's and the nearest neighbour's) from eval's metrics.json."""
    import argparse

    out = tmp_path / "fit_8min"
    out.mkdir()
    (out / "metrics.json").write_text(json.dumps({
        "mean": {"psnr": 22.3, "ssim": 0.79, "lidar_intensity_rmse": 0.1155,
                 "baseline_intensity_rmse": 0.1654, "raw_intensity_rmse": 0.1292,
                 "raw_baseline_intensity_rmse": 0.1464},
        "fit": {"iterations": {"stage 1": 2484, "stage 2": 924}, "wall_s": 470.0,
                "peak_rss_mb": 6062}}))
    args = argparse.Namespace(native_budget=True, reuse=True, min_iterations=10)
    row = bc.fit_budget("kitti", tmp_path / "scene.xml", 8, "llvm_ad_rgb", args, None,
                        tmp_path / "bench.log")
    assert (row.stage1, row.stage2) == (2484, 924)
    assert (row.intensity_rmse, row.nn_intensity_rmse) == (0.1155, 0.1654)
    assert (row.raw_intensity_rmse, row.nn_raw_intensity_rmse) == (0.1292, 0.1464)
    cells = bc.table([row]).splitlines()[2].split(" | ")
    assert "0.1292" in cells and "0.1464" in cells and "0.1155" in cells
    assert not (tmp_path / "bench.log").exists()     # nothing was run
