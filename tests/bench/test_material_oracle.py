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


def test_a_textured_surface_gives_its_texture_at_the_point(tmp_path):
    # A 2 m square whose texture is white for u < 0.5 and black beyond:
    # points on the square's first metre (u = x / 2 < 0.5) read white, the
    # rest black, as Mitsuba's bitmap reads the sRGB image; --nominal's
    # single value stays the material's.
    import cv2
    gt = tmp_path / "gt"
    (gt / "meshes").mkdir(parents=True)
    (gt / "textures").mkdir()
    image = np.zeros((8, 16, 3), np.uint8)
    image[:, :8] = 255
    cv2.imwrite(str(gt / "textures" / "paint.png"), image)
    square = trimesh.Trimesh([[0, 0, 0], [2, 0, 0], [2, 2, 0], [0, 2, 0]], [[0, 1, 2], [0, 2, 3]],
                             process=False)
    square.visual = trimesh.visual.TextureVisuals(uv=square.vertices[:, :2] / 2.0)
    square.export(str(gt / "meshes" / "ground.ply"))
    (gt / "materials.json").write_text(json.dumps({
        "meshes": [{"name": "ground", "file": "meshes/ground.ply", "material": "road", "dynamic": False}],
        "materials": {"road": {"roughness": 0.9, "albedo": [0.1, 0.1, 0.1],
                               "albedo_texture": "textures/paint.png"}}}))
    points, _, alb = mo.sample_materials(gt, density=400.0)
    # Away from the bilinear seams: the edge at x = 1 and, as the texture
    # repeats, its wrap at x = 0 and 2.
    inner = np.min(np.abs(points[:, :1] - [0.0, 1.0, 2.0]), axis=1) > 0.1
    white = points[:, 0] < 1.0
    assert np.allclose(alb[inner & white], 1.0, atol=1e-3)
    assert np.allclose(alb[inner & ~white], 0.0, atol=1e-3)
    _, _, nominal = mo.sample_materials(gt, density=400.0, textures=False)
    assert np.allclose(nominal, 0.1)


def test_the_channel_scale_is_the_least_squares_level():
    truth = np.array([[0.2, 0.1, 0.4], [0.4, 0.3, 0.1]])
    assert np.allclose(mo.channel_scale(1.5 * truth, truth), 1.5)
    fitted = truth * [2.0, 0.5, 1.0] + [[0.01, -0.01, 0.0], [-0.005, 0.0033, 0.0]]
    s = mo.channel_scale(fitted, truth)
    # Least squares: the residual is orthogonal to the truth in each channel.
    assert np.allclose(np.sum((fitted - s * truth) * truth, axis=0), 0.0, atol=1e-12)
    assert np.all(np.isfinite(mo.channel_scale(fitted, np.zeros_like(truth))))


def test_the_albedo_floor_solves_the_least_squares_problem():
    # cgls against numpy's dense least squares on a random sparse system of
    # two "frames"; a column no row touches keeps its start value.
    import albedo_floor as af
    rng = np.random.default_rng(3)
    frames, dense = [], []
    for n_rows in (40, 25):
        rows = np.repeat(np.arange(n_rows), 3)
        cols = rng.integers(0, 9, rows.size)          # column 9 is never hit
        vals = rng.uniform(0.1, 1.0, rows.size)
        target = rng.uniform(0.0, 1.0, (n_rows, 3))
        frames.append(af.Rows(rows, cols, vals, target, np.ones((1, n_rows), bool),
                              np.zeros(n_rows, np.int64)))
        A = np.zeros((n_rows, 10))
        np.add.at(A, (rows, cols), vals)
        dense.append((A, target))
    A = np.concatenate([a for a, _ in dense])
    b = np.concatenate([t for _, t in dense])
    x0 = np.full((10, 3), 0.5)
    x = af.cgls(frames, x0, 60)
    best = np.linalg.lstsq(A[:, :9], b, rcond=None)[0]
    assert np.allclose(x[:9], best, atol=1e-6) and np.allclose(x[9], 0.5)
    # A frame's score is eval's: the scaled RMSE of the rendered rows.
    pred = frames[0].apply(x)
    img = lambda v: v.reshape(1, -1, 3)  # noqa: E731
    assert np.isclose(frames[0].score(x), af.M.albedo_rmse_scaled(img(pred), img(frames[0].target)))


def test_the_normal_descent_keeps_unit_normals_and_finds_consistent_ones():
    # Pixels blending unit normals (one alone, two halves): targets made from
    # known normals are met from a random unit start, every solved normal is
    # unit length, and the rows' targets are left as they were.
    import albedo_floor as af
    rng = np.random.default_rng(5)
    truth = af.unit(rng.normal(size=(6, 3)) + [0.0, 0.0, 2.0])
    rows = np.array([0, 1, 2, 3, 4, 5, 6, 6, 7, 7, 8, 8])
    cols = np.array([0, 1, 2, 3, 4, 5, 0, 1, 2, 3, 4, 5])
    vals = np.array([1.0] * 6 + [0.5] * 6)
    blend = np.zeros((9, 3))
    np.add.at(blend, rows, vals[:, None] * truth[cols])
    target = af.unit(blend)
    r = af.Rows(rows, cols, vals, target.copy(), np.ones((1, 9), bool), np.zeros(9, np.int64),
                kind="normal")
    start = af.unit(rng.normal(size=(6, 3)))
    assert r.score(start) > 20.0
    x = af.descend_normals([r], start, 600, 0.02)
    assert np.allclose(np.linalg.norm(x, axis=1), 1.0) and np.array_equal(r.target, target)
    assert r.score(x) < 1.0 and np.allclose(x, truth, atol=3e-2)


def test_an_edit_of_several_clouds_edits_each_and_copies_the_rest(tmp_path):
    # write_edited with {ply name: edit}: each named cloud is edited, a cloud
    # it does not name is copied as it is, and the fit is left unchanged.
    import shutil
    fit = _fit(tmp_path)
    shutil.copy2(fit / "background.ply", fit / "object_0.ply")
    shutil.copy2(fit / "background.ply", fit / "object_1.ply")
    before = {p.name: p.read_bytes() for p in fit.iterdir()}

    def grey(value):
        def edit(cloud):
            cloud.albedo = np.full_like(cloud.albedo, value)
        return edit
    target = pathlib.Path(mo.write_edited(str(fit), "albedo floor",
                                          {"background.ply": grey(0.2), "object_0.ply": grey(0.7)}))
    assert target.name == "fit_8min_albedo_floor"
    assert np.allclose(read_ply(str(target / "background.ply")).albedo, 0.2)
    assert np.allclose(read_ply(str(target / "object_0.ply")).albedo, 0.7)
    assert (target / "object_1.ply").read_bytes() == before["object_1.ply"]
    assert {p.name: p.read_bytes() for p in fit.iterdir()} == before
