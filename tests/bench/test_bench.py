"""Benchmark entry for pytest: ``pytest -m bench -s tests/bench`` runs the quick size."""

import pathlib
import sys

import pytest

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))


@pytest.mark.bench
def test_bench_render_quick():
    import bench_render
    rows = bench_render.main(["--quick"])
    timed = [r for r in rows if "task" in r]
    assert len(timed) == 5
    assert all(r["t"] > 0 and r["hits"] > 0 for r in timed)
