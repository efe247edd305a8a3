"""The convergence bench's budget arithmetic, table and plot (no fit runs)."""

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
    bc.plot(rows, tmp_path / "p.png")
    img = cv2.imread(str(tmp_path / "p.png"))
    assert img is not None and img.shape == (380, 1180, 3)
    # Both cases' colours were drawn.
    for bgr in bc.COLOURS.values():
        assert np.any(np.all(img == np.array(bgr, np.uint8), axis=2))
