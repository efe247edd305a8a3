"""frames.json records and set_frame (moving dynamic objects per frame)."""

import json

import numpy as np
import pytest
import mitsuba as mi

from mi_invrgbl.errors import UserError
from mi_invrgbl.physics.gaussian_ply import GaussianCloud, write_ply, quaternion_to_matrix
from mi_invrgbl.scene.frames import Frames, CAMERA_FLIP, FORMAT
from mi_invrgbl.scene.posing import set_frame


def _pose(angle, t):
    c, s = np.cos(angle), np.sin(angle)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = t
    return T


def _matrix_xml(T):
    return " ".join("%.17g" % v for v in np.ravel(T))


def _sensor(kind, i):
    return (f'<sensor type="{kind}" id="{"camera" if kind == "perspective" else "lidar"}_{i:04d}">'
            f'<film type="hdrfilm"><integer name="width" value="8"/>'
            f'<integer name="height" value="{8 if kind == "perspective" else 2}"/></film>'
            + ('<string name="elevations" value="1,-1"/>' if kind == "lidar" else "")
            + f'<sampler type="independent"><integer name="seed" value="{i}"/></sampler></sensor>')


@pytest.fixture
def tiny_scene(tmp_path):
    rng = np.random.default_rng(1)
    n = 20
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    cloud = GaussianCloud(centers=rng.normal(size=(n, 3)).astype(np.float32),
                          scales=np.full((n, 3), 0.1, np.float32),
                          quaternions=q.astype(np.float32),
                          opacities=np.full(n, 0.7, np.float32),
                          normals=np.tile(np.float32([1, 0, 0]), (n, 1)))
    write_ply(str(tmp_path / "object_7.ply"), cloud)
    poses = [_pose(0.0, [5, 0, 0]), _pose(0.5, [6, 1, 0]), _pose(-1.0, [2, -3, 0.5])]
    (tmp_path / "scene.xml").write_text(
        '<scene version="3.0.0"><integrator type="invrgbl"/>'
        '<shape type="gaussians" id="object_7"><string name="filename" value="object_7.ply"/>'
        f'<transform name="to_world"><matrix value="{_matrix_xml(poses[0])}"/></transform></shape>'
        + "".join(_sensor(k, i) for i in range(3) for k in ("perspective", "lidar"))
        + "</scene>")
    frames = {
        "format": FORMAT, "source": str(tmp_path),
        "camera": {"width": 8, "height": 8, "fx": 4.0, "fy": 4.0, "cx": 4.0, "cy": 4.0},
        "lidar": {"beams": 2, "azimuth_steps": 8, "elevations_deg": [1, -1],
                  "intensity": "raw"},
        "objects": {"object_7": {"track_id": 7, "kind": "Car", "size_hwl": [1.5, 1.8, 4],
                                 "moving": True, "ply": "object_7.ply"}},
        "frames": [{"index": i, "time": 0.1 * i, "held_out": i % 5 == 4,
                    "camera": f"camera_{i:04d}", "lidar": f"lidar_{i:04d}",
                    "image": f"observations/image_{i:04d}.png",
                    "lidar_scan": f"observations/lidar_{i:04d}.exr",
                    "points": f"observations/points_{i:04d}.npy",
                    "camera_to_world": _pose(0.1 * i, [i, 0, 1.6]).tolist(),
                    "lidar_to_world": _pose(0.1 * i, [i, 0, 1.7]).tolist(),
                    "objects": {"object_7": poses[i].tolist()}} for i in range(3)],
    }
    (tmp_path / "frames.json").write_text(json.dumps(frames))
    return tmp_path, cloud, poses


