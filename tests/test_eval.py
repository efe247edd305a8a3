"""``mi-invrgbl eval`` on a tiny hand-built scene in the documented layout.

The fixture writes DIR/scene.xml, frames.json, Gaussians PLYs (a ground, a
wall and one moving object), observations rendered from that very scene,
scene_lidar.xml with a non-default sensor response, and a synthetic ground
truth (maps from the render's AOVs, a time-B relit render, lights.json and a
trajectory.json whose world is rotated against the scene's) — so every
metric must come out perfect.
"""

import json
import math

import numpy as np
import pytest
import mitsuba as mi

from mi_invrgbl.eval.scoring import EVAL_SPP
from mi_invrgbl.physics.gaussian_ply import GaussianCloud, write_ply
from mi_invrgbl.io.images import write_exr, write_png
from mi_invrgbl.scene.frames import Frames, CAMERA_FLIP

W, H = 32, 24
FX = 20.0
N_FRAMES = 3
ELEVATIONS = "-4, -8, -12, -16, -20"
AZ = 48
#: Ground truth's world = the scene's, rotated by -90 degrees about z.
RZ = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])   # scene <- gt
TIME_B = {"sky_radiance": [0.3, 0.32, 0.4], "sun_irradiance": [2.0, 1.6, 1.1]}
SUN_B_SCENE = np.array([-0.4, 0.5, 0.77])
SUN_B_SCENE /= np.linalg.norm(SUN_B_SCENE)


def grid_cloud(centers, scale, normal, albedo, roughness, lidar_albedo):
    n = len(centers)
    return GaussianCloud(
        centers=np.asarray(centers, np.float32),
        scales=np.tile(np.float32(scale), (n, 1)),
        quaternions=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
        opacities=np.full(n, 0.98, np.float32),
        normals=np.tile(np.float32(normal), (n, 1)),
        albedo=np.asarray(albedo, np.float32).reshape(n, 3),
        roughness=np.asarray(roughness, np.float32).reshape(n),
        lidar_albedo=np.asarray(lidar_albedo, np.float32).reshape(n),
        sun_visibility=np.ones(n, np.float32))


def background_cloud():
    xs, ys = np.meshgrid(np.arange(-2, 14.01, 0.5), np.arange(-5, 5.01, 0.5))
    g = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], 1)
    stripe = (np.floor(g[:, 0] / 2) % 2 == 0)
    alb = np.where(stripe[:, None], [0.3, 0.28, 0.25], [0.12, 0.12, 0.13])
    ground = grid_cloud(g, [0.5, 0.5, 0.05], [0, 0, 1], alb, np.where(stripe, 0.6, 0.8),
                        np.where(stripe, 0.35, 0.12))
    ys, zs = np.meshgrid(np.arange(-5, 5.01, 0.5), np.arange(0.25, 4.01, 0.5))
    wpts = np.stack([np.full(ys.size, 12.0), ys.ravel(), zs.ravel()], 1)
    walb = np.tile([0.55, 0.45, 0.3], (len(wpts), 1))
    wall = grid_cloud(wpts, [0.05, 0.5, 0.5], [-1, 0, 0], walb, np.full(len(wpts), 0.4),
                      np.full(len(wpts), 0.5))
    return GaussianCloud(*[np.concatenate([getattr(ground, f), getattr(wall, f)])
                           for f in ("centers", "scales", "quaternions", "opacities", "normals",
                                     "albedo", "roughness", "lidar_albedo", "sun_visibility")])


def object_cloud():
    a = np.arange(-0.4, 0.41, 0.4)
    x, y, z = np.meshgrid(a, a, a)
    c = np.stack([x.ravel(), y.ravel(), z.ravel()], 1)
    n = len(c)
    return grid_cloud(c, [0.3, 0.3, 0.3], [0, 0, 1], np.tile([0.6, 0.1, 0.1], (n, 1)),
                      np.full(n, 0.3), np.full(n, 0.7))


def cam_to_world(i):
    m = np.eye(4)
    m[:3, :3] = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]   # dataset camera looking along +x
    m[:3, 3] = [1.0 * i, 0.0, 1.5]
    return m


def lidar_to_world(i):
    m = np.eye(4)
    m[:3, 3] = [1.0 * i, 0.0, 1.7]
    return m


def object_pose(i):
    m = np.eye(4)
    m[:3, 3] = [7.0, -1.5 + 1.2 * i, 0.7]
    return m


def mat(m):
    return " ".join("%.9g" % v for v in np.asarray(m).ravel())


