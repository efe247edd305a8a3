"""``mi-invrgbl import``: drive -> scene (docs/scene_format.md).

A tiny synthetic street (6 frames, 64x24 pixels, 256 azimuth steps, a moving
and a parked car) is generated and imported once per session; the shared
KITTI excerpt is imported for its first 3 frames at 1/4 image size (skipped
when absent). The sensors are checked against independent projections: a
LiDAR point projected with K and camera_to_world must lie on the Mitsuba
camera's ray through that pixel, and on the lidar sensor's beam through its
range-image pixel.
"""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
import mitsuba as mi

from mi_invrgbl.errors import UserError
from mi_invrgbl.io import init_gaussians as ig
from mi_invrgbl.io import objects as objs
from mi_invrgbl.io.images import read_exr
from mi_invrgbl.io.importer import ImportOptions, import_scene
from mi_invrgbl.io.velodyne import write_velodyne
from mi_invrgbl.physics.gaussian_ply import read_ply, quaternion_to_matrix
from mi_invrgbl.scene.frames import Frames
from mi_invrgbl.scene.posing import set_frame
import tiny_street

TINY = tiny_street.CONFIG
TINY_OPTS = dict(max_points=20000, azimuth_steps=256)
# The odometry check needs kiss-icp (the "odometry" extra, in "test" too);
# without it the street's own poses are imported unchecked and only the
# check's test is skipped.
try:
    import kiss_icp  # noqa: F401
    HAVE_KISS_ICP = True
except ImportError:
    HAVE_KISS_ICP = False


def _quiet(*_a, **_k):
    pass


@pytest.fixture(scope="session")
def street(tiny_street):
    return tiny_street


@pytest.fixture(scope="session")
def imported(street, tmp_path_factory):
    out = tmp_path_factory.mktemp("import_out") / "scene" / "scene.xml"
    report = import_scene(street, out, ImportOptions(check_odometry=HAVE_KISS_ICP, **TINY_OPTS),
                          log=_quiet)
    return out.parent, report


@pytest.fixture(scope="session")
def kitti_imported(kitti_dir, tmp_path_factory):
    pytest.importorskip("kiss_icp")     # the excerpt has no poses: LiDAR odometry
    data = kitti_dir
    out = tmp_path_factory.mktemp("import_kitti") / "kitti" / "scene.xml"
    report = import_scene(data, out, ImportOptions(frames="0:3", image_scale=0.25,
                                                   max_points=20000, azimuth_steps=1024),
                          log=_quiet)
    return out.parent, report


@pytest.fixture
def street_copy(street, tmp_path):
    """A writable copy of the tiny street's KITTI files (no ground truth)."""
    dst = tmp_path / "data"
    shutil.copytree(street / "sequences", dst / "sequences")
    shutil.copytree(street / "poses", dst / "poses")
    shutil.copytree(street / "label_02", dst / "label_02")
    return dst


# ----------------------------------------------------------------------------
# Layout and loading
# ----------------------------------------------------------------------------

def test_layout(imported):
    root, report = imported
    for name in ("scene.xml", "frames.json", "background.ply", "object_0.ply"):
        assert (root / name).is_file(), name
    assert not (root / "object_1.ply").exists()          # the parked car stays background
    frames = Frames.load(root / "scene.xml")
    assert len(frames) == TINY["frames"] == report.counts["frames"]
    for f in frames:
        assert f.image.is_file() and f.lidar_scan.is_file() and f.points.is_file()
        assert f.held_out == (f.index % 5 == 4)
        assert f.camera == "camera_%04d" % f.index and f.lidar == "lidar_%04d" % f.index
        pts = np.load(f.points)
        assert pts.dtype == np.float32 and pts.shape[1] == 4
    assert frames.camera.width == TINY["width"] and frames.camera.height == TINY["height"]
    assert frames.lidar.beams == 64 and frames.lidar.azimuth_steps == 256
    assert frames.lidar.intensity == "raw"
    assert frames.ground_truth is not None and frames.ground_truth.name == "gt"
    assert frames.extra["pose_source"] == "poses file"
    # no temporary folders left next to the output
    assert [p.name for p in root.parent.iterdir()] == [root.name]


def test_scene_loads_and_renders(imported):
    root, _ = imported
    scene = mi.load_file(str(root / "scene.xml"), spp=1, samples=4)
    ids = [s.id() for s in scene.sensors()]
    assert ids[:2] == ["camera_0000", "lidar_0000"] and len(ids) == 2 * TINY["frames"]
    assert {s.id() for s in scene.shapes()} == {"background", "object_0"}
    assert scene.emitters()[0].id() == "sky"
    img = np.array(mi.render(scene, sensor=scene.sensors()[2]))
    assert img.shape[:2] == (TINY["height"], TINY["width"])
    assert np.isfinite(img).all() and img[..., :3].mean() > 0.05


def test_observation_exr(imported):
    root, _ = imported
    frames = Frames.load(root)
    data, names = read_exr(str(frames[0].lidar_scan))
    ch = {n: data[..., k] for k, n in enumerate(names)}
    assert set(ch) == {"intensity", "range", "hit"}
    assert ch["hit"].shape == (64, 256)
    hit = ch["hit"] > 0.5
    assert hit.mean() > 0.3
    assert (ch["intensity"][hit] >= 0).all() and (ch["intensity"][hit] <= 1).all()
    assert (ch["range"][~hit] == 0).all() and (ch["range"][hit] > 0).all()