def test_load_records(tiny_scene):
    root, _, poses = tiny_scene
    for where in (root / "scene.xml", root, root / "frames.json"):
        frames = Frames.load(where)
        assert len(frames) == 3
    f = frames[1]
    assert f.camera == "camera_0001" and f.lidar == "lidar_0001"
    assert f.image == root / "observations" / "image_0001.png"
    np.testing.assert_allclose(f.objects["object_7"], poses[1])
    np.testing.assert_allclose(f.camera_to_world_mitsuba, f.camera_to_world @ CAMERA_FLIP)
    assert frames.objects["object_7"].ply == root / "object_7.ply"
    assert frames.objects["object_7"].moving
    assert frames.camera.K[0, 0] == 4.0 and frames.lidar.beams == 2
    assert frames.train_indices() == [0, 1, 2] and frames.held_out_indices() == []
    assert frames.moving_objects() == ["object_7"]


def test_fit_subfolder_and_save_roundtrip(tiny_scene):
    root, _, _ = tiny_scene
    (root / "fit").mkdir()
    frames = Frames.load(root / "fit" / "scene.xml")     # falls back to DIR/frames.json
    assert frames.root == root
    out = frames.save(root / "fit")
    data = json.loads(out.read_text())
    assert data["frames"][0]["image"] == "../observations/image_0000.png"
    again = Frames.load(out)
    assert again.frames[2].points == frames.frames[2].points
    np.testing.assert_allclose(again[2].lidar_to_world, frames[2].lidar_to_world)


def test_bad_frames_file(tmp_path):
    with pytest.raises(UserError, match="frames.json"):
        Frames.load(tmp_path / "scene.xml")
    (tmp_path / "frames.json").write_text("{not json")
    with pytest.raises(UserError, match="frames.json"):
        Frames.load(tmp_path)
    (tmp_path / "frames.json").write_text(json.dumps({"format": FORMAT, "camera": {}}))
    with pytest.raises(UserError, match="missing key"):
        Frames.load(tmp_path)


def _shape_state(scene, name):
    shape = [s for s in scene.shapes() if s.id() == name][0]
    p = mi.traverse(shape)
    data = np.array(p["data"], np.float64).reshape(-1, 10)
    return data, np.array(p["normal"], np.float64).reshape(-1, 3)


def test_set_frame_moves_objects(tiny_scene):
    root, cloud, poses = tiny_scene
    scene = mi.load_file(str(root / "scene.xml"))
    frames = Frames.load(root)
    data0, _ = _shape_state(scene, "object_7")
    np.testing.assert_allclose(data0[:, :3], cloud.centers @ poses[0][:3, :3].T + poses[0][:3, 3],
                               atol=1e-5)
    for i in (2, 1, 0, 2):
        cam, lidar = set_frame(scene, frames, i)
        assert cam.id() == f"camera_{i:04d}" and lidar.id() == f"lidar_{i:04d}"
        data, normals = _shape_state(scene, "object_7")
        T = poses[i]
        np.testing.assert_allclose(data[:, :3], cloud.centers @ T[:3, :3].T + T[:3, 3], atol=1e-4)
        np.testing.assert_allclose(normals, np.tile(T[:3, 0], (len(normals), 1)), atol=1e-5)
        q = np.concatenate([data[:, 9:10], data[:, 6:9]], axis=1)   # -> w x y z
        R = quaternion_to_matrix(q)
        R_true = T[:3, :3] @ quaternion_to_matrix(cloud.quaternions.astype(np.float64))
        np.testing.assert_allclose(R, R_true, atol=1e-4)
    with pytest.raises(IndexError):
        set_frame(scene, frames, 3)


