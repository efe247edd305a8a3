"""Tests of the synthetic street generator (``mi-invrgbl make-scene street``).

One tiny street (4 frames, 64x24 pixels, 256 LiDAR azimuth steps) is
generated per session and checked against independent computations: the
KITTI files against Mitsuba's camera and the true poses, the ground-truth
maps against the material table and the canopy's analytic shadow, the LiDAR
points against the meshes and the paper's closed-form intensity.
"""

from __future__ import annotations

import filecmp
import json
import math
import os

import cv2
import numpy as np
import pytest
import mitsuba as mi
import drjit as dr

from mi_invrgbl.errors import UserError
from mi_invrgbl.synthetic import StreetConfig, generate_street
from mi_invrgbl.synthetic import labels as labels_mod, rgb_frames, writers
import variant_choice

TINY = dict(seed=3, frames=4, width=64, height=24, azimuth_steps=256, spp=4)
FRAMES = TINY["frames"]


@pytest.fixture(scope="module")
def street(tmp_path_factory):
    variant_choice.use()
    out = tmp_path_factory.mktemp("street") / "out"
    generate_street(str(out), StreetConfig(**TINY), log=lambda *a: None)
    return out


@pytest.fixture(scope="module")
def info(street):
    with open(street / "gt" / "trajectory.json") as f:
        traj = json.load(f)
    with open(street / "gt" / "materials.json") as f:
        mats = json.load(f)
    seq = street / "sequences" / "00"
    calib = writers.read_calib(str(seq / "calib.txt"))
    poses = writers.read_poses(str(street / "poses" / "00.txt"))
    world_from_cam0 = np.array(traj["world_from_cam"][0])
    cam_from_velo = np.eye(4)
    cam_from_velo[:3, :4] = calib["Tr"]
    return {"traj": traj, "mats": mats, "P2": calib["P2"], "poses": poses,
            "world_from_cam": [world_from_cam0 @ p for p in poses],  # from the KITTI files
            "cam_from_velo": cam_from_velo,
            "mesh_id": {m["name"]: m["mesh_id"] for m in mats["meshes"]}}


def read_map(street, frame, name):
    ch = writers.read_exr(str(street / "gt" / "maps" / ("%06d_%s.exr" % (frame, name))))
    if "R" in ch:
        return np.stack([ch["R"], ch["G"], ch["B"]], axis=-1)
    return ch["Y"]


def project(P, world_from_cam, X):
    """Pixel (u, v) of world point X, and its depth, through KITTI P and camera pose."""
    Xc = np.linalg.inv(world_from_cam) @ np.append(X, 1.0)
    uvw = P @ Xc
    return uvw[:2] / uvw[2], Xc[2]


def test_layout_complete_and_loadable(street):
    seq = street / "sequences" / "00"
    for i in range(FRAMES):
        assert (seq / "image_2" / ("%06d.png" % i)).is_file()
        assert (seq / "velodyne" / ("%06d.bin" % i)).is_file()
        assert (street / "gt" / "lidar" / ("%06d.exr" % i)).is_file()
        for kind in ("time_a", "time_b", "night"):
            assert (street / "gt" / kind / ("%06d.exr" % i)).is_file()
        for name in ("albedo", "roughness", "normal", "lidar_albedo", "sun_visibility", "depth"):
            assert (street / "gt" / "maps" / ("%06d_%s.exr" % (i, name))).is_file()
    assert len(np.loadtxt(seq / "times.txt")) == FRAMES
    assert writers.read_poses(str(street / "poses" / "00.txt")).shape == (FRAMES, 4, 4)
    assert set(writers.read_calib(str(seq / "calib.txt"))) == {"P0", "P1", "P2", "P3", "Tr"}
    rows = writers.read_tracking_labels(str(street / "label_02" / "0000.txt"))
    assert {r["track_id"] for r in rows} == {0, 1}
    lights = json.loads((street / "gt" / "lights.json").read_text())
    assert set(lights) >= {"time_a", "time_b", "night"}
    for kind in ("time_a", "time_b", "night"):
        scene = mi.load_file(str(street / "gt" / ("scene_%s.xml" % kind)))
        assert len(scene.shapes()) == len(json.loads(
            (street / "gt" / "materials.json").read_text())["meshes"])
    png = np.array(mi.Bitmap(str(seq / "image_2" / "000000.png")))
    assert png.shape == (24, 64, 3) and png.dtype == np.uint8 and png.std() > 5
    rgb = writers.read_exr_rgb(str(street / "gt" / "time_a" / "000000.exr"))
    night = writers.read_exr_rgb(str(street / "gt" / "night" / "000000.exr"))
    assert np.isfinite(rgb).all() and rgb.mean() > 5 * night.mean()
    # Nothing half-written is left next to OUT.
    assert [p.name for p in street.parent.iterdir()] == ["out"]


