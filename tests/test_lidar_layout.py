"""Beam layout from the data: synthetic sweeps of three sensors (a non-uniform
VLP-32C stored in shuffled order, an OS1-128 and an explicit solid-state ray
pattern) imported, and their beam layout recovered exactly."""

import json

import numpy as np
import pytest
import mitsuba as mi

from mi_invrgbl.errors import UserError
from mi_invrgbl.io.range_image import detect_beam_layout, range_image
from mi_invrgbl.physics.beam_layout import elevation_clusters, ray_beams
from mi_invrgbl.synthetic import StreetConfig, generate_street, sensors, writers

FRAMES = 2


def solid_state_rays(path):
    """The generator's example solid-state pattern (20 non-uniform rows, not a grid)."""
    rays = sensors.solid_state_rays()
    np.save(path, rays)
    el = np.arctan2(rays[:, 5], np.hypot(rays[:, 3], rays[:, 4]))
    return np.degrees([np.median(el[rays[:, 6] == k]) for k in range(20)])


@pytest.fixture(scope="module")
def streets(tmp_path_factory):
    mi.set_variant("llvm_ad_rgb")
    root = tmp_path_factory.mktemp("sensors")
    solid = solid_state_rays(root / "solid.npy")
    out = {}
    for name, lidar, inten in (("vlp32", "vlp32", "raw"), ("os128", "os128", "reflectivity"),
                               ("rays", "rays:%s" % (root / "solid.npy"), "raw")):
        path = root / name
        generate_street(str(path), StreetConfig(seed=5, frames=FRAMES, width=16, height=8, spp=1,
                                                azimuth_steps=128, night=False, lidar=lidar,
                                                intensity=inten), log=lambda *a: None)
        out[name] = path
    out["solid_elevations"] = solid
    return out


def sweeps(path, shuffle=None):
    pts = [writers.read_velodyne(str(path / "sequences" / "00" / "velodyne" / ("%06d.bin" % i)))
           for i in range(FRAMES)]
    if shuffle is not None:
        pts = [p[shuffle.permutation(len(p))] for p in pts]
    return pts


def truth(path):
    return json.loads((path / "gt" / "trajectory.json").read_text())["lidar"]


def test_vlp32_non_uniform_shuffled(streets):
    pts = sweeps(streets["vlp32"], np.random.default_rng(0))
    layout = detect_beam_layout([p[:, :3] for p in pts])
    assert layout.kind == "spinning" and layout.method == "histogram"
    assert layout.n_beams == 32 and not layout.uniform
    assert np.allclose(np.degrees(layout.elevations), sensors.VLP32C_DEG, atol=1e-3)
    assert "32 beams, non-uniform" in layout.describe()
    # Every point gets its true beam: its row in the ground-truth range image.
    ri = range_image(pts[0][:, :3], pts[0][:, 3], width=128, beam_elevations=layout.elevations)
    gt = writers.read_exr(str(streets["vlp32"] / "gt" / "lidar" / "000000.exr"))
    assert np.array_equal(ri.hit, gt["hit"] > 0.5)
    # The old default (KITTI's firing order, else 64 clusters) would not find 32.
    assert truth(streets["vlp32"])["beams"] == 32


def test_os128_uniform(streets):
    layout = detect_beam_layout([p[:, :3] for p in sweeps(streets["os128"])])
    assert layout.kind == "spinning" and layout.n_beams == 128 and layout.uniform
    assert np.allclose(np.degrees(layout.elevations), np.linspace(22.5, -22.5, 128), atol=1e-3)


def test_explicit_ray_pattern(streets):
    path = streets["rays"]
    layout = detect_beam_layout([p[:, :3] for p in sweeps(path)])
    assert layout.kind == "rays"
    assert layout.n_beams == 20
    assert np.allclose(np.degrees(layout.elevations), streets["solid_elevations"], atol=1e-3)
    # The recovered rays are exactly the pattern's rays that returned in some sweep,
    # each with its own beam.
    pattern = np.load(path / "gt" / "lidar_rays.npy")
    hit = np.zeros(len(pattern), bool)
    for i in range(FRAMES):
        hit |= writers.read_exr(str(path / "gt" / "lidar" / ("%06d.exr" % i)))["hit"].ravel() > 0.5
    want = pattern[hit]
    assert len(layout.rays) == len(want)
    cos = layout.rays @ want[:, 3:6].T
    match = np.argmax(cos, axis=1)
    assert np.all(cos[np.arange(len(match)), match] > 1 - 1e-9)
    assert len(np.unique(match)) == len(match)
    assert np.array_equal(layout.ray_beam, want[match, 6].astype(int))


def test_street_metadata_and_reflectivity(streets):
    li = truth(streets["os128"])
    assert li["sensor"] == "os128" and li["intensity"] == "reflectivity"
    assert len(li["beam_gains"]) == 128 and np.ptp(li["beam_gains"]) > 0.1
    assert truth(streets["rays"])["rays"] == "gt/lidar_rays.npy"


def test_histogram_refuses_overlapping_beams():
    rng = np.random.default_rng(1)
    # Two beams 0.4 deg apart, each smeared over 1 deg (a multi-origin head).
    e = np.radians(np.concatenate([rng.uniform(-0.5, 0.5, 2000), rng.uniform(-0.9, 0.1, 2000)]))
    assert not elevation_clusters(e).separated


def test_rosette_is_one_beam():
    rng = np.random.default_rng(2)
    d = rng.normal(size=(500, 3))
    d[:, 0] = np.abs(d[:, 0]) + 2
    beam, table = ray_beams(d)
    assert table.size == 1 and np.all(beam == 0)