def scene_xml(object_frame=0):
    fov = math.degrees(2 * math.atan(W / (2 * FX)))
    out = ['<scene version="3.0.0">',
           '<integrator type="invrgbl"><integer name="samples" value="8"/></integrator>',
           '<emitter type="shsun" id="sky"><integer name="order" value="1"/>'
           '<string name="sh" value="1.6 1.8 2.3  0 0 0  0.5 0.5 0.7  0 0 0"/>'
           '<vector name="sun_direction" x="0.3" y="0.4" z="0.85"/>'
           '<rgb name="sun_irradiance" value="3.0, 2.8, 2.5"/></emitter>',
           '<shape type="gaussians" id="background"><string name="filename" value="background.ply"/></shape>',
           '<shape type="gaussians" id="object_1"><string name="filename" value="object_1.ply"/>'
           '<transform name="to_world"><matrix value="%s"/></transform></shape>' % mat(object_pose(object_frame))]
    for i in range(N_FRAMES):
        out.append('<sensor type="perspective" id="camera_%04d"><float name="fov" value="%.9g"/>'
                   '<string name="fov_axis" value="x"/>'
                   '<transform name="to_world"><matrix value="%s"/></transform>'
                   '<sampler type="independent"><integer name="sample_count" value="1"/></sampler>'
                   '<film type="hdrfilm"><integer name="width" value="%d"/>'
                   '<integer name="height" value="%d"/><rfilter type="box"/></film></sensor>'
                   % (i, fov, mat(cam_to_world(i) @ CAMERA_FLIP), W, H))
        out.append('<sensor type="lidar" id="lidar_%04d"><string name="elevations" value="%s"/>'
                   '<float name="far_clip" value="60"/>'
                   '<transform name="to_world"><matrix value="%s"/></transform>'
                   '<film type="hdrfilm"><integer name="width" value="%d"/>'
                   '<integer name="height" value="5"/><rfilter type="box"/></film></sensor>'
                   % (i, ELEVATIONS, mat(lidar_to_world(i)), AZ))
    out.append("</scene>")
    return "\n".join(out)


LIDAR_XML = """<scene version="3.0.0">
    <default name="gain" value="1.2"/>
    <integrator type="lidar_return">
        <string name="model" value="pbr"/>
        <float name="range_exponent" value="0.5"/>
        <float name="angle_exponent" value="0.8"/>
        <string name="beam_gains" value="1.0, $gain, 0.9, 1.1, 1.0"/>
    </integrator>
</scene>
"""


def frames_json(root, gt_dir):
    frames = []
    for i in range(N_FRAMES):
        frames.append({"index": i, "time": 0.1 * i, "held_out": i == 2,
                       "camera": "camera_%04d" % i, "lidar": "lidar_%04d" % i,
                       "image": "observations/image_%04d.png" % i,
                       "lidar_scan": "observations/lidar_%04d.exr" % i,
                       "points": "observations/points_%04d.npy" % i,
                       "camera_to_world": cam_to_world(i).tolist(),
                       "lidar_to_world": lidar_to_world(i).tolist(),
                       "objects": {"object_1": object_pose(i).tolist()}})
    return {"format": "mi-invrgbl-frames/1", "source": str(root),
            "camera": {"width": W, "height": H, "fx": FX, "fy": FX, "cx": W / 2, "cy": H / 2},
            "lidar": {"beams": 5, "azimuth_steps": AZ,
                      "elevations_deg": [float(e) for e in ELEVATIONS.split(",")],
                      "intensity": "raw"},
            "objects": {"object_1": {"track_id": 1, "kind": "Car", "size_hwl": [1, 1, 1],
                                     "moving": True, "ply": "object_1.ply"}},
            "ground_truth": {"dir": str(gt_dir)},
            "frames": frames}


def aov(img, names, key):
    idx = [i for i, n in enumerate(names) if n == key or n.startswith(key + ".")]
    return img[..., idx] if len(idx) > 1 else img[..., idx[0]]


