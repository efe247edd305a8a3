"""The convergence bench's bookkeeping: rows over their budget are marked,
and the table is rewritten whole after every row (no fits are run here)."""

import importlib.util
import json
import sys
from pathlib import Path

BENCH = Path(__file__).parent / "bench" / "bench_convergence.py"


def load_bench():
    spec = importlib.util.spec_from_file_location("bench_convergence", BENCH)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod      # (its dataclasses look their module up)
    spec.loader.exec_module(mod)
    return mod


def test_over_budget_marks_only_runs_past_the_tolerance():
    b = load_bench()
    assert not b.ran_over(2, 120.0 * (1 + b.OVER_TOLERANCE) - 1)
    assert b.ran_over(2, 252.0)          # KITTI at 2 minutes on 2 cores
    assert not b.ran_over(8, None)       # a fit without a wall time is not judged


def test_rows_written_whole_and_marked(tmp_path):
    b = load_bench()
    rows = [b.Row("kitti", 2, 130, 5, b.ran_over(2, 252.0), psnr=15.57, wall_s=252.0,
                  variant="llvm_ad_rgb"),
            b.Row("street", 8, 640, 846, b.ran_over(8, 453.0), psnr=25.81, wall_s=453.0,
                  variant="llvm_ad_rgb")]
    text = b.write_rows(tmp_path, rows)
    assert (tmp_path / "convergence.md").read_text() == text + "\n"
    lines = text.splitlines()
    assert "2 (over)" in lines[2] and "(over)" not in lines[3]
    back = json.loads((tmp_path / "convergence.json").read_text())
    assert [r["case"] for r in back] == ["kitti", "street"]
    assert not list(tmp_path.glob("*.partial"))


def test_merged_rows_are_judged_by_their_wall_time(tmp_path):
    b = load_bench()
    old = tmp_path / "old.json"
    # A row written before the mark existed: over_budget False, wall 2.1x the budget.
    old.write_text(json.dumps([dict(case="kitti", budget_min=2, stage1=130, stage2=5,
                                    psnr=15.5, wall_s=252.0, variant="llvm_ad_rgb")]))
    b.main(["--merge", "%s:earlier" % old, "--work", str(tmp_path / "w")])
    md = (tmp_path / "w" / "convergence.md").read_text()
    assert "earlier-llvm_ad_rgb | 2 (over)" in md
