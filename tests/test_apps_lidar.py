"""``mi-invrgbl lidar``: simulated sweeps vs the synthetic street's own scans.

The generator scans its street by ray casting with the paper's LiDAR model
plus noise (range sigma 1 cm, intensity 2 %) and 2 % random ray drop. The
command re-simulates the same frames from the ground-truth scene with the
``lidar_return`` integrator (true LiDAR albedo swapped in from
``materials.json``). On beams both report:

* intensity RMSE below ``INTENSITY_RMSE`` (absolute, intensities in [0, 1])
  and below ``INTENSITY_REL`` of the mean intensity;
* median absolute range error below ``RANGE_MEDIAN_M``;
* returns the generator has and the simulation lacks: below ``MISSING``;
  returns only the simulation has: about the generator's drop rate.

Measured (64 x 512, 2 frames): intensity RMSE 2e-4 (2.5 % of the mean, the
generator's noise), median range error 7 mm (its 1 cm noise), missing 0.0 %,
extra 2.0 %.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import mitsuba as mi

from mi_invrgbl.cli import main
from mi_invrgbl.io.velodyne import read_velodyne
from mi_invrgbl.synthetic import StreetConfig, generate_street
from mi_invrgbl.synthetic.writers import read_exr
import variant_choice

CFG = dict(seed=4, frames=2, width=32, height=16, spp=1, azimuth_steps=512, night=False)
INTENSITY_RMSE = 0.002
INTENSITY_REL = 0.1
RANGE_MEDIAN_M = 0.015
MISSING = 0.005
STREET_XML = __import__("os").path.join(__import__("os").path.dirname(__import__("os").path.dirname(
    __import__("os").path.abspath(__file__))), "scenes", "street.xml")


@pytest.fixture(scope="module")
def street(tmp_path_factory):
    variant_choice.use()
    import mi_invrgbl  # noqa: F401
    out = tmp_path_factory.mktemp("lidar") / "street"
    generate_street(str(out), StreetConfig(**CFG), log=lambda *a: None)
    return out


@pytest.fixture(scope="module")
def simulated(street, tmp_path_factory):
    out = tmp_path_factory.mktemp("lidar_out") / "sim"
    assert main(["lidar", str(street / "gt" / "scene_time_a.xml"), "-o", str(out)]) == 0
    return out


def test_simulation_matches_the_generators_scans(street, simulated):
    drop = json.loads((street / "gt" / "trajectory.json").read_text())["lidar"]["drop_rate"]
    for frame in range(CFG["frames"]):
        sim = read_exr(str(simulated / ("frame_%04d.exr" % frame)))
        gt = read_exr(str(street / "gt" / "lidar" / ("%06d.exr" % frame)))
        assert sim["range"].shape == gt["range"].shape == (64, CFG["azimuth_steps"])
        s_hit, g_hit = sim["hit"] > 0, gt["hit"] > 0
        both = s_hit & g_hit
        rmse = float(np.sqrt(np.mean((sim["intensity"][both] - gt["intensity"][both]) ** 2)))
        mean = float(gt["intensity"][both].mean())
        err = np.abs(sim["range"][both] - gt["range"][both])
        missing, extra = float(np.mean(g_hit & ~s_hit)), float(np.mean(s_hit & ~g_hit))
        print("frame %d: intensity RMSE %.5f (mean %.4f, %.1f %%), range error median %.4f m, "
              "mean %.4f m, p99 %.3f m; returns missing %.2f %%, extra %.2f %% (drop rate %.0f %%)"
              % (frame, rmse, mean, 100 * rmse / mean, np.median(err), err.mean(),
                 np.percentile(err, 99), 100 * missing, 100 * extra, 100 * drop))
        assert rmse < INTENSITY_RMSE and rmse < INTENSITY_REL * mean
        assert np.median(err) < RANGE_MEDIAN_M
        assert missing < MISSING
        assert abs(extra - drop) < 0.01


def test_kitti_bin_points_lie_on_the_generators_points(street, simulated):
    from mi_invrgbl.eval.baselines import NearestNeighbourIntensity
    points, intensity = read_velodyne(str(simulated / "frame_0000.bin"))
    sim = read_exr(str(simulated / "frame_0000.exr"))
    assert len(points) == int(np.sum(sim["hit"] > 0))
    assert np.all((intensity >= 0) & (intensity <= 1))
    ref, _ = read_velodyne(str(street / "sequences" / "00" / "velodyne" / "000000.bin"))
    _, d = NearestNeighbourIntensity(ref, np.zeros(len(ref))).query(points)
    print("KITTI .bin: %d points, nearest generator point median %.4f m" % (len(points), np.median(d)))
    assert np.median(d) < 0.03
    # Sensor frame: x forward, y left, z up; the road is about 1.73 m below the sensor.
    ground = points[np.abs(points[:, 1]) < 2] if len(points) else points
    assert np.percentile(ground[:, 2], 5) == pytest.approx(-1.73, abs=0.1)
    assert (simulated / "frame_0000.png").is_file() and (simulated / "frame_0000_range.png").is_file()
    assert (simulated / "sequence.mp4").is_file() or (simulated / "sequence.gif").is_file()


def test_new_poses_and_sensors(street, tmp_path):
    out = tmp_path / "vlp16"
    assert main(["lidar", str(street / "gt" / "scene_time_a.xml"), "--pose", "5,-1.75,1.73,10",
                 "--pose", "6,-1.75,1.73", "--sensor", "vlp16", "-o", str(out)]) == 0
    a = read_exr(str(out / "frame_0000.exr"))
    assert a["range"].shape == (16, 1800) and np.mean(a["hit"]) > 0.3
    custom = tmp_path / "sensor.json"
    custom.write_text(json.dumps({"elevations_deg": [0, -10, -20], "azimuth_steps": 90, "far_clip": 50}))
    out = tmp_path / "custom"
    assert main(["lidar", str(street / "gt" / "scene_time_a.xml"), "--pose", "5,-1.75,1.73",
                 "--sensor", str(custom), "-o", str(out)]) == 0
    c = read_exr(str(out / "frame_0000.exr"))
    assert c["range"].shape == (3, 90)
    assert 'name="far_clip" value="50"' in (out / "scene.xml").read_text()
    # The -20 degree beam straight ahead meets the road at 1.73 / tan(20 deg) = 4.75 m.
    assert c["range"][2, 45] == pytest.approx(1.73 / np.sin(np.radians(20)), rel=0.02)
    rays = tmp_path / "rays.json"
    rays.write_text(json.dumps({"rays": [[0, 0, 0, 0, 0, -1], [0, 0, 0, 1, 0, -1]]}))
    out = tmp_path / "rays"
    assert main(["lidar", str(street / "gt" / "scene_time_a.xml"), "--pose", "5,-1.75,1.73",
                 "--sensor", str(rays), "-o", str(out)]) == 0
    r = read_exr(str(out / "frame_0000.exr"))
    assert r["range"].ravel() == pytest.approx([1.73, 1.73 * np.sqrt(2)], rel=0.01)


def test_far_clip_limits_the_range(street, tmp_path):
    custom = tmp_path / "sensor.json"
    custom.write_text(json.dumps({"elevations_deg": [0, -10, -20], "azimuth_steps": 90, "far_clip": 30}))
    out = tmp_path / "custom"
    assert main(["lidar", str(street / "gt" / "scene_time_a.xml"), "--pose", "5,-1.75,1.73",
                 "--sensor", str(custom), "-o", str(out)]) == 0
    assert read_exr(str(out / "frame_0000.exr"))["range"].max() <= 30


def test_fitted_response_is_used(tmp_path):
    """A fit's scene_lidar.xml next to the scene supplies the sensor response."""
    folder = tmp_path / "fit"
    folder.mkdir()
    scene = ('<scene version="3.0.0"><integrator type="%s"/>'
             '<shape type="rectangle"><transform name="to_world"><scale value="50"/></transform>'
             '<bsdf type="cooktorrance"><float name="lidar_albedo" value="0.4"/>'
             '<float name="roughness" value="1"/></bsdf></shape></scene>')
    (folder / "scene.xml").write_text(scene % "invrgbl")
    (folder / "scene_lidar.xml").write_text(scene.replace(
        '<integrator type="%s"/>', '<integrator type="lidar_return"><float name="range_exponent" '
        'value="0"/><float name="angle_exponent" value="0"/><string name="beam_gains" value="%s"/>'
        '</integrator>') % ", ".join(["2"] * 64))
    out = tmp_path / "out"
    assert main(["lidar", str(folder / "scene.xml"), "--pose", "0,0,2", "--sensor", "vlp16",
                 "-o", str(out)]) == 0
    ch = read_exr(str(out / "frame_0000.exr"))
    hit = ch["hit"] > 0
    # Fitted exponents 0 (reflectivity, as KITTI's): I = g (rho + spec) / pi at every range
    # and angle; the 64 fitted gains (2) do not fit 16 beams and become their mean.
    values = ch["intensity"][hit]
    assert hit.sum() > 1000 and np.ptp(ch["range"][hit]) > 20
    assert values.std() < 0.05 * values.mean()
    assert values.mean() == pytest.approx(2 * 0.42 / np.pi, rel=0.05)
    xml = (out / "scene.xml").read_text()
    assert 'name="range_exponent" value="0"' in xml and 'name="beam_gains" value="2"' in xml


