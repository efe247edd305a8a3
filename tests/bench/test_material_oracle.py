"""``material_oracle.py``: the truth's materials found for points near its
surfaces, and the edited scene written next to a fit (no renders)."""

import json
import pathlib
import sys

import numpy as np
import trimesh

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))

import material_oracle as mo  # noqa: E402
from test_normal_oracle import _fit, _listing  # noqa: E402
from mi_invrgbl.physics.gaussian_ply import read_ply  # noqa: E402


def _truth(tmp_path):
    gt = tmp_path / "gt"
    (gt / "meshes").mkdir(parents=True)
    square = lambda z: trimesh.Trimesh([[0, 0, z], [2, 0, z], [2, 2, z], [0, 2, z]],  # noqa: E731
                                       [[0, 1, 2], [0, 2, 3]], process=False)
    square(0.0).export(str(gt / "meshes" / "ground.ply"))
    square(5.0).export(str(gt / "meshes" / "glass.ply"))
    square(2.5).export(str(gt / "meshes" / "car.ply"))
    (gt / "materials.json").write_text(json.dumps({
        "meshes": [{"name": "ground", "file": "meshes/ground.ply", "material": "rough", "dynamic": False},
                   {"name": "glass", "file": "meshes/glass.ply", "material": "smooth", "dynamic": False},
                   {"name": "car", "file": "meshes/car.ply", "material": "paint", "dynamic": True}],
        "materials": {"rough": {"roughness": 0.9, "albedo": [0.4, 0.3, 0.2]},
                      "smooth": {"roughness": 0.08, "albedo": [0.04, 0.05, 0.06]},
                      "paint": {"roughness": 0.2, "albedo": [0.0, 0.0, 1.0]}}}))
    return gt


def test_points_carry_their_static_surface_material(tmp_path):
    points, rough, alb = mo.sample_materials(_truth(tmp_path), density=100.0)
    assert len(points) == len(rough) == len(alb) >= 200
    # The third query stands where the moving car is: 2 m above the ground.
    pick, dist = mo.nearest_points(points, np.array([[1.0, 1.0, 0.05], [1.0, 1.0, 4.9], [1.0, 1.0, 2.0]]))
    assert rough[pick].tolist() == [0.9, 0.08, 0.9]
    assert np.allclose(alb[pick[0]], [0.4, 0.3, 0.2]) and np.allclose(alb[pick[1]], [0.04, 0.05, 0.06])
    # The moving car is not a static surface: nothing is sampled on it.
    assert not np.any(np.isclose(points[:, 2], 2.5))
    assert dist[0] < 0.2 and dist[1] < 0.2 and dist[2] > 1.9


def test_an_edit_writes_a_sibling_and_keeps_the_fit(tmp_path):
    fit = _fit(tmp_path)
    before = (fit / "background.ply").read_bytes()

    def edit(cloud):
        cloud.roughness = np.full(len(cloud.centers), 0.25, np.float32)
    target = pathlib.Path(mo.write_edited(str(fit), "true roughness", edit))
    assert target.name == "fit_8min_true_roughness"
    assert np.allclose(read_ply(str(target / "background.ply")).roughness, 0.25)
    assert (fit / "background.ply").read_bytes() == before
    assert _listing(tmp_path) == ["fit_8min", "fit_8min_true_roughness"]