def test_poses_match_the_rendering_camera(street, info):
    """A point on the wall projects (KITTI P2 + poses) to where Mitsuba's camera sees it."""
    wall = info["mats"]["uniform_wall"]
    X = np.array([np.mean(wall["x"]), wall["front_y"], 1.0])
    scene = mi.load_file(str(street / "gt" / "scene_time_a.xml"))
    sensor = scene.sensors()[0]
    params = mi.traverse(scene)
    flip = np.diag([-1.0, -1.0, 1.0, 1.0])      # KITTI camera -> Mitsuba camera axes
    for i in range(FRAMES):
        cam = info["world_from_cam"][i]
        (u, v), z = project(info["P2"], cam, X)
        assert 0 <= u < 64 and 0 <= v < 24 and z > 0
        params["sensor.to_world"] = mi.Transform4f(mi.ScalarMatrix4f(cam @ flip))
        params.update()
        # KITTI pixel centres are integers; Mitsuba's film coordinates are offset by 0.5.
        ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(float(u + 0.5) / 64, float(v + 0.5) / 24),
                                   mi.Point2f(0.5, 0.5))
        o = np.array(ray.o).reshape(3)
        d = np.array(ray.d).reshape(3)
        miss = np.linalg.norm(np.cross(X - o, d))
        assert miss < 1e-3, (i, miss)
        # ... and the depth map that camera produced agrees at the nearest pixel centre.
        ui, vi = int(round(u)), int(round(v))
        ray_dir = np.linalg.inv(info["P2"][:, :3]) @ np.array([ui, vi, 1.0])
        ray_world = cam[:3, :3] @ ray_dir
        t = (wall["front_y"] - cam[1, 3]) / ray_world[1]   # hit the wall plane
        assert read_map(street, i, "depth")[vi, ui] == pytest.approx(t, rel=1e-3)


def test_labels_match_true_car_poses(street, info):
    rows = writers.read_tracking_labels(str(street / "label_02" / "0000.txt"))
    true = np.array(info["traj"]["world_from_moving_car"])
    moving = [r for r in rows if r["track_id"] == labels_mod.TRACK_MOVING]
    assert [r["frame"] for r in moving] == list(range(FRAMES))
    car_id = info["mesh_id"]["moving_car"]
    for r in moving:
        i = r["frame"]
        pose = labels_mod.car_pose_from_label(r, info["world_from_cam"][i])
        assert np.allclose(pose[:3, 3], true[i][:3, 3], atol=1e-4)
        yaw = math.atan2(pose[1, 0], pose[0, 0])
        assert abs(yaw - math.atan2(true[i][1, 0], true[i][0, 0])) < 1e-4
        # The car's pixels lie inside its 2D box.
        ids = read_map(street, i, "mesh_id")
        vs, us = np.nonzero(ids == car_id)
        assert len(us) > 0
        left, top, right, bottom = r["bbox"]
        assert us.min() >= left - 1 and us.max() <= right + 1
        assert vs.min() >= top - 1 and vs.max() <= bottom + 1