def test_gaussian_scene_from_its_own_lidar_pose(tmp_path):
    out = tmp_path / "street"
    assert main(["lidar", STREET_XML, "--azimuth-steps", "256", "-o", str(out)]) == 0
    ch = read_exr(str(out / "frame_0000.exr"))
    assert ch["range"].shape == (64, 256) and np.mean(ch["hit"]) > 0.4


@pytest.mark.parametrize("args, message", [
    (["--pose", "500,0,1.7"], "lies outside the scene"),
    (["--pose", "5,0,1.7", "--sensor", "hdl32"], "expected hdl64, vlp32, vlp16, scene or a .json"),
    (["--pose", "5,0,1.7", "--sensor", "BADJSON"], "not valid JSON"),
    (["--pose", "5,0,1.7", "--sensor", "NOBEAMS"], "give 'elevations_deg'"),
    (["--trajectory", "/nonexistent/poses.txt"], "trajectory file not found"),
    (["--pose", "5,0,1.7", "--drop-rate", "1.5"], "--drop-rate must lie in [0, 1)"),
])
def test_bad_input_gives_one_clear_error(street, tmp_path, capsys, args, message):
    (tmp_path / "bad.json").write_text("{elevations: [1, 2]")
    (tmp_path / "nobeams.json").write_text('{"azimuth_steps": 10}')
    args = [{"BADJSON": str(tmp_path / "bad.json"), "NOBEAMS": str(tmp_path / "nobeams.json")}.get(a, a)
            for a in args]
    code = main(["lidar", str(street / "gt" / "scene_time_a.xml"), "-o", str(tmp_path / "o")] + args)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and message in err[0], err


def test_scene_without_lidar_poses_asks_for_one(tmp_path, capsys):
    scene = tmp_path / "plain.xml"
    scene.write_text('<scene version="3.0.0"><shape type="sphere"/></scene>')
    assert main(["lidar", str(scene), "-o", str(tmp_path / "o")]) == 2
    assert "give --pose or --trajectory" in capsys.readouterr().err