@pytest.fixture(scope="module")
def fit_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("evalscene")
    gt = root / "gt"
    for d in ("observations", "gt/maps", "gt/time_b"):
        (root / d).mkdir(parents=True)
    write_ply(str(root / "background.ply"), background_cloud())
    write_ply(str(root / "object_1.ply"), object_cloud())
    (root / "scene.xml").write_text(scene_xml())
    (root / "scene_lidar.xml").write_text(LIDAR_XML)
    (root / "frames.json").write_text(json.dumps(frames_json(root, gt), indent=1))
    lights = {"time_b": {**TIME_B, "sun_direction": (RZ.T @ SUN_B_SCENE).tolist()}}
    (gt / "lights.json").write_text(json.dumps(lights))
    (gt / "trajectory.json").write_text(json.dumps(
        {"world_from_cam": [(np.block([[RZ.T, np.zeros((3, 1))], [np.zeros((1, 3)), 1]])
                             @ cam_to_world(i)).tolist() for i in range(N_FRAMES)]}))

    lidar_integ = mi.load_string(LIDAR_XML.replace("$gain", "1.2")).integrator()
    for i in range(N_FRAMES):
        # Observations independent of set_frame: the object loaded at frame i's pose.
        (root / "frame.xml").write_text(scene_xml(object_frame=i))
        scene = mi.load_file(str(root / "frame.xml"))
        params = mi.traverse(scene)
        cam = next(s for s in scene.sensors() if s.id() == "camera_%04d" % i)
        lidar = next(s for s in scene.sensors() if s.id() == "lidar_%04d" % i)
        # At eval's own sample count, so that eval's render repeats this one.
        img = np.array(mi.render(scene, sensor=cam, spp=EVAL_SPP), np.float32)
        names = [f.name for f in cam.film().bitmap().struct_()]
        write_png(str(root / "observations" / ("image_%04d.png" % i)), img[..., :3])
        scan = np.array(mi.render(scene, sensor=lidar, integrator=lidar_integ), np.float32)
        write_exr(str(root / "observations" / ("lidar_%04d.exr" % i)), scan[..., :3],
                  ["intensity", "range", "hit"])
        dirs = lidar.ray_directions_local() @ lidar_to_world(i)[:3, :3].T
        hit = scan[..., 2] > 0.5
        pts = lidar_to_world(i)[:3, 3] + dirs[hit] * scan[..., 1][hit][:, None]
        np.save(root / "observations" / ("points_%04d.npy" % i),
                np.column_stack([pts, scan[..., 0][hit]]).astype(np.float32))
        # ground truth: the render's own AOVs (divided by alpha), gt world rotated
        alpha = aov(img, names, "alpha")
        inv = 1.0 / np.maximum(alpha, 1e-6)
        covered = alpha > 0.5
        write_exr(str(gt / "maps" / ("%06d_albedo.exr" % i)),
                  aov(img, names, "albedo") * inv[..., None], ["R", "G", "B"])
        write_exr(str(gt / "maps" / ("%06d_roughness.exr" % i)),
                  aov(img, names, "roughness") * inv, ["Y"])
        write_exr(str(gt / "maps" / ("%06d_lidar_albedo.exr" % i)),
                  aov(img, names, "lidar_albedo") * inv, ["Y"])
        n = aov(img, names, "normal")
        write_exr(str(gt / "maps" / ("%06d_normal.exr" % i)), n @ RZ, ["R", "G", "B"])
        write_exr(str(gt / "maps" / ("%06d_mesh_id.exr" % i)),
                  np.where(covered, 0.0, -1.0).astype(np.float32), ["Y"])
        # time B: constant sky (SH order 0 of an order-1 emitter) + the B sun
        sh = np.zeros(12, np.float32)
        sh[:3] = np.array(TIME_B["sky_radiance"]) / 0.28209479177387814
        params["sky.sh"] = mi.Float(sh)
        params["sky.sun_direction"] = mi.Vector3f(*[float(v) for v in SUN_B_SCENE])
        params["sky.sun_irradiance"] = mi.Color3f(*TIME_B["sun_irradiance"])
        params.update()
        relit = np.array(mi.render(scene, sensor=cam, spp=EVAL_SPP), np.float32)[..., :3]
        write_exr(str(gt / "time_b" / ("%06d.exr" % i)), relit, ["R", "G", "B"])
    (root / "frame.xml").unlink()
    return root


