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


@pytest.mark.bench
def test_bench_specular_sky_quick():
    import bench_specular_sky
    rows = bench_specular_sky.main(["--points", "4000", "--samples", "16", "--roughness", "0.1",
                                    "1.0", "--cos", "0.9"])
    glossy, rough = rows
    assert all(r["reference"] > 0 and r["plain"][2] > 0 and r["split"][2] > 0 for r in rows)
    # Per Gaussian the split sum resolves a glossy lobe the plain sum misses
    # (measured 0.10 against 0.35) and matches it for a rough one.
    assert glossy["split"][0] < 0.5 * glossy["plain"][0]
    assert rough["split"][0] < 1.2 * rough["plain"][0]


@pytest.mark.bench
def test_bench_fit_quick():
    import bench_fit
    rows = bench_fit.main(["--quick", "--runs", "3", "--ref-runs", "2"])
    timed = {r["row"]: r for r in rows if "row" in r}
    assert set(timed) == {"stage 1", "stage 2", "full re-trace", "hits re-traced", "plugin re-render"}
    assert all(r["t"] > 0 for r in timed.values())
    # Stage 2 works on the frozen caches: it traces no ray; the references do.
    assert timed["stage 2"]["traced"] == 0
    assert timed["full re-trace"]["traced"] > timed["hits re-traced"]["traced"] > 0