def test_ground_truth_maps(street, info):
    mats = info["mats"]
    names = {m["mesh_id"]: m for m in mats["meshes"]}
    wall_id = info["mesh_id"]["wall"]
    K = info["P2"][:, :3]
    for i in range(FRAMES):
        ids = np.rint(read_map(street, i, "mesh_id")).astype(int)
        albedo = read_map(street, i, "albedo")
        rough = read_map(street, i, "roughness")
        lidar = read_map(street, i, "lidar_albedo")
        normal = read_map(street, i, "normal")
        depth = read_map(street, i, "depth")
        assert (ids >= 0).any() and (ids == -1).any()           # street and sky
        for mid in np.unique(ids[ids >= 0]):
            mat = mats["materials"][names[mid]["material"]]
            sel = ids == mid
            assert np.allclose(rough[sel], mat["roughness"], atol=1e-6)
            if mat["albedo_texture"] is None:
                assert np.allclose(albedo[sel], mat["albedo"], atol=1e-6)
                assert np.allclose(lidar[sel], mat["lidar_albedo"], atol=1e-6)
            else:   # the road: texture values, dark asphalt or bright paint
                assert albedo[sel].min() > 0.01 and albedo[sel].max() < 0.9
        assert np.all(depth[ids == -1] == 0) and np.all(depth[ids >= 0] > 0)
        # The uniform wall: facing +y, lit below the canopy's shadow line only.
        # (Pixels on its end face, normal -x, are excluded.)
        wall = (ids == wall_id) & (normal[..., 0] > -0.5)
        assert wall.sum() > 10
        assert np.allclose(normal[wall], [0.0, 1.0, 0.0], atol=1e-5)
        vis = read_map(street, i, "sun_visibility")[wall]
        assert set(np.unique(vis)) == {0.0, 1.0}
        vs, us = np.nonzero(wall)
        pc = depth[wall][:, None] * (np.linalg.inv(K) @ np.stack([us, vs, np.ones_like(us)])).T
        z_world = (pc @ info["world_from_cam"][i][:3, :3].T + info["world_from_cam"][i][:3, 3])[:, 2]
        line = mats["uniform_wall"]["shadow_below_z"]
        clear = np.abs(z_world - line) > 0.05
        assert np.all(vis[clear] == (z_world[clear] < line))


def _scene_at(street, info, frame):
    scene = mi.load_file(str(street / "gt" / "scene_time_a.xml"))
    poser = rgb_frames.FramePoser(scene, np.array(info["traj"]["world_from_moving_car"]))
    poser.set_frame(frame)
    return scene


@pytest.mark.parametrize("frame", [0, FRAMES - 1])
def test_lidar_points_on_meshes_and_intensity(street, info, frame):
    pts = writers.read_velodyne(str(street / "sequences" / "00" / "velodyne" / ("%06d.bin" % frame)))
    n_rays = 64 * 256
    assert 0.5 * n_rays < len(pts) < 0.98 * n_rays                  # sky and ray drop
    assert (pts[:, 3] >= 0).all() and (pts[:, 3] <= 1).all()
    world_from_velo = info["world_from_cam"][frame] @ info["cam_from_velo"]
    scene = _scene_at(street, info, frame)
    rng = np.linalg.norm(pts[:, :3].astype(np.float64), axis=1)
    d_local = pts[:, :3] / rng[:, None]
    d = d_local @ world_from_velo[:3, :3].T
    o = np.tile(world_from_velo[:3, 3], (len(pts), 1))
    si = scene.ray_intersect(mi.Ray3f(mi.Point3f(o.T.astype(np.float32)),
                                      mi.Vector3f(d.T.astype(np.float32))))
    t = np.array(si.t, dtype=np.float64)
    assert np.array(si.is_valid()).all()
    resid = rng - t
    assert abs(resid.mean()) < 2e-3 and 0.007 < resid.std() < 0.013
    assert np.abs(resid).max() < 0.07

    # On the uniform wall the intensity is the paper's closed form.
    wall = info["mats"]["materials"]["wall"]
    wall_ptr = [s for s in scene.shapes() if s.id() == "wall"][0]
    wall_sid = int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(wall_ptr))[0])
    on_wall = np.array(dr.reinterpret_array(mi.UInt32, si.shape)) == wall_sid
    on_wall &= np.array(si.n)[1] > 0.99          # its front face (normal +y)
    if frame == 0:
        assert on_wall.sum() >= 5
    c = np.abs(d[on_wall] @ np.array([0.0, 1.0, 0.0]))
    rho, tau, f0 = wall["lidar_albedo"], wall["roughness"], wall["f0"]
    spec = f0 * tau**2 * np.minimum(1, 2 * c**2) / (4 * c**2 * (c**2 * (tau**2 - 1) + 1) ** 2)
    scale = info["traj"]["lidar"]["intensity_scale"]
    expected = (rho + spec) * c / (math.pi * t[on_wall] ** 2) * scale
    ratio = pts[on_wall, 3] / expected
    if on_wall.any():
        assert abs(np.median(ratio) - 1) < 0.02 and np.all(np.abs(ratio - 1) < 0.1)