def test_eval_perfect_on_own_renders(fit_dir, capsys):
    from mi_invrgbl.cli import main
    out = fit_dir / "m.json"
    assert main(["eval", str(fit_dir), "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "PSNR" in printed and "mean" in printed
    res = json.loads(out.read_text())
    assert [r["index"] for r in res["frames"]] == [2]
    m = res["mean"]
    assert m["psnr"] > 45          # only the PNG's 8-bit rounding
    assert m["ssim"] > 0.99
    assert m["lidar_intensity_rmse"] < 1e-5
    assert m["range_error"] < 1e-5
    assert m["ray_drop_accuracy"] == 1.0
    assert m["albedo_rmse"] < 1e-4
    # The references are scored beside it, on the same pixels.
    assert math.isfinite(m["albedo_rmse_flat"]) and math.isfinite(m["albedo_rmse_chromaticity"])
    assert "alb-flat" in printed and "alb-chr" in printed
    assert m["roughness_mae"] < 1e-4
    assert m["normal_angle_deg"] < 0.1       # through the RZ world alignment
    assert m["lidar_albedo_rmse"] < 1e-4
    assert m["relight_psnr"] > 60            # the time-B sun rotated into the scene's world
    assert m["gt_coverage"] > 0.99
    assert "baseline_intensity_rmse" in m and m["baseline_intensity_rmse"] >= 0
    assert res["lidar_response"].endswith("scene_lidar.xml")
    assert res["camera_spp"] == EVAL_SPP > 4     # not the imported scenes' 4 spp


def test_eval_raw_point_score_and_full_baseline(fit_dir, capsys):
    """eval scores the LiDAR twice: on the range image and on the raw held-out
    points along their own rays, the lookup built from every training point."""
    from mi_invrgbl.cli import main
    out = fit_dir / "raw.json"
    assert main(["eval", str(fit_dir), "-o", str(out), "--no-relight"]) == 0
    printed = capsys.readouterr().out
    for col in ("I-RMSE", "NN-RMSE", "I-raw", "NN-raw", "drop-F1"):
        assert col in printed
    res = json.loads(out.read_text())
    row = res["frames"][0]
    # The observations are the scene's own renders: perfect along the fired rays too.
    assert row["raw_intensity_rmse"] < 1e-4 and row["raw_range_error"] < 1e-3
    assert row["raw_drop_accuracy"] == 1.0 and row["raw_coverage"] == 1.0
    assert row["raw_baseline_intensity_rmse"] > 1e-3     # the lookup from frames 0 and 1
    raw = res["lidar_raw_points"]
    scan = np.load(fit_dir / "observations" / "points_0002.npy")
    hits = (json.loads((fit_dir / "frames.json").read_text())["lidar"]["beams"] * AZ)
    assert raw["returns"] == len(scan) and raw["returns"] + raw["non_returns"] == hits
    assert raw["model"]["drop_f1"] == 1.0 or raw["non_returns"] == 0
    # Every training point, no subsample.
    n_train = sum(len(np.load(fit_dir / "observations" / ("points_%04d.npy" % i))) for i in (0, 1))
    assert raw["train_points"] == n_train
    assert raw["baseline"]["intensity_rmse_on_model_returns"] == pytest.approx(
        row["raw_baseline_intensity_rmse"])


def test_eval_image_baseline_is_the_nearest_training_image(fit_dir, capsys):
    """The camera's lookup baseline shows the nearest training frame (frame 1,
    1 m from the scored frame 2; frame 0 is 2 m away) unchanged and scores it
    like a render."""
    from mi_invrgbl.cli import main
    from mi_invrgbl.eval import metrics as M
    from mi_invrgbl.eval.inputs import read_png
    out = fit_dir / "img.json"
    assert main(["eval", str(fit_dir), "-o", str(out), "--no-relight"]) == 0
    assert "NN-PSNR" in capsys.readouterr().out
    row = json.loads(out.read_text())["frames"][0]
    assert row["baseline_frame"] == 1
    obs = fit_dir / "observations"
    shown, truth = read_png(obs / "image_0001.png"), read_png(obs / "image_0002.png")
    assert row["baseline_psnr"] == pytest.approx(M.psnr(shown, truth, 1.0), abs=1e-9)
    assert row["baseline_psnr"] < 60        # the object moved and the camera with it
    assert row["psnr"] > row["baseline_psnr"]
    assert 0 < row["baseline_ssim"] < 1


def test_nearest_training_frame_rules(tmp_path):
    """Never a held-out or scored frame, nor one looking elsewhere, nor one
    without an image; None when nothing is left."""
    from types import SimpleNamespace
    from mi_invrgbl.eval.baselines import nearest_training_frame
    img = tmp_path / "i.png"
    img.write_bytes(b"png")

    def rec(x, held=False, yaw_deg=0.0, image=True):
        m = cam_to_world(0)
        c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
        m[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ m[:3, :3]
        m[:3, 3] = [x, 0.0, 1.5]
        return SimpleNamespace(camera_to_world=m, held_out=held, image=str(img) if image else None)

    # positions: 0 scored; 1 held out (nearest); 2 looks sideways (next
    # nearest); 3 has no image; 4 is the nearest usable one; 5 is farther.
    frames = [rec(0.0), rec(0.1, held=True), rec(0.2, yaw_deg=60), rec(0.3, image=False),
              rec(0.5, yaw_deg=30), rec(2.0)]
    assert nearest_training_frame(frames, 0, [0]) == 4
    assert nearest_training_frame(frames, 0, [0, 4]) == 5
    assert nearest_training_frame(frames, 0, [0, 4, 5]) is None


def test_image_baseline_skips_an_image_of_another_size(tmp_path):
    """A training image whose size differs from the scored one is no
    baseline (no score rather than a broadcast error)."""
    from types import SimpleNamespace
    from mi_invrgbl.eval.scoring import image_baseline
    small, big = tmp_path / "small.png", tmp_path / "big.png"
    write_png(str(small), np.full((4, 6, 3), 0.2, np.float32))
    write_png(str(big), np.full((8, 6, 3), 0.2, np.float32))
    frames = [SimpleNamespace(index=i, camera_to_world=cam_to_world(i), held_out=False, image=str(p))
              for i, p in enumerate((small, small, big))]
    observed = np.full((4, 6, 3), 0.25)
    assert image_baseline(frames, 0, [0], observed)["baseline_frame"] == 1
    assert image_baseline(frames, 1, [1], observed)["baseline_frame"] == 0
    assert image_baseline(frames, 1, [0, 1], observed) == {}     # only frame 2 left: 8x6


def test_lookup_keeps_every_training_point(tmp_path):
    """More points than any former subsample cap (2e6): all kept, still fast."""
    import time
    from types import SimpleNamespace
    from mi_invrgbl.eval.lidar_novel_view import build_lookup
    rng = np.random.default_rng(2)
    recs = []
    for i in range(3):
        pts = np.column_stack([rng.uniform(0, 60, (750_000, 2)), rng.uniform(0, 3, 750_000),
                               rng.uniform(0, 1, 750_000)]).astype(np.float32)
        np.save(tmp_path / ("p%d.npy" % i), pts)
        recs.append(SimpleNamespace(points=str(tmp_path / ("p%d.npy" % i)), held_out=False))
    recs.append(SimpleNamespace(points=None, held_out=True))

    class FakeFrames(list):
        pass
    t = time.perf_counter()
    lookup = build_lookup(FakeFrames(recs), [3])
    assert len(lookup) == 2_250_000 and lookup.sweeps == 3
    q = np.load(tmp_path / "p1.npy")[:1000]
    np.testing.assert_allclose(lookup.nn.predict(q[:, :3]), q[:, 3])
    assert time.perf_counter() - t < 30


def test_eval_frames_and_default_response(fit_dir, tmp_path):
    import shutil
    from mi_invrgbl.eval.scoring import evaluate
    # a copy without scene_lidar.xml: the default response mismatches the observations
    copy = tmp_path / "fit"
    shutil.copytree(fit_dir, copy, ignore=shutil.ignore_patterns("scene_lidar.xml", "gt"))
    fj = json.loads((copy / "frames.json").read_text())
    del fj["ground_truth"]
    (copy / "frames.json").write_text(json.dumps(fj))
    res = evaluate(str(copy / "scene.xml"), "0:2", baseline=False, log=lambda *a: None)
    assert [r["index"] for r in res["frames"]] == [0, 1]
    assert res["ground_truth"] is None and "albedo_rmse" not in res["mean"]
    assert res["mean"]["lidar_intensity_rmse"] > 1e-3
    assert res["mean"]["range_error"] < 1e-5
    assert res["mean"]["psnr"] > 45           # object placed per frame by set_frame


def test_eval_errors(fit_dir, tmp_path, capsys):
    from mi_invrgbl.cli import main
    from mi_invrgbl.eval.inputs import select_frames
    assert main(["eval", str(tmp_path / "nope")]) == 2
    assert "no such fit folder" in capsys.readouterr().err
    assert main(["eval", str(tmp_path)]) == 2
    assert "no scene.xml" in capsys.readouterr().err
    frames = Frames.load(fit_dir)
    assert select_frames(frames, "all") == [0, 1, 2]
    assert select_frames(frames, "1,2") == [1, 2]
    assert select_frames(frames, ":1") == [0]
    from mi_invrgbl.errors import UserError
    for bad in ("7", "x:y", "5:9"):
        with pytest.raises(UserError):
            select_frames(frames, bad)
    bad_dir = tmp_path / "bad"
    bad_dir.mkdir()
    (bad_dir / "scene.xml").write_text("<scene version='3.0.0'><shape type='nosuch'/></scene>")
    (bad_dir / "frames.json").write_text((fit_dir / "frames.json").read_text())
    assert main(["eval", str(bad_dir), "--frames", "all"]) == 2
    assert "cannot load scene" in capsys.readouterr().err


def test_nn_baseline():
    from mi_invrgbl.eval.baselines import NearestNeighbourIntensity, load_points
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-20, 20, (5000, 3)) + [500, -300, 0],
                           rng.uniform(0, 1, 5000)])
    nn = NearestNeighbourIntensity(pts)
    q = pts[:200, :3] + rng.normal(0, 1e-3, (200, 3))
    np.testing.assert_allclose(nn.predict(q), pts[:200, 3], rtol=1e-6)
    # exact nearest neighbour against brute force
    q2 = rng.uniform(-20, 20, (100, 3)) + [500, -300, 0]
    brute = np.argmin(((q2[:, None] - pts[None, :, :3]) ** 2).sum(-1), axis=1)
    np.testing.assert_allclose(nn.predict(q2), pts[brute, 3], rtol=1e-6)
    far = NearestNeighbourIntensity(pts, max_distance=0.5, fill=-1.0)
    assert far.predict(np.array([[0.0, 0.0, 0.0]]))[0] == -1.0
    # a range image
    dirs = np.zeros((2, 3, 3))
    dirs[..., 0] = 1
    rng_img = np.array([[1.0, 0, 2], [0, 3, 0]])
    base = NearestNeighbourIntensity(np.array([[1, 0, 0, 0.2], [2, 0, 0, 0.5], [3, 0, 0, 0.9]]))
    np.testing.assert_allclose(base.predict_scan(rng_img, dirs, [0, 0, 0]),
                               [[0.2, 0, 0.5], [0, 0.9, 0]])
    with pytest.raises(FileNotFoundError):
        load_points(["/nonexistent/points_0000.npy"])


