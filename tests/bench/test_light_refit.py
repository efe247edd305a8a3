"""``light_refit.py``: a finished fit's stage 2 rebuilt from its checkpoint,
with fields taken from a variant and held while the rest is fitted, and
the result written beside the fit without touching it."""

import os
import pathlib
import sys

import numpy as np
import pytest

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

import light_refit as lr  # noqa: E402
from fit_scene import build, small_config  # noqa: E402
from normal_oracle import write_edited  # noqa: E402
from mi_invrgbl.fit.runner import run_fit  # noqa: E402
from mi_invrgbl.fit.variables import GaussianVariable  # noqa: E402
from mi_invrgbl.physics.fields import BY_NAME  # noqa: E402
from mi_invrgbl.physics.gaussian_ply import read_ply  # noqa: E402


def _albedo(state):
    node = state.model.nodes["background"]
    return np.array(node.values[BY_NAME["albedo"].variable]).reshape(-1, 3)


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    d = tmp_path_factory.mktemp("refit")
    scene = build(str(d / "scene"), n_frames=5, width=48, height=16, columns=128)
    fit = d / "fit"
    run_fit(scene, small_config(fit, stage2_iterations=8), log=lambda *a: None)
    return fit


def _files(folder):
    return {p.name: p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def test_held_fields_stay_where_the_variant_put_them_and_the_fit_is_untouched(fitted):
    before = _files(fitted)

    def grey(cloud):
        cloud.albedo = np.full_like(cloud.albedo, 0.3)
    variant = write_edited(str(fitted), "grey", grey)
    state, stage2 = lr.open_stage2(str(fitted))
    assert not np.allclose(_albedo(state), 0.3)
    lr.replace_field(state, variant, "albedo")
    assert np.allclose(_albedo(state), 0.3, atol=1e-6)
    stage2.build_optimizer(only=lambda v: not (isinstance(v, GaussianVariable) and v.field.name == "albedo"))
    assert not any(k.endswith(".albedo") for k in stage2.opt.variables)
    sky0 = np.array(state.params[state.sky_key])
    for it in range(3):
        stage2.iteration(it)
    stage2.commit()
    # The held albedo did not move; the light did.
    assert np.allclose(_albedo(state), 0.3, atol=1e-6)
    assert not np.allclose(np.array(state.params[state.sky_key]), sky0)
    target = lr.variant_folder(str(fitted), "refit")
    lr.write_fit(state, stage2, target)
    written = read_ply(os.path.join(target, "background.ply"))
    assert np.allclose(written.albedo, 0.3, atol=1e-6)
    assert os.path.isfile(os.path.join(target, "scene.xml"))
    assert _files(fitted) == before
    # No temporary folder is left beside them.
    assert sorted(p.name for p in fitted.parent.iterdir()) == ["fit", "fit_grey", "fit_refit", "scene"]


def test_a_variant_of_other_gaussians_is_refused(fitted, tmp_path):
    state, _ = lr.open_stage2(str(fitted))
    other = tmp_path / "other"
    other.mkdir()
    cloud = read_ply(str(fitted / "background.ply"))
    from mi_invrgbl.physics.gaussian_ply import write_ply
    cloud.albedo = cloud.albedo[:-1]
    for f in ("centers", "scales", "quaternions", "opacities", "normals", "roughness",
              "lidar_albedo", "sun_visibility"):
        if getattr(cloud, f, None) is not None:
            setattr(cloud, f, getattr(cloud, f)[:-1])
    write_ply(str(other / "background.ply"), cloud)
    with pytest.raises(SystemExit, match="Gaussians, the fit's node 'background'"):
        lr.replace_field(state, str(other), "albedo")


def test_an_unfinished_fit_is_refused(tmp_path):
    with pytest.raises(SystemExit, match="no checkpoint"):
        lr.read_meta(str(tmp_path))


def test_roughness_taken_from_a_variant_is_held_while_the_light_moves(fitted):
    def rough(cloud):
        cloud.roughness = np.full_like(cloud.roughness, 0.85)
    variant = write_edited(str(fitted), "rough", rough)
    state, stage2 = lr.open_stage2(str(fitted))
    node = state.model.nodes["background"]
    key = BY_NAME["roughness"].variable
    assert not np.allclose(np.array(node.values[key]), 0.85)
    lr.replace_field(state, variant, "roughness")
    stage2.build_optimizer(only=lambda v: not (isinstance(v, GaussianVariable)
                                               and v.field.name == "roughness"))
    sky0 = np.array(state.params[state.sky_key])
    for it in range(3):
        stage2.iteration(it)
    stage2.commit()
    assert np.allclose(np.array(node.values[key]), 0.85, atol=1e-6)
    assert not np.allclose(np.array(state.params[state.sky_key]), sky0)


def test_a_bench_output_file_that_exists_is_refused_and_new_ones_are_written_whole(tmp_path, monkeypatch):
    import street_truth
    mine = tmp_path / "mine.json"
    mine.write_text("the user's")
    with pytest.raises(SystemExit, match="mine.json: exists; not overwritten"):
        street_truth.refuse_existing(None, str(mine))
    assert mine.read_text() == "the user's"
    out = tmp_path / "rows.json"
    street_truth.refuse_existing(str(out))
    street_truth.write_json(str(out), {"rows": [1, 2]})
    import json
    assert json.loads(out.read_text()) == {"rows": [1, 2]}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine.json", "rows.json"]
    # light_refit refuses before it loads anything.
    monkeypatch.setattr(sys, "argv", ["light_refit.py", str(tmp_path / "nofit"), "--json", str(mine)])
    with pytest.raises(SystemExit, match="exists; not overwritten"):
        lr.main()