def test_bad_lidar_options(tmp_path):
    with pytest.raises(UserError, match="--lidar"):
        StreetConfig(lidar="hdl32").validate()
    with pytest.raises(UserError, match="cannot read"):
        StreetConfig(lidar="rays:%s" % (tmp_path / "none.npy")).validate()
    np.save(tmp_path / "bad.npy", np.zeros((4, 5)))
    with pytest.raises(UserError, match=r"\(N, 6\)"):
        StreetConfig(lidar="rays:%s" % (tmp_path / "bad.npy")).validate()
    with pytest.raises(UserError, match="--intensity"):
        StreetConfig(intensity="dB").validate()


def test_import_finds_the_vlp32_layout(streets, tmp_path):
    """``import`` of the VLP-32C street, its sweeps stored shuffled: 32 beams
    with the sensor's table in frames.json and the scene, reported in the log."""
    import shutil
    from mi_invrgbl.io.importer import ImportOptions, import_scene
    data = tmp_path / "street"
    shutil.copytree(streets["vlp32"], data)
    rng = np.random.default_rng(3)
    for i in range(FRAMES):
        f = data / "sequences" / "00" / "velodyne" / ("%06d.bin" % i)
        p = writers.read_velodyne(str(f))
        writers.write_velodyne(str(f), p[rng.permutation(len(p))])
    lines = []
    import_scene(data, tmp_path / "out" / "scene.xml",
                 ImportOptions(max_points=3000, azimuth_steps=128, object_points=50, verify=False),
                 log=lambda *a: lines.append(" ".join(map(str, a))))
    assert any("32 beams, non-uniform" in ln for ln in lines), lines
    frames = json.loads((tmp_path / "out" / "frames.json").read_text())
    assert frames["lidar"]["beams"] == 32
    assert np.allclose(frames["lidar"]["elevations_deg"], sensors.VLP32C_DEG, atol=1e-3)


def test_cli_lidar_options_are_checked(tmp_path, capsys):
    from mi_invrgbl.cli import main
    assert main(["make-scene", "street", str(tmp_path / "o"), "--lidar", "hdl32"]) == 2
    err = capsys.readouterr().err
    assert "--lidar must be one of hdl64, vlp32, os128 or rays:FILE" in err and len(err.strip().splitlines()) == 1
    assert main(["make-scene", "street", str(tmp_path / "o"), "--lidar", "rays:%s" % (tmp_path / "x.npy")]) == 2
    assert "cannot read the ray list" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_import_explicit_pattern_in_rays_mode(streets, tmp_path):
    """``import`` of the solid-state street writes ``lidar`` sensors in ``rays``
    mode (the recovered pattern next to the scene), one N x 1 scan per sweep
    on those rays, and the scene loads and renders them."""
    import shutil
    from mi_invrgbl.io.images import read_exr
    from mi_invrgbl.io.importer import ImportOptions, import_scene
    from mi_invrgbl.scene.frames import Frames
    import_scene(streets["rays"], tmp_path / "out" / "scene.xml",
                 ImportOptions(max_points=3000, azimuth_steps=128, object_points=50, verify=False),
                 log=lambda *a: None)
    # Moved elsewhere: the pattern is found relative to the scene.
    out = tmp_path / "moved"
    shutil.move(str(tmp_path / "out"), out)
    frames = Frames.load(out / "scene.xml")
    rays = np.load(out / frames.lidar.extra["rays"])
    pattern = np.load(streets["rays"] / "gt" / "lidar_rays.npy")
    assert rays.shape[1] == 7 and frames.lidar.azimuth_steps == len(rays) <= len(pattern)
    # Every recovered ray is one of the pattern's, its beam from its row.
    cos = rays[:, 3:6] @ (pattern[:, 3:6] / np.linalg.norm(pattern[:, 3:6], axis=1,
                                                            keepdims=True)).T
    assert np.all(cos.max(axis=1) > np.cos(1e-4))
    assert len(np.unique(rays[:, 6])) == frames.lidar.beams == 20
    scene = mi.load_file(str(out / "scene.xml"))
    sensor = next(s for s in scene.sensors() if s.id() == frames[0].lidar)
    assert sensor.explicit_rays and sensor.n_beams == 20
    np.testing.assert_array_equal(np.array(sensor.beam_index()), rays[:, 6])
    arr, names = read_exr(str(frames[0].lidar_scan))
    assert arr.shape[:2] == (1, len(rays))
    hit = arr[0, :, names.index("hit")] > 0.5
    # Each observed return lies on its own ray: the recorded point's range along it.
    pts = np.load(frames[0].points)
    assert hit.sum() == len(pts)
    T = frames[0].lidar_to_world
    local = (pts[:, :3] - T[:3, 3]) @ T[:3, :3]
    got = np.sort(np.linalg.norm(local, axis=1))
    np.testing.assert_allclose(np.sort(arr[0, hit, names.index("range")]), got, rtol=1e-4)
    img = np.array(mi.render(scene, sensor=sensor, integrator=mi.load_dict({"type": "lidar_return"})))
    assert img.shape[:2] == (1, len(rays)) and (img[0, :, 2] > 0.5).mean() > 0.5
    # A copy written beside its own PLYs (as fit writes one) still finds the pattern.
    from mi_invrgbl.scene.xml import SceneDoc
    doc = SceneDoc.load(str(out / "scene.xml"), resolve_paths=False)
    strings = list(doc.root.iter("string"))
    assert {e.get("value") for e in strings if e.get("name") == "rays"} == {str(out / "lidar_rays.npy")}
    assert "background.ply" in {e.get("value") for e in strings if e.get("name") == "filename"}
