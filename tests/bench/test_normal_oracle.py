"""``normal_oracle.py --write``: the edited scenes it writes next to a fit,
and what it refuses (no renders: a hand-made fit folder)."""

import os
import pathlib
import sys

import numpy as np
import pytest

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))

import normal_oracle as no  # noqa: E402
from mi_invrgbl.physics.gaussian_ply import GaussianCloud, read_ply, write_ply  # noqa: E402


def _fit(tmp_path, n=4):
    fit = tmp_path / "fit_8min"
    fit.mkdir()
    write_ply(str(fit / "background.ply"), GaussianCloud(
        centers=np.arange(3 * n, dtype=np.float32).reshape(n, 3),
        scales=np.full((n, 3), 0.1, np.float32),
        quaternions=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
        opacities=np.full(n, 0.9, np.float32),
        normals=np.tile(np.float32([0, 0, 1]), (n, 1)),
        albedo=np.full((n, 3), 0.5, np.float32),
        roughness=np.full(n, 0.5, np.float32),
        lidar_albedo=np.full(n, 0.3, np.float32),
        sun_visibility=np.ones(n, np.float32)))
    for name in no.SCENE_FILES:
        (fit / name).write_text("<!-- %s -->\n" % name)
    return fit


def _listing(folder):
    return sorted(p.name for p in folder.iterdir())


def test_write_variant_edits_only_the_background_and_keeps_the_fit(tmp_path):
    fit = _fit(tmp_path)
    before = {p.name: p.read_bytes() for p in fit.iterdir()}
    normals = np.tile(np.float32([1, 0, 0]), (4, 1))
    opacities = np.float32([0.9, 0.0, 0.9, 0.0])
    target = pathlib.Path(no.write_variant(str(fit), "on-surface only", normals, opacities))
    assert target == tmp_path / "fit_8min_on_surface_only"
    assert _listing(target) == _listing(fit)
    for name in no.SCENE_FILES:
        assert (target / name).read_bytes() == before[name]
    cloud = read_ply(str(target / "background.ply"))
    np.testing.assert_allclose(cloud.normals, normals, atol=1e-6)
    # Opacity 0 is written as the smallest storable one, not -inf.
    assert np.all(np.isfinite(cloud.opacities)) and np.all(cloud.opacities[[1, 3]] <= 1e-5)
    np.testing.assert_allclose(cloud.opacities[[0, 2]], 0.9, atol=1e-5)
    # The fit itself is untouched, and no temporary folder is left beside it.
    assert {p.name: p.read_bytes() for p in fit.iterdir()} == before
    assert _listing(tmp_path) == ["fit_8min", "fit_8min_on_surface_only"]


def test_write_variant_refuses_an_existing_folder(tmp_path):
    fit = _fit(tmp_path)
    taken = tmp_path / "fit_8min_true_normals"
    taken.mkdir()
    (taken / "mine.txt").write_text("a user's file")
    with pytest.raises(SystemExit, match="exists; not overwritten"):
        no.write_variant(str(fit), "true normals", np.zeros((4, 3)), np.ones(4))
    assert _listing(taken) == ["mine.txt"] and (taken / "mine.txt").read_text() == "a user's file"


def test_write_variant_leaves_nothing_when_it_fails(tmp_path):
    fit = _fit(tmp_path)
    with pytest.raises(Exception):
        # One normal too few for the four Gaussians: the PLY write fails.
        no.write_variant(str(fit), "both", np.ones((3, 3)), np.ones(4))
    assert _listing(tmp_path) == ["fit_8min"]


def test_write_is_refused_before_anything_is_rendered(tmp_path, monkeypatch):
    # The fit folder holds no real scene: had the run got as far as opening
    # it (or rendering), it would have stopped with another message.
    fit = _fit(tmp_path)
    (tmp_path / "fit_8min_both").mkdir()
    monkeypatch.setattr(sys, "argv", ["normal_oracle.py", str(fit), "--write"])
    with pytest.raises(SystemExit, match="fit_8min_both: exists; not overwritten"):
        no.main()
    monkeypatch.setattr(no, "open_fit", lambda *a, **k: pytest.fail("opened the fit"))
    with pytest.raises(SystemExit, match="exists; not overwritten"):
        no.main()
