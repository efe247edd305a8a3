"""Ray drop as a model and LiDAR novel-view scoring on raw points."""

import numpy as np
import pytest
import mitsuba as mi

from mi_invrgbl.physics.lidar_response import ReturnModel, return_scores
from mi_invrgbl.fit.response import fit_return_model
from mi_invrgbl.eval.lidar_novel_view import PointCloudCaster, _beam_of


def test_return_model_is_recovered():
    rng = np.random.default_rng(0)
    n, B = 40000, 4
    d = rng.uniform(2, 60, n)
    c = rng.uniform(0.02, 1, n)
    rho = rng.uniform(0.02, 1, n)
    beam = rng.integers(0, B, n)
    truth = ReturnModel(np.array([-3.0, 1.5, 1.2]), np.array([9.0, 9.5, 8.5, 10.0]))
    p = truth.probability_np(d, c, rho, beam)
    y = rng.random(n) < p
    fit = fit_return_model(d, c, rho, beam, y, B, beam_l2=1e-3)
    assert np.allclose(fit.weights, truth.weights, atol=0.15), fit.weights
    assert np.allclose(fit.beam_bias, truth.beam_bias, atol=0.5), fit.beam_bias
    s = return_scores(y, fit.logit_np(d, c, rho, beam) >= 0)
    best = return_scores(y, p >= 0.5)
    assert s["accuracy"] > best["accuracy"] - 0.005


def test_return_scores():
    s = return_scores([1, 1, 0, 0, 1], [1, 0, 0, 1, 1])
    # drop class: truth [0,0,1,1,0], predicted [0,1,1,0,0] -> tp 1, fp 1, fn 1
    assert s["accuracy"] == pytest.approx(0.6) and s["f1"] == pytest.approx(0.5)


def plane_scene(elev, width=16, h=2.0):
    return mi.load_dict({
        "type": "scene",
        "plane": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale(1000.0),
                  "bsdf": {"type": "cooktorrance", "lidar_albedo": 0.5, "roughness": 0.6}},
        "lidar": {"type": "lidar", "elevations": ",".join("%g" % e for e in elev), "far_clip": 1000.0,
                  "to_world": mi.ScalarTransform4f().translate([0, 0, h]),
                  "film": {"type": "hdrfilm", "width": width, "height": len(elev),
                           "rfilter": {"type": "box"}}}})


def test_integrator_drops_weak_returns():
    """Return iff bias - 3 log d >= 0: beams meeting the ground beyond e^(bias/3) drop."""
    elev = np.array([-2.0, -5.0, -10.0, -30.0])
    h = 2.0
    dist = h / np.sin(-np.radians(elev))           # 57.3, 22.9, 11.5, 4.0 m
    bias = 3 * np.log(15.0)
    scene = plane_scene(elev, h=h)
    integ = mi.load_dict({"type": "lidar_return", "return_weights": "-3, 0, 0",
                          "return_bias": "%.12g" % bias})
    img = np.array(mi.render(scene, integrator=integ))
    hit = img[..., 2] > 0.5
    assert np.array_equal(hit.all(axis=1), dist <= 15.0) and np.array_equal(hit.any(axis=1), dist <= 15.0)
    # Sampled: each beam returns with its probability.
    p = 1 / (1 + np.exp(-(bias - 3 * np.log(dist))))
    integ_s = mi.load_dict({"type": "lidar_return", "return_weights": "-3, 0, 0",
                            "return_bias": "%.12g" % bias, "sample_drop": True, "seed": 3})
    scene = plane_scene(elev, width=4000, h=h)
    rate = (np.array(mi.render(scene, integrator=integ_s))[..., 2] > 0.5).mean(axis=1)
    assert np.allclose(rate, p, atol=0.03), (rate, p)
    with pytest.raises(Exception, match="return_weights"):
        mi.load_dict({"type": "lidar_return", "return_weights": "1, 2"})


def test_point_cloud_caster():
    xs = np.arange(-20, 20, 0.05)
    X, Y = np.meshgrid(xs, xs)
    pts = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], 1)
    caster = PointCloudCaster(pts)
    d = np.array([[1.0, 0, -1.0], [0.3, 0.2, -1.0], [1.0, 0.0, 0.2]])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = caster.cast([0, 0, 3.0], d, 0.5, 80.0)
    expect = 3.0 / -d[:2, 2]
    assert np.all(np.abs(r[:2] - expect) < 0.35) and r[2] == 0


def test_beam_of_nearest_elevation():
    table = np.radians([2.0, 0.0, -5.0])
    d = np.array([[1, 0, np.tan(np.radians(1.2))], [1, 0, np.tan(np.radians(-3.0))], [1, 0, -1.0]])
    assert list(_beam_of(d, table)) == [0, 2, 2]


@pytest.mark.slow
def test_fitted_street_beats_the_lookup_on_raw_points(tmp_path):
    """make-scene (VLP-32C) -> import -> a short fit: the fit writes a ray-drop
    model, and on held-out raw points the scene's LiDAR beats the lookup built
    from every training point (intensity and range), its ray drop better than
    without the model."""
    import os
    import subprocess
    import sys
    import xml.etree.ElementTree as ET
    from mi_invrgbl.eval.lidar_novel_view import score_scene
    env = dict(os.environ, PYTHONPATH=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

    def cli(*args):
        r = subprocess.run([sys.executable, "-m", "mi_invrgbl_main", *args], cwd=tmp_path, env=env,
                           capture_output=True, text=True)
        assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
        return r.stdout

    cli("make-scene", "street", "st", "--frames", "10", "--width", "64", "--height", "24", "--spp", "2",
        "--azimuth-steps", "512", "--lidar", "vlp32", "--no-night")
    out = cli("import", "st", "-o", "imp/scene.xml", "--max-points", "20000", "--azimuth-steps", "512")
    assert "32 beams, non-uniform" in out
    out = cli("fit", "imp/scene.xml", "--stage1", "30", "--stage2", "40", "--width", "64",
              "--lidar-columns", "256", "--batch", "2048", "--samples", "4", "--render-samples", "4",
              "--eval-every", "100")
    assert "ray-drop model" in out
    fit = tmp_path / "imp" / "fit"
    integ = ET.parse(fit / "scene_lidar.xml").getroot().find("integrator")
    assert {e.get("name") for e in integ} >= {"return_weights", "return_bias"}
    res = score_scene(fit / "scene.xml", log=lambda *a: None)
    m, b = res["raw_points"]["model"], res["raw_points"]["baseline"]
    assert m["intensity_rmse"] < 0.8 * b["intensity_rmse_on_model_returns"]
    assert m["range_mae"] < b["range_mae"]
    assert m["drop_accuracy"] > b["drop_accuracy"]
    # Without the ray-drop model (every beam reaching a surface returns).
    for e in [e for e in integ if e.get("name", "").startswith("return_")]:
        integ.remove(e)
    bare = tmp_path / "bare_lidar.xml"
    ET.ElementTree(ET.Element("scene", {"version": "3.0.0"})).write(bare)
    root = ET.parse(bare).getroot()
    root.append(integ)
    ET.ElementTree(root).write(bare)
    res0 = score_scene(fit / "scene.xml", bare, log=lambda *a: None)
    assert m["drop_accuracy"] > res0["raw_points"]["model"]["drop_accuracy"]
    assert m["drop_f1"] > res0["raw_points"]["model"]["drop_f1"]
