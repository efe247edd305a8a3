"""LiDAR odometry checked before use, on a synthetic street with its poses hidden.

``make-scene street`` writes a 12-frame street (1 m per frame, 11 m of
travel); the test copies its KITTI files without ``poses/`` and ``gt/``, so
the import has to estimate the ego poses itself.
"""

from __future__ import annotations

import json
import shutil
import warnings

import numpy as np
import pytest

from mi_invrgbl.cli import main
from mi_invrgbl.io import kitti, odometry
from mi_invrgbl.io.importer import ImportOptions, import_scene

FRAMES = 12
STREET = ["--seed", "3", "--frames", str(FRAMES), "--width", "96", "--height", "32",
          "--azimuth-steps", "512", "--spp", "2", "--no-night"]
OPTS = dict(max_points=20000, azimuth_steps=512)


def _quiet(*_a, **_k):
    pass


@pytest.fixture(scope="module")
def street(tmp_path_factory):
    out = tmp_path_factory.mktemp("odo") / "street"
    assert main(["make-scene", "street", str(out)] + STREET) == 0
    return out


@pytest.fixture(scope="module")
def truth(street):
    T = np.array(json.loads((street / "gt" / "trajectory.json").read_text())["world_from_velo"])
    return np.linalg.inv(T[0]) @ T


@pytest.fixture(scope="module")
def hidden(street, tmp_path_factory):
    """The street's sensors without poses or ground truth."""
    dst = tmp_path_factory.mktemp("odo_hidden") / "data"
    shutil.copytree(street / "sequences", dst / "sequences")
    shutil.copytree(street / "label_02", dst / "label_02")
    return dst


@pytest.fixture(scope="module")
def scans(hidden):
    drive = kitti.read_kitti_odometry(hidden)
    assert drive.poses is None
    return drive, [drive.load_scan(i)[0] for i in range(len(drive))]


def test_ground_removed_odometry_follows_the_street(scans, truth):
    pytest.importorskip("kiss_icp")    # the LiDAR odometry (extra "odometry")
    _, sweeps = scans
    poses = odometry.lidar_odometry([odometry.remove_ground(s) for s in sweeps])
    err = odometry.trajectory_error(poses, truth)
    assert err.path_length_m == pytest.approx(FRAMES - 1, rel=0.01)
    assert err.drift_percent < 2.0, err
    assert odometry.path_length(poses) == pytest.approx(err.path_length_m, rel=0.03)


def test_import_reports_the_checked_trajectory(hidden, truth, tmp_path):
    pytest.importorskip("kiss_icp")    # the LiDAR odometry (extra "odometry")
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)        # no check may disagree here
        report = import_scene(hidden, tmp_path / "s" / "scene.xml", ImportOptions(**OPTS),
                              log=_quiet)
    odo = report.odometry
    true_length = odometry.path_length(truth)
    assert odo["trajectory_length_m"] == pytest.approx(true_length, rel=0.03)
    assert odo["check_speed"] == "agrees" and odo["check_image_motion"] == "agrees"
    assert odo["check_scene_extent"] == "agrees"
    # With the motion right, the parked car stays parked and the moving one moves.
    moving = sorted(o["moving"] for o in report.objects)
    assert moving == [False, True], report.objects


def test_import_prints_the_length(hidden, tmp_path, capsys):
    pytest.importorskip("kiss_icp")    # the LiDAR odometry (extra "odometry")
    assert main(["import", str(hidden), "-o", str(tmp_path / "s" / "scene.xml"), "--frames", "0:4",
                 "--max-points", "20000", "--azimuth-steps", "512"]) == 0
    out = capsys.readouterr().out
    import re
    said = re.search(r"poses by LiDAR odometry \(ground removed\): ([\d.]+) m travelled over "
                     r"4 frames", out)
    summary = re.search(r"\[import\] odometry: .*trajectory_length_m ([\d.]+)", out)
    assert said and summary, out
    assert float(said.group(1)) == pytest.approx(3.0, abs=0.15)
    assert float(summary.group(1)) == pytest.approx(3.0, rel=0.03)


def test_images_measure_the_step(scans, truth, hidden):
    """The image check's own measurement, with the true rotations and with none."""
    drive, sweeps = scans
    import cv2
    images = [cv2.imread(str(p))[:, :, ::-1] for p in drive.image_paths]
    true_steps = np.linalg.norm(np.diff(truth[:, :3, 3], axis=0), axis=1)
    for poses in (truth, np.repeat(np.eye(4)[None], len(truth), 0)):
        deltas = [np.linalg.inv(poses[k]) @ poses[k + 1] for k in range(len(poses) - 1)]
        seen = odometry.image_steps(images, sweeps, drive.K, drive.T_velo_to_cam2, deltas)
        assert np.isfinite(seen).mean() > 0.8
        assert np.nanmedian(seen) == pytest.approx(np.median(true_steps), rel=0.35)


def test_odometry_that_misses_the_motion_is_flagged(hidden, tmp_path, monkeypatch, capsys):
    """Full sweeps on a corridor-like street reported ~1 m for 23 m: the images disagree."""
    pytest.importorskip("kiss_icp")    # the LiDAR odometry (extra "odometry")
    real = odometry.lidar_odometry

    def stuck(scans, **kwargs):
        poses = real(scans, **kwargs)
        poses[:, :3, 3] *= 0.04                      # 4 % of the true travel
        return poses
    monkeypatch.setattr(odometry, "lidar_odometry", stuck)
    code = main(["import", str(hidden), "-o", str(tmp_path / "s" / "scene.xml"),
                 "--max-points", "20000", "--azimuth-steps", "512"])
    err = capsys.readouterr().err
    assert code == 0
    lines = [l for l in err.splitlines() if "DISAGREE" in l]
    assert len(lines) == 1 and "image motion" in lines[0] and str(hidden) in lines[0]


def test_impossible_speed_is_flagged(scans):
    pytest.importorskip("kiss_icp")    # the LiDAR odometry (extra "odometry")
    _, sweeps = scans
    times = np.arange(len(sweeps)) * 0.01               # 100 m/s at 1 m per frame
    with pytest.warns(UserWarning, match="speed DISAGREE"):
        _, report = odometry.checked_odometry(sweeps, timestamps=times, source="street")
    assert not report.agrees


def test_non_finite_poses_are_refused(scans, monkeypatch):
    from mi_invrgbl.errors import UserError
    _, sweeps = scans
    monkeypatch.setattr(odometry, "lidar_odometry",
                        lambda s, **k: np.full((len(s), 4, 4), np.nan))
    with pytest.raises(UserError, match="street: LiDAR odometry diverged"):
        odometry.checked_odometry(sweeps, source="street")