# ----------------------------------------------------------------------------
# Sensor conventions
# ----------------------------------------------------------------------------

def _camera_round_trip(root, max_points=300):
    frames = Frames.load(root)
    scene = mi.load_file(str(root / "scene.xml"))
    sensors = {s.id(): s for s in scene.sensors()}
    W, H = frames.camera.width, frames.camera.height
    worst = 0.0
    for f in frames:
        pts = np.load(f.points)[:, :3].astype(np.float64)
        uv, z, ok = ig.project(pts, np.linalg.inv(f.camera_to_world), frames.camera.K, (W, H))
        sel = np.nonzero(ok & (z > 2))[0]
        sel = sel[:: max(1, len(sel) // max_points)]
        assert sel.size > 20
        pos = (uv[sel] + 0.5) / np.array([W, H])
        ray, _ = sensors[f.camera].sample_ray(0.0, 0.5, mi.Point2f(pos[:, 0], pos[:, 1]),
                                              mi.Point2f(0.5, 0.5))
        o = np.array(ray.o).reshape(3, -1).T
        d = np.array(ray.d).reshape(3, -1).T
        v = pts[sel] - o
        along = np.sum(v * d, axis=1)
        perp = np.linalg.norm(v - along[:, None] * d, axis=1)
        assert (along > 0).all()
        worst = max(worst, float((perp / np.linalg.norm(v, axis=1)).max()))
    return worst


def test_camera_convention_synthetic(imported):
    """A point projected with K and camera_to_world lies on the Mitsuba
    camera's ray through that pixel (within float precision)."""
    assert _camera_round_trip(imported[0]) < 1e-4


def test_camera_convention_kitti(kitti_imported):
    """Same with KITTI's off-centre principal point and 1/4 image size."""
    root, _ = kitti_imported
    frames = Frames.load(root)
    assert frames.camera.width == round(1242 * 0.25)
    assert abs(frames.camera.cx - (frames.camera.width / 2 - 0.5)) > 1   # really off-centre
    assert _camera_round_trip(root) < 1e-4


def test_lidar_convention(imported):
    """A point's range-image pixel (row = nearest beam, column from its
    azimuth) is the lidar sensor's beam within half a pixel, and the
    observation EXR holds a return there no farther than the point."""
    root, _ = imported
    frames = Frames.load(root)
    scene = mi.load_file(str(root / "scene.xml"))
    sensors = {s.id(): s for s in scene.sensors()}
    table = np.radians(frames.lidar.elevations_deg)
    W, Hb = frames.lidar.azimuth_steps, frames.lidar.beams
    half_el = 0.5 * np.abs(np.diff(table)).max() + 1e-6
    for f in list(frames)[:3]:
        pts = np.load(f.points)
        inv = np.linalg.inv(f.lidar_to_world)
        local = pts[:, :3] @ inv[:3, :3].T + inv[:3, 3]
        local = local[:: max(1, len(local) // 500)]
        el = np.arctan2(local[:, 2], np.hypot(local[:, 0], local[:, 1]))
        az = np.arctan2(local[:, 1], local[:, 0])
        row = np.argmin(np.abs(el[:, None] - table[None]), axis=1)
        col = np.mod(np.floor((1 - az / math.pi) * W / 2).astype(int), W)
        pos = np.stack([(col + 0.5) / W, (row + 0.5) / Hb], axis=1)
        ray, _ = sensors[f.lidar].sample_ray(0.0, 0.5, mi.Point2f(pos[:, 0], pos[:, 1]),
                                             mi.Point2f(0.5, 0.5))
        d_world = np.array(ray.d).reshape(3, -1).T
        d = d_world @ inv[:3, :3].T
        ray_el = np.arcsin(np.clip(d[:, 2], -1, 1))
        ray_az = np.arctan2(d[:, 1], d[:, 0])
        daz = np.abs(np.angle(np.exp(1j * (ray_az - az))))
        assert (daz <= math.pi / W + 1e-5).all()
        assert (np.abs(ray_el - el) <= half_el).all()
        data, names = read_exr(str(f.lidar_scan))
        ch = {n: data[..., k] for k, n in enumerate(names)}
        rng = np.linalg.norm(local, axis=1)
        assert (ch["hit"][row, col] > 0.5).all()
        assert (ch["range"][row, col] <= rng + 1e-3).all()


# ----------------------------------------------------------------------------
# Gaussians
# ----------------------------------------------------------------------------

def test_background_gaussians(imported):
    root, report = imported
    frames = Frames.load(root)
    c = read_ply(str(root / "background.ply"))
    assert len(c) <= TINY_OPTS["max_points"] == report.counts["background_gaussians"]
    assert np.allclose(np.linalg.norm(c.normals, axis=1), 1, atol=1e-5)
    # the normal is the rotation's third axis and the thinnest one
    R = quaternion_to_matrix(c.quaternions.astype(np.float64))
    assert np.allclose(R[:, :, 2], c.normals, atol=1e-4)
    assert (c.scales[:, 2] <= c.scales[:, 0] + 1e-9).all()
    # facing the nearest LiDAR position
    origins = np.array([f.lidar_to_world[:3, 3] for f in frames])
    k = np.argmin(((c.centers[:, None] - origins[None]) ** 2).sum(-1), axis=1)
    v = origins[k] - c.centers
    assert np.mean(np.sum(c.normals * v, axis=1) > 0) > 0.97
    # road: flat, normals up, LiDAR albedo near the true 0.15 (textured)
    z0 = np.percentile(c.centers[:, 2], 5)
    road = (np.abs(c.centers[:, 2] - z0) < 0.05) & (np.abs(c.centers[:, 1]) < 3)
    assert road.sum() > 500
    assert np.median(c.normals[road, 2]) > 0.99
    assert 0.1 < np.median(c.lidar_albedo[road]) < 0.2
    assert (c.lidar_albedo >= 0).all() and (c.lidar_albedo <= 1).all()
    assert np.allclose(c.opacities, 0.7, atol=1e-4) and np.allclose(c.roughness, 0.5)
    # colours: some seen by a camera, the rest grey
    seen = ~np.all(np.isclose(c.albedo, 0.5), axis=1)
    assert 0.05 < seen.mean() < 1.0


def test_moving_object(imported, street):
    root, report = imported
    frames = Frames.load(root)
    assert list(frames.objects) == ["object_0"]
    obj = frames.objects["object_0"]
    assert obj.moving and obj.kind == "Car" and obj.track_id == 0
    tracks = {t["track_id"]: t for t in frames.extra["tracks"]}
    assert tracks[0]["moving"] and tracks[0]["dynamic"]
    assert not tracks[1]["moving"] and not tracks[1]["dynamic"]
    assert tracks[1]["displacement_m"] < 0.05
    c = read_ply(str(obj.ply))
    assert len(c) == 5000
    h, w, l = obj.size_hwl
    assert (np.abs(c.centers) <= np.array([l / 2, w / 2, h / 2]) + objs.BOX_MARGIN + 1e-4).all()
    # poses: the generator's true car poses (its car frame: origin at the bottom)
    traj = json.loads((street / "gt" / "trajectory.json").read_text())
    G = np.array(frames.extra["gt_world_from_world"])
    up = np.eye(4)
    up[2, 3] = h / 2
    for f in frames:
        true = np.array(traj["world_from_moving_car"][f.index]) @ up
        np.testing.assert_allclose(G @ f.objects["object_0"], true, atol=1e-4)
        np.testing.assert_allclose(G @ f.lidar_to_world, traj["world_from_velo"][f.index],
                                   atol=1e-6)
    # set_frame moves the node to each frame's pose
    scene = mi.load_file(str(root / "scene.xml"))
    shape = [s for s in scene.shapes() if s.id() == "object_0"][0]
    for i in (3, 1):
        set_frame(scene, frames, i)
        data = np.array(mi.traverse(shape)["data"]).reshape(-1, 10)
        T = frames[i].objects["object_0"]
        np.testing.assert_allclose(data[:, :3], c.centers @ T[:3, :3].T + T[:3, 3], atol=1e-3)


def test_dynamic_modes(street, tmp_path):
    rep = import_scene(street, tmp_path / "all" / "scene.xml",
                       ImportOptions(dynamic="all", frames="0:3", object_points=200, **TINY_OPTS),
                       log=_quiet)
    frames = Frames.load(rep.scene)
    assert set(frames.objects) == {"object_0", "object_1"}
    assert not frames.objects["object_1"].moving
    rep = import_scene(street, tmp_path / "none" / "scene.xml",
                       ImportOptions(dynamic="none", frames="0:3", **TINY_OPTS), log=_quiet)
    assert Frames.load(rep.scene).objects == {}
    assert "object_" not in (rep.scene).read_text()


def test_odometry_check(imported):
    pytest.importorskip("kiss_icp")
    _, report = imported
    odo = report.odometry
    # kiss-icp on the corridor-like street: ground points must go (see io.odometry)
    assert odo["ate_m_ground_removed"] < 0.3
    assert odo["path_length_m"] == pytest.approx(5.0, abs=0.05)


def test_kitti_excerpt(kitti_imported):
    root, report = kitti_imported
    frames = Frames.load(root)
    assert len(frames) == 3 and frames.objects == {}
    assert frames.lidar.intensity == "reflectivity" and frames.lidar.beams == 64
    el = np.array(frames.lidar.elevations_deg)
    # apparent (from-origin) beam elevations of the HDL-64: about +2 .. -24 degrees
    assert (np.diff(el) < 0).all() and 0 < el[0] < 6 and -27 < el[-1] < -21
    assert frames.extra["pose_source"] == "odometry"
    np.testing.assert_allclose(frames[0].lidar_to_world, np.eye(4), atol=1e-9)
    assert report.counts["background_gaussians"] == 20000
    import cv2
    img = cv2.imread(str(frames[0].image))
    assert img.shape[:2] == (frames.camera.height, frames.camera.width)
    mi.load_file(str(root / "scene.xml"))


# ----------------------------------------------------------------------------
# Pieces
# ----------------------------------------------------------------------------

def test_knn_exact_and_pca():
    rng = np.random.default_rng(0)
    p = rng.uniform(-5, 5, (3000, 3))
    p[:, 2] = 0.01 * rng.normal(size=3000) + 0.1 * p[:, 0]      # a tilted plane
    idx, d = ig.knn(p, 8)
    for j in rng.integers(0, 3000, 20):
        true = np.sort(np.linalg.norm(p - p[j], axis=1))[:8]
        np.testing.assert_allclose(d[j], true, atol=1e-4)
    # the neighbours of some rows only: the same lists, and their frames
    rows = rng.choice(3000, 200, replace=False)
    qi, qd = ig.knn(p, 8, queries=rows)
    np.testing.assert_allclose(qd, d[rows], atol=1e-6)
    assert np.all(qi[:, 0] == rows)
    n, t, eig = ig.pca_frames(p, idx)
    np.testing.assert_allclose(np.abs(np.sum(ig.pca_frames(p, qi)[0] * n[rows], 1)), 1, atol=1e-6)
    assert ig.knn(p, 8, queries=np.zeros(0, int))[0].shape == (0, 8)
    truth = np.array([-0.1, 0, 1]) / np.linalg.norm([-0.1, 0, 1])
    assert np.median(np.abs(n @ truth)) > 0.99
    n = ig.orient_towards(n, np.tile([0, 0, 1.0], (len(n), 1)))
    assert (n[:, 2] > 0).all()
    q = ig.frames_to_quaternions(t, n)
    R = quaternion_to_matrix(q)
    np.testing.assert_allclose(R[:, :, 2], n / np.linalg.norm(n, axis=1, keepdims=True), atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(R), 1, atol=1e-9)


def test_lidar_albedo_models():
    # paper model: I = rho cos / (pi d^2) * P, scaled so white at 2 m facing reads 1
    rho, d, cos = 0.3, 7.0, 0.6
    I = rho * cos / d ** 2 * 2.0 ** 2
    assert ig.lidar_albedo([I], [d], [cos], "raw", 2.0)[0] == pytest.approx(rho)
    assert ig.lidar_albedo([0.4], [50.0], [0.1], "reflectivity")[0] == pytest.approx(0.4)
    assert ig.lidar_albedo([0.9], [30.0], [1.0], "raw")[0] == 1.0            # clipped


def test_object_frame_matches_kitti_box():
    """Our object frame (centre, x fwd, y left, z up) vs KITTI's box frame."""
    h = 1.5
    T = objs.kitti_box_from_object(h)
    # bottom centre of ours -> KITTI origin; our up -> KITTI -y; our left -> KITTI +z
    np.testing.assert_allclose(T @ [0, 0, -h / 2, 1], [0, 0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3] @ [0, 0, 1], [0, -1, 0])
    np.testing.assert_allclose(T[:3, :3] @ [0, 1, 0], [0, 0, 1])
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1)


def test_fill_poses_interpolates_and_holds():
    def pose(yaw, x):
        T = np.eye(4)
        T[:3, :3] = [[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0],
                     [0, 0, 1]]
        T[0, 3] = x
        return T
    out = objs.fill_poses([1, 3], [pose(0, 0), pose(0.4, 2)], 5)
    np.testing.assert_allclose(out[0], pose(0, 0))                 # held before
    np.testing.assert_allclose(out[2], pose(0.2, 1), atol=1e-9)    # interpolated
    np.testing.assert_allclose(out[4], pose(0.4, 2))               # held after
    # A track registered from the LiDAR moves on at its end's velocity
    # (heading held); a single labelled frame has none.
    ext = objs.fill_poses([1, 2, 3], [pose(0, 0), pose(0.2, 1.0), pose(0.4, 2.2)], 6,
                          extrapolate=True)
    np.testing.assert_allclose(ext[5][:3, :3], pose(0.4, 0)[:3, :3])
    np.testing.assert_allclose(ext[5][:3, 3], [2.2 + 2 * 1.1, 0, 0], atol=1e-9)
    np.testing.assert_allclose(ext[0][:3, 3], [-1.1, 0, 0], atol=1e-9)
    one = objs.fill_poses([2], [pose(0.1, 3.0)], 4, extrapolate=True)
    assert all(np.allclose(T, pose(0.1, 3.0)) for T in one)


# ----------------------------------------------------------------------------
# Bad input
# ----------------------------------------------------------------------------

def _no_leftovers(parent):
    return [p.name for p in parent.iterdir() if p.name.startswith(".")] == []


def test_missing_input(tmp_path):
    with pytest.raises(UserError, match="nowhere"):
        import_scene(tmp_path / "nowhere", tmp_path / "out" / "scene.xml", log=_quiet)
    (tmp_path / "empty").mkdir()
    with pytest.raises(UserError, match="empty"):
        import_scene(tmp_path / "empty", tmp_path / "out" / "scene.xml", log=_quiet)
    assert not (tmp_path / "out").exists() and _no_leftovers(tmp_path)


def test_bad_bin_size(street_copy, tmp_path):
    bad = street_copy / "sequences" / "00" / "velodyne" / "000002.bin"
    with open(bad, "ab") as f:
        f.write(b"\0" * 5)
    with pytest.raises(UserError, match="000002.bin.*multiple of 16"):
        import_scene(street_copy, tmp_path / "out" / "scene.xml",
                     ImportOptions(**TINY_OPTS), log=_quiet)
    assert not (tmp_path / "out").exists() and _no_leftovers(tmp_path)


def test_nan_points_dropped_with_warning(street_copy, tmp_path):
    path = street_copy / "sequences" / "00" / "velodyne" / "000001.bin"
    data = np.fromfile(path, "<f4").reshape(-1, 4)
    data[:7, 0] = np.nan
    data[7:9, 3] = np.inf
    write_velodyne(path, data[:, :3], np.nan_to_num(data[:, 3], posinf=np.inf))
    with pytest.warns(UserWarning, match="000001.bin.*dropped 9"):
        rep = import_scene(street_copy, tmp_path / "out" / "scene.xml",
                           ImportOptions(frames="0:3", **TINY_OPTS), log=_quiet)
    pts = np.load(Frames.load(rep.scene)[1].points)
    assert np.isfinite(pts).all() and len(pts) == len(data) - 9


def test_empty_scan_skipped(street_copy, tmp_path):
    (street_copy / "sequences" / "00" / "velodyne" / "000001.bin").write_bytes(b"")
    with pytest.warns(UserWarning, match="000001.bin"):
        rep = import_scene(street_copy, tmp_path / "out" / "scene.xml",
                           ImportOptions(frames="0:4", **TINY_OPTS), log=_quiet)
    frames = Frames.load(rep.scene)
    assert len(frames) == 3
    assert [f.extra["source_frame"] for f in frames] == [0, 2, 3]
    assert frames.extra["skipped_source_frames"] == [1]


def test_mismatched_frame_counts(street_copy, tmp_path):
    (street_copy / "sequences" / "00" / "image_2" / "000005.png").unlink()
    with pytest.warns(UserWarning, match="5 images but 6 LiDAR sweeps"):
        rep = import_scene(street_copy, tmp_path / "out" / "scene.xml",
                           ImportOptions(**TINY_OPTS), log=_quiet)
    assert len(Frames.load(rep.scene)) == 5
    # a poses file shorter than the sequence is an error naming it
    poses = street_copy / "poses" / "00.txt"
    poses.write_text("\n".join(poses.read_text().splitlines()[:3]) + "\n")
    with pytest.warns(UserWarning, match="5 images"), pytest.raises(UserError, match="00.txt"):
        import_scene(street_copy, tmp_path / "out2" / "scene.xml", log=_quiet)


def test_calibration_without_points_in_image(street_copy, tmp_path):
    calib = street_copy / "sequences" / "00" / "calib.txt"
    lines = calib.read_text().splitlines()
    # Tr: shift the LiDAR 10 km to the side (every point lands far outside the image)
    tr = np.array([float(v) for v in lines[-1].split(":")[1].split()]).reshape(3, 4)
    tr[0, 3] += 1e4
    lines[-1] = "Tr: " + " ".join("%.12e" % v for v in tr.ravel())
    calib.write_text("\n".join(lines) + "\n")
    with pytest.raises(UserError, match="calib.txt"):
        import_scene(street_copy, tmp_path / "out" / "scene.xml", log=_quiet)


def test_no_half_written_output(street, tmp_path, monkeypatch):
    from mi_invrgbl.io import importer

    def broken(path):
        raise RuntimeError("simulated crash after writing")
    monkeypatch.setattr(importer, "_verify", broken)
    with pytest.raises(RuntimeError, match="simulated"):
        import_scene(street, tmp_path / "out" / "scene.xml",
                     ImportOptions(frames="0:2", **TINY_OPTS), log=_quiet)
    assert list(tmp_path.iterdir()) == []


def test_existing_output(street, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    # a folder mi-invrgbl did not write is refused, with or without --overwrite
    for overwrite in (False, True):
        with pytest.raises(UserError, match="not written by mi-invrgbl"):
            import_scene(street, out / "scene.xml",
                         ImportOptions(frames="0:2", overwrite=overwrite, **TINY_OPTS),
                         log=_quiet)
    assert (out / "keep.txt").read_text() == "x" and _no_leftovers(tmp_path)
    ours = tmp_path / "ours"
    import_scene(street, ours / "scene.xml", ImportOptions(frames="0:3", **TINY_OPTS), log=_quiet)
    with pytest.raises(UserError, match="--overwrite"):
        import_scene(street, ours / "scene.xml", ImportOptions(frames="0:2", **TINY_OPTS),
                     log=_quiet)
    # --overwrite replaces the import's files and keeps a file the user added
    (ours / "notes.txt").write_text("mine")
    rep = import_scene(street, ours / "scene.xml",
                       ImportOptions(frames="0:2", overwrite=True, **TINY_OPTS), log=_quiet)
    assert (ours / "notes.txt").read_text() == "mine" and (ours / "scene.xml").is_file()
    assert len(Frames.load(rep.scene)) == 2 and _no_leftovers(tmp_path)


def test_bad_options(street, tmp_path):
    with pytest.raises(UserError, match="--frames"):
        import_scene(street, tmp_path / "o" / "scene.xml", ImportOptions(frames="9:12"),
                     log=_quiet)
    with pytest.raises(UserError, match="--image-scale"):
        import_scene(street, tmp_path / "o" / "scene.xml", ImportOptions(image_scale=2),
                     log=_quiet)
    with pytest.raises(UserError, match="--roughness"):
        import_scene(street, tmp_path / "o" / "scene.xml", ImportOptions(roughness=0.0),
                     log=_quiet)
    with pytest.raises(UserError, match="--roughness"):
        import_scene(street, tmp_path / "o" / "scene.xml", ImportOptions(roughness=float("nan")),
                     log=_quiet)
    for k in (-1, 2):
        with pytest.raises(UserError, match="--normal-knn"):
            import_scene(street, tmp_path / "o" / "scene.xml", ImportOptions(normal_knn=k),
                         log=_quiet)
    with pytest.raises(UserError, match="scene.xml"):
        import_scene(street, tmp_path / "o", log=_quiet)


def test_cli(street, tmp_path, capsys):
    from mi_invrgbl.cli import main
    out = tmp_path / "cli" / "scene.xml"
    assert main(["import", str(street), "-o", str(out), "--frames", "0:2",
                 "--max-points", "5000", "--azimuth-steps", "256", "--image-scale", "0.5",
                 "--roughness", "0.8"]) == 0
    text = capsys.readouterr().out
    for step in ("read", "odometry", "accumulate", "normals", "objects", "colours", "write"):
        assert step in text
    assert Frames.load(out).camera.width == 32
    assert np.allclose(read_ply(str(out.parent / "background.ply")).roughness, 0.8)
    assert main(["import", str(tmp_path / "missing"), "-o", str(tmp_path / "x" / "s.xml")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "missing" in err[0]


def test_cli_warnings_are_one_line(street_copy, tmp_path, capsys):
    from mi_invrgbl.cli import main
    (street_copy / "sequences" / "00" / "velodyne" / "000001.bin").write_bytes(b"")
    assert main(["import", str(street_copy), "-o", str(tmp_path / "w" / "scene.xml"),
                 "--frames", "0:3", "--max-points", "5000", "--azimuth-steps", "256"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err and all(line.startswith("mi-invrgbl import: warning: ") for line in err)
    assert any("000001.bin" in line and "skipped" in line for line in err)


@pytest.mark.slow
def test_full_kitti_excerpt(kitti_dir, tmp_path):
    """All 40 frames at 1/4 image size with the default 8e5 Gaussians
    (about 25 s on 2 cores)."""
    rep = import_scene(kitti_dir, tmp_path / "k" / "scene.xml",
                       ImportOptions(image_scale=0.25), log=print)
    print(rep.times, rep.counts)
    frames = Frames.load(rep.scene)
    assert len(frames) == 40 and sum(f.held_out for f in frames) == 8
    assert rep.counts["background_gaussians"] == 800_000
    assert rep.times["total"] < 180


def test_extend_walls_only_where_the_top_beam_cut_a_facade():
    from mi_invrgbl.io.importer import (BackgroundPoints, ImportOptions, ImportState,
                                        _extend_walls)
    # Sensor at the origin, top beam 10 degrees up. A facade 8 m away seen up
    # to the top beam (z = 8 tan 10deg = 1.41 m) and a 1.2 m box at 4 m whose
    # top edge lies well below the top beam (-4.3 degrees).
    top = np.radians(10.0)
    zs = np.linspace(-1.5, 8 * np.tan(top), 30)
    ys = np.linspace(-2, 2, 20)
    wall = np.array([(8.0, y, z) for y in ys for z in zs])
    box = np.array([(4.0, y, z) for y in ys for z in np.linspace(-1.5, -0.3, 10)])
    pts = np.concatenate([wall, box]).astype(np.float32)
    n = len(pts)
    state = ImportState(positions=[0], scans=[], images=[], K=np.eye(3), size=(1, 1), crop=None,
                        skipped=[], poses=np.eye(4)[None],
                        lidar_table=np.linspace(top, np.radians(-25), 64),
                        bg=BackgroundPoints(pts, np.full(n, 0.5, np.float32),
                                            np.linalg.norm(pts, axis=1).astype(np.float32),
                                            np.zeros(n, np.int32)))
    _extend_walls(state, ImportOptions(extend_walls=3.0), log=lambda *a: None)
    new = state.bg.points[n:]
    assert state.counts["wall_extension_points"] == len(new) > 0
    assert np.allclose(new[:, 0], 8.0)                     # only the facade grows
    assert new[:, 2].max() == pytest.approx(8 * np.tan(top) + 3.0, abs=0.16)
    assert np.all(state.bg.intensity[n:] == 0.5)
    assert len(state.bg.frame) == len(state.bg.points) == len(state.bg.extended)
    # each added point names the measured facade point it stands on
    seed = state.bg.seed[n:]
    assert np.all((seed >= 0) & (seed < n)) and np.all(state.bg.seed[:n] == -1)
    assert np.allclose(pts[seed, 1], new[:, 1]) and np.all(new[:, 2] > pts[seed, 2])


def test_extend_walls_option_is_checked():
    from mi_invrgbl.io.importer import ImportOptions
    with pytest.raises(UserError, match="extend-walls"):
        ImportOptions(extend_walls=-1).validate()


def _truck_side(top_z=0.2, length=6.0):
    """Object-frame points of a truck's near side (y = -1) up to ``top_z`` and,
    behind it, a low bonnet whose top the scan measured (x > 3)."""
    xs = np.arange(-length / 2, length / 2, 0.1)
    zs = np.arange(-1.0, top_z + 1e-9, 0.1)
    side = np.array([(x, -1.0, z) for x in xs for z in zs])
    bonnet = np.array([(x, y, -0.3) for x in np.arange(3.2, 4.0, 0.1) for y in np.arange(-0.9, 0.9, 0.1)])
    return side, bonnet


def test_extend_object_top_only_where_the_top_beam_cut():
    side, bonnet = _truck_side()
    pts = np.concatenate([side, bonnet])
    normals = np.tile([0.0, -1.0, 0.0], (len(pts), 1))
    normals[len(side):] = [0.0, 0.0, 1.0]
    tangents = np.tile([1.0, 0.0, 0.0], (len(pts), 1))
    cut = np.zeros(len(pts), bool)
    cut[:len(side)] = side[:, 2] >= 0.2 - 1e-9          # the side's top row met the top beam
    new, n, t, seed = objs.extend_object_top(pts, normals, tangents, cut, headroom=1.5)
    assert len(new) > 0 and len(new) == len(n) == len(t) == len(seed)
    assert np.all(seed < len(side)) and np.all(cut[seed])    # only the cut side grows
    assert np.allclose(new[:, 1], -1.0) and np.allclose(n, [0.0, -1.0, 0.0])
    assert new[:, 2].min() == pytest.approx(0.35) and new[:, 2].max() == pytest.approx(1.7)
    # every cut column continues once, with no gaps
    columns = np.unique(np.floor(new[:, 0] / 0.15))
    assert len(new) == len(np.unique(seed)) * 10 and len(columns) >= 35
    # nothing cut, too few cut points, or no headroom: nothing added
    for c, h in ((np.zeros(len(pts), bool), 1.5), (cut & (np.arange(len(pts)) < 5), 1.5), (cut, 0.0)):
        assert len(objs.extend_object_top(pts, normals, tangents, c, headroom=h)[0]) == 0


def test_import_extends_a_truck_the_top_beam_cut():
    """The objects step: a truck whose side the top beam cut gains Gaussians
    above it (with the seed's LiDAR albedo); a car whose roof was measured does not."""
    from mi_invrgbl.io.importer import ImportState, _objects
    top = np.radians(2.0)
    side, _ = _truck_side()
    car = np.array([(x, y, z) for x in np.arange(-2, 2, 0.1) for y in np.arange(-0.8, 0.8, 0.1)
                    for z in (-0.7, 0.0)])
    tracks = []
    for name, p, elev in (("object_1", side, np.where(side[:, 2] >= 0.2 - 1e-9, top, -0.1)),
                          ("object_2", car, np.full(len(car), -0.2))):
        rng = np.random.default_rng(1)
        tr = objs.ObjectTrack(name=name, track_id=int(name[-1]), kind="moving",
                              size_hwl=np.array([2.4, 2.2, 6.0]), poses=np.eye(4)[None],
                              labelled=np.ones(1, bool), displacement_m=3.0, moving=True,
                              dynamic=True)
        tr.points.append(p + rng.normal(0, 1e-3, p.shape))
        tr.intensity.append(np.full(len(p), 0.4))
        tr.distance.append(np.full(len(p), 3.0))
        tr.view.append(np.tile([0.0, -1.0, 0.0], (len(p), 1)))
        tr.elevation.append(elev)
        tracks.append(tr)
    state = ImportState(positions=[0], scans=[], images=[], K=np.eye(3), size=(1, 1), crop=None,
                        skipped=[], poses=np.eye(4)[None], objects=tracks,
                        lidar_table=np.linspace(top, np.radians(-25), 64),
                        object_report=[{"track_id": 1}, {"track_id": 2}])
    state.intensity = ("reflectivity", None)
    opts = ImportOptions(object_points=2000, voxel=0.05)
    _objects(state, opts, log=lambda *a: None)
    truck, car_cloud = state.object_clouds["object_1"], state.object_clouds["object_2"]
    added = len(truck["centers"]) - 2000
    assert added > 0 and state.object_report[0]["gaussians_above_top_beam"] == added
    assert truck["centers"][:, 2].max() > 0.2 + objs.OBJECT_HEADROOM - 0.2
    assert np.all(np.isfinite(truck["scales"])) and np.all(truck["lidar_albedo"][-added:] > 0)
    assert len(car_cloud["centers"]) == 2000 and state.object_report[1]["gaussians_above_top_beam"] == 0
    state2 = ImportState(positions=[0], scans=[], images=[], K=np.eye(3), size=(1, 1), crop=None,
                         skipped=[], poses=np.eye(4)[None], objects=tracks[:1],
                         lidar_table=np.linspace(top, np.radians(-25), 64))
    state2.intensity = ("reflectivity", None)
    _objects(state2, ImportOptions(object_points=2000, voxel=0.05, object_headroom=0.0),
             log=lambda *a: None)
    assert len(state2.object_clouds["object_1"]["centers"]) == 2000


def test_object_headroom_option_is_checked():
    with pytest.raises(UserError, match="object-headroom"):
        ImportOptions(object_headroom=-0.5).validate()


def _state_with(points, top_deg=10.0):
    from mi_invrgbl.io.importer import BackgroundPoints, ImportState
    pts = np.asarray(points, np.float32)
    n = len(pts)
    return ImportState(intensity=("raw", 2.0), positions=[0], scans=[], images=[], K=np.eye(3), size=(1, 1), crop=None,
                       skipped=[], poses=np.eye(4)[None],
                       lidar_table=np.linspace(np.radians(top_deg), np.radians(-25), 64),
                       bg=BackgroundPoints(pts, np.full(n, 0.5, np.float32),
                                           np.linalg.norm(pts, axis=1).astype(np.float32),
                                           np.zeros(n, np.int32)))


def test_background_normals_come_from_every_voxel_not_the_thinned_centres():
    from mi_invrgbl.io.importer import ImportOptions, _background
    # Two facades meeting at a corner (x = 8 facing -x, y = 2 facing -y),
    # sampled every 2 cm and thinned to 400 Gaussians: the thinned centres'
    # neighbours reach round the corner, a voxel's neighbours do not.
    zs = np.arange(-1.5, 1.0, 0.02)
    a = np.array([(8.0, y, z) for y in np.arange(-2.0, 2.0, 0.02) for z in zs])
    b = np.array([(x, 2.0, z) for x in np.arange(4.0, 8.0, 0.02) for z in zs])
    pts = np.concatenate([a, b])
    errors = {}
    for k in (0, 16):
        state = _state_with(pts)
        opts = ImportOptions(max_points=400, voxel=0.02, normal_knn=k)
        _background(state, opts, log=lambda *a: None)
        g = state.background
        # the truth of each Gaussian: the facade its centre lies on
        on_a = np.abs(g["centers"][:, 0] - 8.0) < np.abs(g["centers"][:, 1] - 2.0)
        t = np.where(on_a[:, None], [-1.0, 0, 0], [0, -1.0, 0])
        cos = np.clip(np.abs(np.sum(g["normals"] * t, 1)), 0, 1)
        # Gaussians on the corner's edge itself (within 10 cm) are left out
        corner = np.hypot(g["centers"][:, 0] - 8.0, g["centers"][:, 1] - 2.0)
        errors[k] = np.degrees(np.arccos(cos))[corner > 0.1]
        assert np.all(np.isfinite(g["normals"]))
        assert np.allclose(np.linalg.norm(g["normals"], axis=1), 1, atol=1e-5)
    print({k: (round(float(v.mean()), 2), round(float(v.max()), 1)) for k, v in errors.items()})
    assert errors[16].max() < 1.0                          # exact planes, exact normals
    assert errors[0].max() > 20.0                          # the thinned centres reach round the corner
    assert errors[16].mean() < 0.2 * errors[0].mean()


def test_wall_extension_takes_its_seed_normal():
    from mi_invrgbl.io.importer import ImportOptions, _background
    # A facade patch 8 m away, turned 30 degrees about the vertical, and one
    # column of points added above it (as _extend_walls adds them) beside a
    # measured branch sticking out of the wall towards the sensor: the
    # column's PCA finds the plane of column and branch, whose normal runs
    # along the wall. The Gaussians on the column take the normal of the
    # measured point below them.
    turn = np.radians(30.0)
    Rz = np.array([[np.cos(turn), -np.sin(turn), 0], [np.sin(turn), np.cos(turn), 0], [0, 0, 1]])
    facade = np.array([(8.0, y, z) for y in np.arange(-1.0, 1.0, 0.05)
                       for z in np.arange(-1.5, 1.4, 0.05)]) @ Rz.T
    top = int(np.argmax(facade[:, 2] - np.abs(facade[:, 1] - facade[0, 1])))   # a top-edge point
    column = facade[top] + np.array([[0, 0, 0.25 * (k + 1)] for k in range(12)])
    want = Rz @ np.array([-1.0, 0.0, 0.0])
    branch = column[6] + 0.1 * want + np.arange(12)[:, None] * 0.1 * want[None]
    pts = np.concatenate([facade, branch, column])
    for k in (0, 16):
        cos = {}
        for with_seed in (False, True):
            state = _state_with(pts)
            state.bg.seed = np.full(len(pts), -1, np.int64)
            if with_seed:
                state.bg.seed[-len(column):] = top
            _background(state, ImportOptions(max_points=100000, voxel=0.05, normal_knn=k),
                        log=lambda *a: None)
            g = state.background
            up = ((g["centers"][:, 2] > facade[:, 2].max() + 0.2)
                  & (np.linalg.norm(g["centers"][:, :2] - column[0, :2], axis=1) < 0.01))
            assert up.sum() == len(column)
            cos[with_seed] = g["normals"][up] @ want
        assert np.all(cos[True] > 0.999)                   # the facade's normal, facing the sensor
        assert np.min(cos[False]) < 0.99                   # what the column alone gives


def test_held_out_frames_give_the_gaussians_nothing(street_copy, tmp_path):
    """A held-out frame's sweep and image are observations for ``eval`` and
    nothing more: changing them (the sweep's ranges and intensities, the
    image's colours) leaves every Gaussian of the import bit for bit as it
    was, while the held-out observations written do change."""
    from mi_invrgbl.io.triangulate import held_out
    import cv2

    frames = Frames.load(import_scene(street_copy, tmp_path / "a" / "scene.xml",
                                      ImportOptions(**TINY_OPTS), log=_quiet).scene)
    k = next(i for i in range(len(frames)) if held_out(i))
    assert frames[k].held_out
    seq = street_copy / "sequences" / "00"
    sweep = seq / "velodyne" / ("%06d.bin" % k)
    data = np.fromfile(sweep, "<f4").reshape(-1, 4)
    # Moved along their own rays, so that the beam table (elevations) stays.
    write_velodyne(sweep, 0.8 * data[:, :3], 1.0 - data[:, 3])
    image = seq / "image_2" / ("%06d.png" % k)
    img = cv2.imread(str(image))
    img[:] = (255, 0, 255)
    cv2.imwrite(str(image), img)
    changed = Frames.load(import_scene(street_copy, tmp_path / "b" / "scene.xml",
                                       ImportOptions(**TINY_OPTS), log=_quiet).scene)

    assert not np.array_equal(np.load(frames[k].points), np.load(changed[k].points))
    assert not np.array_equal(cv2.imread(str(frames[k].image)), cv2.imread(str(changed[k].image)))
    for name in ["background.ply"] + ["%s.ply" % o for o in frames.objects]:
        a, b = read_ply(str(tmp_path / "a" / name)), read_ply(str(tmp_path / "b" / name))
        assert len(a) == len(b) > 0
        for key in ("centers", "scales", "quaternions", "normals", "albedo", "lidar_albedo"):
            assert np.array_equal(getattr(a, key), getattr(b, key)), (name, key)