@pytest.mark.slow
def test_nn_baseline_million_points_fast():
    import time
    from mi_invrgbl.eval.baselines import NearestNeighbourIntensity
    rng = np.random.default_rng(1)
    pts = np.column_stack([rng.uniform(0, 80, (1_000_000, 3)), rng.uniform(0, 1, 1_000_000)])
    t = time.perf_counter()
    nn = NearestNeighbourIntensity(pts)
    nn.predict(rng.uniform(0, 80, (131072, 3)))
    assert time.perf_counter() - t < 10



def test_eval_keeps_what_fit_wrote(fit_dir):
    from mi_invrgbl.cli import main
    out = fit_dir / "fit_and_eval.json"
    # As fit leaves it (the keys eval recognises a fit's metrics file by).
    out.write_text('{"selection": {"sun": {"use_sun": true}}, "wall_s": 12.5, '
                   '"heldout_psnr": 21.5, "config": {"seed": 0}}')
    assert main(["eval", str(fit_dir), "-o", str(out), "--no-baseline", "--no-relight"]) == 0
    res = json.loads(out.read_text())
    assert res["fit"]["wall_s"] == 12.5 and res["fit"]["selection"]["sun"]["use_sun"]
    assert "mean" in res
    assert main(["eval", str(fit_dir), "-o", str(out), "--no-baseline", "--no-relight"]) == 0
    assert json.loads(out.read_text())["fit"]["wall_s"] == 12.5          # a second eval keeps it


