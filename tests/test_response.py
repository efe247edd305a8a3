"""LiDAR sensor response estimation on simulated returns."""

import time

import numpy as np
import pytest

from mi_invrgbl.fit.response import (SensorResponse, estimate_response, format_statistics,
                                     ground_mask, intensity_statistics)


def simulate(a, b, n_beams=16, n_surf=300, per_surf=40, noise=0.03, gains=None, seed=0,
             outliers=0.0):
    """Returns seen from several ranges / angles per surface, as over a drive."""
    rng = np.random.default_rng(seed)
    rho = rng.uniform(0.05, 0.8, n_surf)
    if gains is None:
        gains = np.exp(rng.normal(0, 0.15, n_beams))
        gains /= np.median(gains)
    s = np.repeat(np.arange(n_surf), per_surf)
    d = rng.uniform(3, 40, s.size)
    c = rng.uniform(0.1, 1.0, s.size)
    beam = rng.integers(0, n_beams, s.size)
    inten = gains[beam] * rho[s] * c ** a / (np.pi * d ** b)
    inten *= np.exp(rng.normal(0, noise, s.size))
    if outliers:
        bad = rng.uniform(size=s.size) < outliers
        inten[bad] *= rng.uniform(3, 10, bad.sum())   # specular glints, multipath
    return dict(intensity=inten, distance=d, cos_theta=c, beam=beam, surface_id=s,
                n_beams=n_beams), rho, gains


@pytest.mark.parametrize("a,b", [(1.0, 2.0), (0.0, 0.0), (0.6, 1.2)])
def test_recovers_exponents_and_gains(a, b):
    obs, rho, gains = simulate(a, b)
    r = estimate_response(**obs)
    assert isinstance(r, SensorResponse)
    assert r.angle_exponent == pytest.approx(a, abs=0.02)
    assert r.range_exponent == pytest.approx(b, abs=0.02)
    np.testing.assert_allclose(r.beam_gains, gains, rtol=0.02)
    assert np.median(r.beam_gains) == pytest.approx(1.0)
    np.testing.assert_allclose(r.rho, rho, rtol=0.04)
    assert r.residual_rms == pytest.approx(0.03, rel=0.2)
    assert r.n_used == obs["intensity"].size


def test_robust_to_outliers_and_bad_returns():
    obs, rho, gains = simulate(1.0, 2.0, outliers=0.05, seed=3)
    obs["intensity"][:50] = 0.0                    # dropped / zero returns
    obs["cos_theta"][50:100] = 0.01                # grazing: ignored
    obs["intensity"][100:110] = np.nan
    r = estimate_response(**obs)
    assert r.n_used == obs["intensity"].size - 110
    assert r.angle_exponent == pytest.approx(1.0, abs=0.03)
    assert r.range_exponent == pytest.approx(2.0, abs=0.03)
    np.testing.assert_allclose(r.beam_gains, gains, rtol=0.03)
    # plain least squares is visibly pulled by the glints
    r2 = estimate_response(**obs, robust="l2", trim=0)
    assert abs(r2.range_exponent - 2.0) + abs(r2.angle_exponent - 1.0) > \
        abs(r.range_exponent - 2.0) + abs(r.angle_exponent - 1.0)


def test_fixed_parts_and_degenerate_input():
    obs, rho, gains = simulate(1.0, 2.0, gains=np.ones(16))
    r = estimate_response(**obs, fit_gains=False, fit_angle=False, angle_exponent=1.0)
    assert r.angle_exponent == 1.0 and np.all(r.beam_gains == 1.0)
    assert r.range_exponent == pytest.approx(2.0, abs=0.02)
    # a beam without returns keeps gain 1 (relative to the median)
    obs2, _, _ = simulate(1.0, 2.0, n_beams=8)
    obs2["n_beams"] = 10
    r = estimate_response(**obs2)
    assert r.beam_gains.shape == (10,) and np.all(np.isfinite(r.beam_gains))
    # nothing usable
    r = estimate_response(np.zeros(5), np.ones(5), np.ones(5), np.zeros(5, int),
                          np.arange(5), 4)
    assert r.n_used == 0 and np.all(np.isnan(r.rho)) and np.all(r.beam_gains == 1)
    with pytest.raises(ValueError):
        estimate_response(np.ones(3), np.ones(2), np.ones(3), np.zeros(3, int), np.zeros(3, int), 2)
    # integrator dictionary loads
    import mitsuba as mi
    integ = mi.load_dict(estimate_response(**obs).integrator_dict())
    assert "lidar_return" in integ.to_string().lower() or integ is not None


def test_large_problem_is_fast():
    obs, rho, gains = simulate(1.0, 2.0, n_beams=64, n_surf=50000, per_surf=12, seed=5)
    t = time.perf_counter()
    r = estimate_response(**obs)
    assert time.perf_counter() - t < 20
    assert r.range_exponent == pytest.approx(2.0, abs=0.02)
    np.testing.assert_allclose(r.beam_gains, gains, rtol=0.03)


def test_intensity_statistics():
    rng = np.random.default_rng(1)
    n = 20000
    d = rng.uniform(3, 30, n)
    phi = rng.uniform(-np.pi, np.pi, n)
    r_xy = np.sqrt(np.maximum(d ** 2 - 1.73 ** 2, 0))
    pts = np.stack([r_xy * np.cos(phi), r_xy * np.sin(phi), np.full(n, -1.73),
                    rng.normal(0.16, 0.02, n)], 1)
    rows = intensity_statistics(pts, [(3, 5), (8, 12), (20, 30)], mask=ground_mask(pts))
    assert [r["n"] > 0 for r in rows] == [True] * 3
    for r in rows:
        assert r["median"] == pytest.approx(0.16, abs=0.005)
    assert rows[2]["inv_d2"] < 0.05    # cos/d^2 falls, the reflectivity does not
    assert "median" in format_statistics(rows)
    empty = intensity_statistics(pts, [100, 200])
    assert empty[0]["n"] == 0 and np.isnan(empty[0]["median"])


def test_kitti_excerpt_is_reflectivity(kitti_dir):
    """The shared excerpt's ground: ~0.16 at every range (range-compensated)."""
    import glob
    from mi_invrgbl.io.velodyne import read_velodyne
    files = sorted(glob.glob(str(kitti_dir / "**" / "velodyne_points" / "data" / "*.bin"),
                             recursive=True))
    if not files:
        pytest.skip("no sweeps")
    xyz, inten = read_velodyne(files[0])
    pts = np.column_stack([xyz, inten])
    rows = intensity_statistics(pts, [(3, 5), (8, 12), (20, 30)], mask=ground_mask(pts))
    for r in rows:
        assert r["n"] > 100
        assert 0.1 < r["median"] < 0.25