def test_frames_refuse_non_finite_numbers(tiny_scene, capsys):
    root, _, _ = tiny_scene
    frames = Frames.load(root)
    frames.frames[1].time = float("nan")
    out = root / "copy"
    with pytest.raises(UserError, match=r"frames.json: refusing to write a non-finite number "
                                        r"\(frames.json.frames\[1\].time = nan\)"):
        frames.save(out)
    assert not (out / "frames.json").exists()
    # Python's json reads the non-standard NaN; the loader refuses it, naming the file.
    text = (root / "frames.json").read_text().replace('"time": 0.1', '"time": NaN', 1)
    (root / "frames.json").write_text(text)
    with pytest.raises(UserError, match="frames.json: not valid JSON .*NaN"):
        Frames.load(root)
    data = json.loads((root / "frames.json").read_text().replace("NaN", "0.1"))
    data["camera"]["fx"] = 1e999
    (root / "frames.json").write_text(json.dumps(data))
    with pytest.raises(UserError, match="frames.json"):
        Frames.load(root)
    data["camera"]["fx"] = 4.0
    data["frames"][2]["camera_to_world"][0][3] = None
    (root / "frames.json").write_text(json.dumps(data))
    with pytest.raises(UserError, match=r"frames.json, frames\[2\].camera_to_world"):
        Frames.load(root)


def test_place_moves_every_kind_of_node_and_rays_see_it(tiny_scene):
    """Gaussians, a mesh, a spot light and a sensor, moved by the one function;
    rays traced after the move hit the objects where they now are."""
    import drjit as dr
    from mi_invrgbl.scene.posing import place, reset_tracking, to_world_of
    root, cloud, poses = tiny_scene
    text = (root / "scene.xml").read_text().replace("</scene>", (
        '<shape type="cube" id="box"><transform name="to_world"><translate x="0" y="5"/>'
        '</transform></shape><emitter type="spot" id="lamp"><transform name="to_world">'
        '<translate z="4"/></transform></emitter></scene>'))
    (root / "moved.xml").write_text(text)
    scene = mi.load_file(str(root / "moved.xml"))
    target = _pose(0.3, [-20, 7, 1])
    box_to = _pose(1.0, [30, -4, 2])
    cam_to = _pose(0.2, [1, 2, 3])
    place(scene, {"object_7": target, "box": box_to, "lamp": box_to, "camera_0001": cam_to},
          loaded={"object_7": poses[0], "box": _pose(0.0, [0, 5, 0]),
                  "lamp": _pose(0.0, [0, 5, 0])})    # the lamp rides on the box
    data, _ = _shape_state(scene, "object_7")
    np.testing.assert_allclose(data[:, :3], cloud.centers @ target[:3, :3].T + target[:3, 3],
                               atol=1e-4)
    p = mi.traverse(scene)
    box = np.array(p["box.vertex_positions"], np.float64).reshape(-1, 3)
    np.testing.assert_allclose(box.mean(axis=0), box_to[:3, 3], atol=1e-5)
    np.testing.assert_allclose(to_world_of(p, "lamp"), box_to @ _pose(0.0, [0, -5, 4]), atol=1e-5)
    # Without a loaded pose a sensor's pose is its to_world.
    np.testing.assert_allclose(to_world_of(p, "camera_0001"), cam_to, atol=1e-5)

    def hit_count(point):
        # Rays from high above, straight down onto ``point``: the scene's
        # acceleration structure must know the moved geometry.
        n = 64
        o = np.tile(np.asarray(point, np.float32) + [0, 0, 50], (n, 1))
        o[:, :2] += np.random.default_rng(0).uniform(-0.2, 0.2, (n, 2)).astype(np.float32)
        ray = mi.Ray3f(mi.Point3f(*o.T), mi.Vector3f(0, 0, -1))
        return int(dr.count(scene.ray_intersect(ray).is_valid())[0])

    assert hit_count(box_to[:3, 3]) == 64 and hit_count([0, 5, 0]) == 0
    # A second placement composes with where the node is now (tracked per scene).
    place(scene, {"box": _pose(0.0, [0, 5, 0])})
    assert hit_count([0, 5, 0]) == 64 and hit_count(box_to[:3, 3]) == 0
    reset_tracking(scene)
    with pytest.raises(UserError, match="'nothing' cannot be moved"):
        place(scene, {"nothing": target})