def test_same_seed_identical(street, tmp_path):
    again = tmp_path / "again"
    generate_street(str(again), StreetConfig(**TINY), log=lambda *a: None)
    for root, _, files in os.walk(street):
        for name in files:
            a = os.path.join(root, name)
            b = os.path.join(again, os.path.relpath(a, street))
            assert filecmp.cmp(a, b, shallow=False), os.path.relpath(a, street)


def test_paper_bsdf_street(street, tmp_path):
    # The same street rendered with the paper's own BSDF: every material is a
    # cooktorrance, the images differ from roughplastic's only in shading.
    out = tmp_path / "ct"
    generate_street(str(out), StreetConfig(**dict(TINY, frames=1, night=False, bsdf="cooktorrance")),
                    log=lambda *a: None)
    xml = (out / "gt" / "scene_time_a.xml").read_text()
    assert 'type="cooktorrance"' in xml and "roughplastic" not in xml
    assert '<texture type="bitmap" name="albedo">' in xml
    a = np.asarray(cv2.imread(str(out / "sequences/00/image_2/000000.png")), np.float64)
    b = np.asarray(cv2.imread(str(street / "sequences/00/image_2/000000.png")), np.float64)
    assert a.shape == b.shape and a.mean() > 5
    # roughplastic's diffuse lobe is dimmed by its coat ((1 - F)^2 / eta^2 ~ 0.4):
    # the paper's BRDF renders the same albedo brighter, never darker.
    assert 1.1 < a.mean() / b.mean() < 2.5


def test_bad_options(tmp_path):
    with pytest.raises(UserError, match="--bsdf"):
        generate_street(str(tmp_path / "a"), StreetConfig(bsdf="lambert"))
    with pytest.raises(UserError, match="--frames"):
        generate_street(str(tmp_path / "a"), StreetConfig(frames=0))
    with pytest.raises(UserError, match="--spp"):
        generate_street(str(tmp_path / "a"), StreetConfig(spp=-1))
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(UserError, match="does not exist"):
        generate_street(str(blocker / "out"), StreetConfig(**TINY))
    with pytest.raises(UserError, match="already exists"):
        generate_street(str(blocker), StreetConfig(**TINY))
    if os.geteuid() != 0:   # root writes anywhere
        locked = tmp_path / "locked"
        locked.mkdir()
        locked.chmod(0o500)
        try:
            with pytest.raises(UserError, match="permission"):
                generate_street(str(locked / "out"), StreetConfig(**TINY))
        finally:
            locked.chmod(0o700)
    if os.path.isdir("/proc"):   # not writable even for root
        with pytest.raises(UserError, match="cannot write"):
            generate_street("/proc/street-out", StreetConfig(**TINY))
    assert not (tmp_path / "a").exists()


def test_cli_reports_bad_options(tmp_path, capsys):
    from mi_invrgbl.cli import main
    assert main(["make-scene", "street", str(tmp_path / "o"), "--frames", "0"]) == 2
    assert "--frames must be at least 1" in capsys.readouterr().err