def test_eval_reads_scan_channels_by_name(fit_dir, tmp_path, capsys):
    import shutil
    from mi_invrgbl.cli import main
    from mi_invrgbl.eval.scoring import evaluate
    from mi_invrgbl.io.images import read_exr
    copy = tmp_path / "fit"
    shutil.copytree(fit_dir, copy, ignore=shutil.ignore_patterns("gt"))
    scan_path = copy / "observations" / "lidar_0002.exr"
    arr, names = read_exr(str(scan_path))
    scan = {n: arr[..., k] for k, n in enumerate(names)}
    # The same scan with its channels in another order: scored the same.
    order = ["range", "hit", "intensity"]
    write_exr(str(scan_path), np.stack([scan[n] for n in order], -1), order)
    res = evaluate(str(copy), "held-out", baseline=False, relight=False, log=lambda *a: None)
    assert res["mean"]["lidar_intensity_rmse"] < 1e-5 and res["mean"]["range_error"] < 1e-5
    # Channels named otherwise are refused, never guessed by position.
    write_exr(str(scan_path), np.stack([scan[n] for n in ("intensity", "range", "hit")], -1),
              ["I", "R", "H"])
    assert main(["eval", str(copy), "--no-baseline", "--no-relight", "-o", str(tmp_path / "m.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "lidar_0002.exr" in err[0] and "no channel 'intensity', 'range', 'hit'" \
        in err[0] and all(c in err[0].split("(it has ")[1] for c in "HIR"), err
    assert not (tmp_path / "m.json").exists()


def test_return_samples_follow_the_moving_object(fit_dir):
    """The ray-drop model's samples see each frame's object where it is: the
    scene's own renders give every observed range back, beam for beam."""
    from mi_invrgbl.eval.rendering import load_lidar_integrator
    from mi_invrgbl.fit.response import scene_return_samples
    from mi_invrgbl.io.images import read_exr
    frames = Frames.load(fit_dir)
    scene = mi.load_file(str(fit_dir / "scene.xml"))
    integ = load_lidar_integrator(fit_dir / "scene_lidar.xml")
    dist, cos, rho, beam, ret = scene_return_samples(scene, integ, frames, [2, 0, 1])
    obs, hits = [], []
    for i in (2, 0, 1):
        arr, names = read_exr(str(fit_dir / "observations" / ("lidar_%04d.exr" % i)))
        hit = arr[..., names.index("hit")].ravel() > 0.5
        obs.append(arr[..., names.index("range")].ravel()[hit])
        hits.append(hit)
    obs = np.concatenate(obs)
    assert ret.all() and dist.shape == obs.shape
    np.testing.assert_allclose(dist, obs, atol=1e-3)
    # A budget of beams: every stride-th beam of each frame, starting at the
    # frame's position modulo stride, each the same sample as rendered in
    # full (here every beam that reaches a surface is an observed hit).
    size = hits[0].size
    budget = 3 * size // 4
    stride = int(np.ceil(3 * size / budget))
    keep = []
    for i, hit in zip((2, 0, 1), hits):
        picked = np.zeros(hit.size, bool)
        picked[i % stride::stride] = True
        keep.append(picked[hit])
    keep = np.concatenate(keep)
    assert stride > 1
    sub = scene_return_samples(scene, integ, frames, [2, 0, 1], max_beams=budget)
    full = (dist, cos, rho, beam, ret)
    assert 0 < sub[0].size == keep.sum() < full[0].size
    for a, b in zip(sub, full):
        np.testing.assert_allclose(a, b[keep], atol=1e-5)


def test_metrics_json_is_strict_with_non_finite_scores(tmp_path):
    # A PSNR of identical images (+inf) is written as PSNR_CAP; a score that
    # could not be computed (NaN, -inf) as null; numpy values as Python ones.
    # The file must parse without JSON's non-standard NaN/Infinity constants.
    from mi_invrgbl.eval.scoring import PSNR_CAP, json_clean
    from mi_invrgbl.scene.frames import json_safe, write_json
    data = {"psnr": np.float32(np.inf), "rmse": float("nan"), "low": -np.inf,
            "n": np.int64(3), "ok": np.bool_(True), "per_beam": np.array([0.5, np.nan]),
            "nested": [{"x": np.float64(1.25)}]}
    clean = json_clean(data)
    assert clean == {"psnr": PSNR_CAP, "rmse": None, "low": None, "n": 3, "ok": True,
                     "per_beam": [0.5, None], "nested": [{"x": 1.25}]}
    assert json_safe({"psnr": np.inf})["psnr"] is None      # no cap unless asked for

    def refuse(constant):
        raise AssertionError("non-standard JSON constant " + constant)
    path = write_json(tmp_path / "metrics.json", clean)
    assert json.loads(path.read_text(), parse_constant=refuse) == clean


def test_a_changed_integrator_keeps_every_other_setting():
    """eval's relighting swaps a fit's learned sun visibility for traced
    shadows (``integrator_like``); the copy must keep the coat, the
    shadowing term and every other setting, or the relit scene is shaded
    with another BRDF than the one fitted."""
    from mi_invrgbl.eval.rendering import integrator_like
    settings = {"type": "invrgbl", "samples": 12, "bounces": 1, "max_hits": 33,
                "min_transmittance": 0.02, "sun_visibility": "attribute", "f0": 0.05,
                "diffuse_fresnel": True, "hide_emitters": True, "shadowing": "smith",
                "moving": "object_0 object_3"}
    scene = mi.load_dict({"type": "scene", "integrator": settings})
    assert scene.integrator().settings() == settings
    assert integrator_like(scene) is None
    copy = integrator_like(scene, samples=7, sun_visibility="trace")
    assert copy.settings() == dict(settings, samples=7, sun_visibility="trace")


def test_relighting_from_the_fitted_light_forgives_its_scale(fit_dir, tmp_path):
    """The images fix albedo times light, not either alone. A truth whose
    albedo is half the scene's under a light twice the scene's draws the same
    images: the truth's time-B light put in as it is then relights twice too
    bright, while the fitted light edited by the truth's time-B / time-A
    ratios (what ``mi-invrgbl relight`` does to a fitted scene) relights as the
    truth does."""
    import shutil
    from mi_invrgbl.eval.scoring import evaluate
    from mi_invrgbl.physics.sh import Y0
    copy = tmp_path / "fit"
    shutil.copytree(fit_dir, copy)
    # A constant fitted sky, so that per-channel ratios carry it exactly to time B's.
    xml = (copy / "scene.xml").read_text()
    sh = "1.6 1.8 2.3  0 0 0  0.5 0.5 0.7  0 0 0"
    assert sh in xml
    (copy / "scene.xml").write_text(xml.replace(sh, "1.6 1.8 2.3  0 0 0  0 0 0  0 0 0"))
    frames = json.loads((copy / "frames.json").read_text())
    frames["ground_truth"]["dir"] = str(copy / "gt")
    (copy / "frames.json").write_text(json.dumps(frames))
    s = 2.0
    fitted = {"sky_radiance": [1.6 * Y0, 1.8 * Y0, 2.3 * Y0], "sun_irradiance": [3.0, 2.8, 2.5]}
    lights = {"time_a": {k: [s * x for x in v] for k, v in fitted.items()},
              "time_b": {**{k: [s * x for x in v] for k, v in TIME_B.items()},
                         "sun_direction": (RZ.T @ SUN_B_SCENE).tolist()}}
    lights["time_a"]["sun_direction"] = (RZ.T @ np.array([0.3, 0.4, 0.85])).tolist()
    (copy / "gt" / "lights.json").write_text(json.dumps(lights))
    res = evaluate(str(copy), "held-out", baseline=False, log=lambda *a: None)
    m = res["mean"]
    assert m["relight_edit_psnr"] > 60, m["relight_edit_psnr"]
    assert m["relight_psnr"] < 25, m["relight_psnr"]
    assert "relight_edit_psnr" in res["notes"]


def test_edit_ratios():
    from mi_invrgbl.eval.scoring import edit_ratios
    sky, sun = edit_ratios({"time_a": {"sky_radiance": [0.5, 1, 2], "sun_irradiance": [4, 0, 2]},
                            "time_b": {"sky_radiance": [1, 1, 1], "sun_irradiance": [2, 3, 2]}})
    assert np.allclose(sky, [2, 1, 0.5]) and np.allclose(sun, [0.5, 0, 1])   # no time-A sun: none
    assert edit_ratios({"time_b": {"sky_radiance": [1, 1, 1]}}) is None
    from mi_invrgbl.errors import UserError
    for bad in ([1, 2], [1, float("nan"), 1], [1, -1, 1], "bright"):
        with pytest.raises(UserError, match=r"gt/lights.json: time_a.sky_radiance must be three finite"):
            edit_ratios({"time_a": {"sky_radiance": bad, "sun_irradiance": [1, 1, 1]},
                         "time_b": {"sky_radiance": [1, 1, 1], "sun_irradiance": [1, 1, 1]}},
                        "gt/lights.json")


def test_albedo_references():
    """The albedo references against closed forms: a flat map scores the
    truth's spread about its per-channel mean; the photo's chromaticity is
    right where the shading is grey and every albedo has one brightness,
    and wrong where the light is coloured."""
    from mi_invrgbl.eval import metrics as M
    from mi_invrgbl.eval.baselines import albedo_references
    rng = np.random.default_rng(3)
    h, w = 24, 32
    hue = rng.uniform(0.2, 1.0, (h, w, 3))
    albedo = 0.4 * hue / hue.mean(axis=2, keepdims=True)       # one brightness, many hues
    grey = rng.uniform(0.3, 1.0, (h, w, 1))                      # shading, grey
    mask = np.ones((h, w), bool)
    mask[0, :] = False
    photo = np.round(np.clip(M.linear_to_srgb(albedo * grey), 0, 1) * 255) / 255

    refs = albedo_references(photo)
    flat = M.albedo_rmse_scaled(refs["flat"], albedo, mask)
    spread = math.sqrt(np.mean((albedo[mask] - albedo[mask].mean(axis=0)) ** 2))
    assert flat == pytest.approx(spread, rel=1e-9)
    assert M.albedo_rmse_scaled(refs["chromaticity"], albedo, mask) < 0.01 < flat / 5

    # Light of two colours (a warm sun on one half, a blue sky on the
    # other) is taken for the albedo's colour; one scale cannot undo both.
    tint = np.where(np.arange(w)[None, :, None] < w // 2, [1.0, 0.6, 0.3], [0.3, 0.6, 1.0])
    tinted = np.round(np.clip(M.linear_to_srgb(albedo * grey * tint), 0, 1) * 255) / 255
    assert M.albedo_rmse_scaled(albedo_references(tinted)["chromaticity"], albedo, mask) > 0.05

    dark = photo.copy()
    dark[3, 4] = 0.0
    chroma = albedo_references(dark)["chromaticity"]
    assert np.all(np.isfinite(chroma)) and np.all(chroma[3, 4] == 1.0)   # no hue: grey
    with pytest.raises(ValueError, match="H, W, 3"):
        albedo_references(photo[..., 0])
