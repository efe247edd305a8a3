"""Bad inputs and misuse: every case exits non-zero with one line naming the
file and the problem, or is handled correctly; no command deletes or
overwrites a file it did not write.

The cases are a table (input class, command, expected exit code, expected
message fragment). Each builds its broken input in ``tmp_path`` from a tiny
synthetic street (6 frames, 64x24 pixels, made once per module) and runs the
command in-process through :func:`mi_invrgbl.cli.main`.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
import mitsuba as mi
import drjit as dr

from mi_invrgbl.cli import main
from mi_invrgbl import outdir
from mi_invrgbl.io.velodyne import write_velodyne

IMPORT_ARGS = ["--max-points", "20000", "--azimuth-steps", "256"]


def _quiet(*_a, **_k):
    pass


@pytest.fixture(scope="module")
def street(tiny_street):
    return tiny_street


@pytest.fixture(scope="module")
def imported(street, tmp_path_factory):
    from mi_invrgbl.io.importer import ImportOptions, import_scene
    out = tmp_path_factory.mktemp("bad_import") / "scene" / "scene.xml"
    import_scene(street, out, ImportOptions(max_points=20000, azimuth_steps=256), log=_quiet)
    return out.parent


def _copy_street(street, tmp_path, gt=False) -> Path:
    dst = tmp_path / "data"
    for name in ("sequences", "poses", "label_02") + (("gt",) if gt else ()):
        shutil.copytree(street / name, dst / name)
    return dst


def _copy_import(imported, tmp_path) -> Path:
    dst = tmp_path / "imp"
    shutil.copytree(imported, dst)
    return dst


def _seq(data: Path) -> Path:
    return data / "sequences" / "00"


def _set_calib(data: Path, key: str, values) -> None:
    calib = _seq(data) / "calib.txt"
    lines = [l for l in calib.read_text().splitlines()
             if not l.startswith(key + ":")]
    lines.append(key + ": " + " ".join("%.12e" % v for v in np.ravel(values)))
    calib.write_text("\n".join(lines) + "\n")


def _tr(data: Path) -> np.ndarray:
    for line in (_seq(data) / "calib.txt").read_text().splitlines():
        if line.startswith("Tr:"):
            return np.array([float(v) for v in line.split(":")[1].split()]).reshape(3, 4)
    raise AssertionError("no Tr")


# ----------------------------------------------------------------------------
# Input builders: each returns the command line (after "mi-invrgbl")
# ----------------------------------------------------------------------------
def imp(data, tmp_path, *extra):
    return ["import", str(data), "-o", str(tmp_path / "out" / "scene.xml")] + IMPORT_ARGS + list(extra)


def b_missing_input(street, imported, tmp_path):
    return imp(tmp_path / "nowhere", tmp_path)


def b_bin_size(street, imported, tmp_path):
    data = _copy_street(street, tmp_path)
    with open(_seq(data) / "velodyne" / "000002.bin", "ab") as f:
        f.write(b"\0" * 5)
    return imp(data, tmp_path)


def b_missing_calib(street, imported, tmp_path):
    data = _copy_street(street, tmp_path)
    (_seq(data) / "calib.txt").unlink()
    return imp(data, tmp_path)


def b_calib_words(street, imported, tmp_path):
    data = _copy_street(street, tmp_path)
    calib = _seq(data) / "calib.txt"
    calib.write_text(calib.read_text().replace("P2: ", "P2: abc "))
    return imp(data, tmp_path)


def b_singular_tr(street, imported, tmp_path):
    data = _copy_street(street, tmp_path)
    tr = _tr(data)
    tr[:, :3] = 0.0
    _set_calib(data, "Tr", tr)
    return imp(data, tmp_path)


def b_nan_tr(street, imported, tmp_path):
    data = _copy_street(street, tmp_path)
    tr = _tr(data)
    tr[1, 3] = np.nan
    _set_calib(data, "Tr", tr)
    return imp(data, tmp_path)


def b_bad_p2(street, imported, tmp_path):
    data = _copy_street(street, tmp_path)
    _set_calib(data, "P2", np.zeros(12))
    return imp(data, tmp_path)


def b_nan_pose(street, imported, tmp_path):
    data = _copy_street(street, tmp_path)
    poses = data / "poses" / "00.txt"
    lines = poses.read_text().splitlines()
    vals = lines[2].split()
    vals[3] = "nan"
    lines[2] = " ".join(vals)
    poses.write_text("\n".join(lines) + "\n")
    return imp(data, tmp_path)


def b_sheared_pose(street, imported, tmp_path):
    data = _copy_street(street, tmp_path)
    poses = data / "poses" / "00.txt"
    lines = poses.read_text().splitlines()
    vals = [float(v) for v in lines[1].split()]
    vals[0] *= 3.0
    lines[1] = " ".join("%.12e" % v for v in vals)
    poses.write_text("\n".join(lines) + "\n")
    return imp(data, tmp_path)


def b_nan_times(street, imported, tmp_path):
    data = _copy_street(street, tmp_path)
    times = _seq(data) / "times.txt"
    lines = times.read_text().splitlines()
    lines[1] = "nan"
    times.write_text("\n".join(lines) + "\n")
    return imp(data, tmp_path)


def b_image_size(street, imported, tmp_path):
    import cv2
    data = _copy_street(street, tmp_path)
    path = _seq(data) / "image_2" / "000003.png"
    img = cv2.imread(str(path))
    cv2.imwrite(str(path), cv2.resize(img, (img.shape[1] // 2, img.shape[0])))
    return imp(data, tmp_path)


def b_corrupt_image(street, imported, tmp_path):
    data = _copy_street(street, tmp_path)
    (_seq(data) / "image_2" / "000002.png").write_bytes(b"not a png at all")
    return imp(data, tmp_path)


def b_origin_sweep(street, imported, tmp_path):
    data = _copy_street(street, tmp_path)
    path = _seq(data) / "velodyne" / "000001.bin"
    n = os.path.getsize(path) // 16
    write_velodyne(path, np.zeros((n, 3)), np.zeros(n))
    return imp(data, tmp_path)


def b_nan_inf_points(street, imported, tmp_path):
    data = _copy_street(street, tmp_path)
    path = _seq(data) / "velodyne" / "000001.bin"
    rec = np.fromfile(path, "<f4").reshape(-1, 4)
    rec[:5, 0] = np.nan
    rec[5:8, 1] = np.inf
    rec[8:10, 3] = -np.inf
    rec.astype("<f4").tofile(path)
    return imp(data, tmp_path, "--frames", "0:3")


def b_import_azimuth_0(street, imported, tmp_path):
    return ["import", str(street), "-o", str(tmp_path / "o" / "scene.xml"), "--azimuth-steps", "0"]


def b_import_not_xml(street, imported, tmp_path):
    return ["import", str(street), "-o", str(tmp_path / "o")]


# -- fit ---------------------------------------------------------------------
def _no_fit(monkeypatch):
    """Make any fit that gets past the checks fail the test loudly."""
    from mi_invrgbl.fit import runner

    def refuse(*_a, **_k):
        raise AssertionError("the fit started although its input or output is bad")
    monkeypatch.setattr(runner, "run_fit", refuse)


def b_fit_missing_scene(street, imported, tmp_path):
    return ["fit", str(tmp_path / "nope" / "scene.xml"), "-o", str(tmp_path / "fit")]


def b_fit_huge_weight(street, imported, tmp_path):
    return ["fit", str(imported / "scene.xml"), "-o", str(tmp_path / "fit"), "--weights", "rgb=1e30"]


def b_fit_unwritable(street, imported, tmp_path):
    # Writing under /proc fails for every user, root included.
    return ["fit", str(imported / "scene.xml"), "-o", "/proc/self/mi-invrgbl-fit"]


def b_fit_output_is_file(street, imported, tmp_path):
    (tmp_path / "afile").write_text("x")
    return ["fit", str(imported / "scene.xml"), "-o", str(tmp_path / "afile" / "fit")]


def b_fit_resume_nothing(street, imported, tmp_path):
    return ["fit", str(imported / "scene.xml"), "-o", str(tmp_path / "fit"), "--resume"]


def _fake_fit(folder: Path, complete=True):
    """A folder marked as a fit's (its files are never read by the refusals)."""
    folder.mkdir(parents=True)
    (folder / "scene.xml").write_text("<scene version='3.0.0'/>")
    outdir.mark(folder, "fit", complete=complete)


def b_fit_into_finished(street, imported, tmp_path):
    _fake_fit(tmp_path / "fit")
    return ["fit", str(imported / "scene.xml"), "-o", str(tmp_path / "fit")]


def b_fit_into_interrupted(street, imported, tmp_path):
    _fake_fit(tmp_path / "fit", complete=False)
    return ["fit", str(imported / "scene.xml"), "-o", str(tmp_path / "fit")]


def b_fit_missing_lidar_exr(street, imported, tmp_path):
    imp_dir = _copy_import(imported, tmp_path)
    (imp_dir / "observations" / "lidar_0002.exr").unlink()
    return ["fit", str(imp_dir / "scene.xml"), "-o", str(tmp_path / "fit"), "--stage1", "1",
            "--stage2", "1", "--width", "64", "--lidar-columns", "64"]


# -- render / lidar / relight ------------------------------------------------
def _plane_scene(tmp_path, extra_param="", ply=None) -> Path:
    shutil.copy(Path(__file__).resolve().parents[1] / "scenes" / "gaussians_plane.ply",
                tmp_path / "gaussians_plane.ply")
    text = (Path(__file__).resolve().parents[1] / "scenes" / "gaussians_plane.xml").read_text()
    if extra_param:
        text = text.replace('<string name="filename" value="gaussians_plane.ply"/>',
                            '<string name="filename" value="gaussians_plane.ply"/>' + extra_param)
    if ply is not None:
        text = text.replace('value="gaussians_plane.ply"', 'value="%s"' % ply)
    path = tmp_path / "plane.xml"
    path.write_text(text)
    return path


def _plane_cloud(tmp_path):
    from mi_invrgbl.physics.gaussian_ply import read_ply
    _plane_scene(tmp_path)
    return read_ply(str(tmp_path / "gaussians_plane.ply"))


def _write_cloud(tmp_path, cloud, name):
    from mi_invrgbl.physics import gaussian_ply as g
    # The writer refuses non-finite values itself: write the fields raw.
    path = tmp_path / name
    g.write_ply(str(path), cloud)
    return path


def b_render_missing(street, imported, tmp_path):
    return ["render", str(tmp_path / "none.xml"), "-o", str(tmp_path / "r")]


def b_render_broken_xml(street, imported, tmp_path):
    (tmp_path / "broken.xml").write_text("<scene version='3.0.0'><shape type='sphere'>")
    return ["render", str(tmp_path / "broken.xml"), "-o", str(tmp_path / "r")]


def b_render_unreferenced(street, imported, tmp_path):
    (tmp_path / "s.xml").write_text("<scene version='3.0.0'><shape type='sphere'>"
                                    "<float name='radiu' value='1'/></shape></scene>")
    return ["render", str(tmp_path / "s.xml"), "-o", str(tmp_path / "r")]


def b_render_spp(street, imported, tmp_path):
    return ["render", str(_plane_scene(tmp_path)), "--spp", "-1", "-o", str(tmp_path / "r")]


def b_render_sensor(street, imported, tmp_path):
    return ["render", str(_plane_scene(tmp_path)), "--sensor", "camera_9999",
            "-o", str(tmp_path / "r")]


def b_gaussians_unknown_param(street, imported, tmp_path):
    scene = _plane_scene(tmp_path, '<float name="extnt" value="2"/>')
    return ["render", str(scene), "-o", str(tmp_path / "r")]


def b_gaussians_nan(street, imported, tmp_path):
    import struct
    scene = _plane_scene(tmp_path)
    ply = tmp_path / "gaussians_plane.ply"
    raw = ply.read_bytes()
    head = raw.index(b"end_header\n") + len(b"end_header\n")
    body = bytearray(raw[head:])
    body[0:4] = struct.pack("<f", float("nan"))          # the first centre's x
    ply.write_bytes(raw[:head] + bytes(body))
    return ["render", str(scene), "-o", str(tmp_path / "r")]


def b_gaussians_zero_quaternion(street, imported, tmp_path):
    cloud = _plane_cloud(tmp_path)
    cloud.quaternions = cloud.quaternions.copy()
    cloud.quaternions[3] = 0.0
    _write_cloud(tmp_path, cloud, "zq.ply")
    return ["render", str(_plane_scene(tmp_path, ply="zq.ply")), "-o", str(tmp_path / "r")]


def b_gaussians_zero_scale(street, imported, tmp_path):
    cloud = _plane_cloud(tmp_path)
    cloud.scales = cloud.scales.copy()
    cloud.scales[:10] = 0.0
    _write_cloud(tmp_path, cloud, "zs.ply")
    return ["render", str(_plane_scene(tmp_path, ply="zs.ply")), "-o", str(tmp_path / "r")]


def b_gaussians_truncated(street, imported, tmp_path):
    scene = _plane_scene(tmp_path)
    ply = tmp_path / "gaussians_plane.ply"
    ply.write_bytes(ply.read_bytes()[:3000])
    return ["render", str(scene), "-o", str(tmp_path / "r")]


def b_gaussians_missing(street, imported, tmp_path):
    return ["render", str(_plane_scene(tmp_path, ply="none.ply")), "-o", str(tmp_path / "r")]


def b_fit_missing_frames(street, imported, tmp_path):
    imp_dir = _copy_import(imported, tmp_path)
    (imp_dir / "frames.json").unlink()
    return ["fit", str(imp_dir / "scene.xml"), "-o", str(tmp_path / "fit")]


def b_fit_corrupt_frames(street, imported, tmp_path):
    imp_dir = _copy_import(imported, tmp_path)
    text = (imp_dir / "frames.json").read_text()
    (imp_dir / "frames.json").write_text(text[: len(text) // 2])
    return ["fit", str(imp_dir / "scene.xml"), "-o", str(tmp_path / "fit")]


def b_fit_nan_frames(street, imported, tmp_path):
    imp_dir = _copy_import(imported, tmp_path)
    data = json.loads((imp_dir / "frames.json").read_text())
    data["frames"][1]["camera_to_world"][0][3] = "NaN"
    (imp_dir / "frames.json").write_text(json.dumps(data).replace('"NaN"', "NaN"))
    return ["fit", str(imp_dir / "scene.xml"), "-o", str(tmp_path / "fit")]


def b_lidar_intensity_scale(street, imported, tmp_path):
    return ["lidar", str(street / "gt" / "scene_time_a.xml"), "--pose", "5,-1.75,1.73",
            "--intensity-scale", "-3", "-o", str(tmp_path / "l")]


def b_lidar_azimuth_0(street, imported, tmp_path):
    return ["lidar", str(street / "gt" / "scene_time_a.xml"), "--pose", "5,-1.75,1.73",
            "--azimuth-steps", "0", "-o", str(tmp_path / "l")]


def b_relight_no_light(street, imported, tmp_path):
    return ["relight", str(street / "gt" / "scene_time_a.xml"), "-o", str(tmp_path / "rl")]


def b_cuda_without_gpu(street, imported, tmp_path):
    return ["-m", "cuda_ad_rgb", "render", str(_plane_scene(tmp_path)), "-o", str(tmp_path / "r")]


def b_relight_into_fit(street, imported, tmp_path):
    _fake_fit(tmp_path / "fit")
    return ["relight", str(street / "gt" / "scene_time_a.xml"), "--sun-elevation", "30",
            "-o", str(tmp_path / "fit"), "--overwrite"]


def b_render_into_scene_folder(street, imported, tmp_path):
    (tmp_path / "s").mkdir()
    scene = _plane_scene(tmp_path / "s")
    return ["render", str(scene), "-o", str(tmp_path / "s"), "--overwrite"]


def b_lidar_into_import(street, imported, tmp_path):
    imp_dir = _copy_import(imported, tmp_path)
    return ["lidar", str(street / "gt" / "scene_time_a.xml"), "--pose", "5,-1.75,1.73",
            "-o", str(imp_dir), "--overwrite"]


def b_eval_onto_scene(street, imported, tmp_path):
    imp_dir = _copy_import(imported, tmp_path)
    return ["eval", str(imp_dir / "scene.xml"), "-o", str(imp_dir / "scene.xml")]


def b_eval_onto_user_file(street, imported, tmp_path):
    (tmp_path / "results.json").write_text('{"mine": 1}')
    return ["eval", str(imported / "scene.xml"), "-o", str(tmp_path / "results.json")]


def b_make_scene_existing(street, imported, tmp_path):
    (tmp_path / "street").mkdir()
    (tmp_path / "street" / "keep.txt").write_text("x")
    return ["make-scene", "street", str(tmp_path / "street"), "--frames", "2"]


# -- eval / insert -------------------------------------------------------------
def b_eval_renamed_channels(street, imported, tmp_path):
    from mi_invrgbl.io.images import read_exr, write_exr
    imp_dir = _copy_import(imported, tmp_path)
    path = imp_dir / "observations" / "lidar_0004.exr"
    arr, names = read_exr(str(path))
    write_exr(str(path), arr, ["c%d" % k for k in range(len(names))])
    return ["eval", str(imp_dir / "scene.xml"), "--frames", "4", "--no-baseline", "--no-relight",
            "-o", str(tmp_path / "m.json")]


def b_insert_track(street, imported, tmp_path):
    track = tmp_path / "track.json"
    track.write_text(json.dumps([[8.0 + k, 3.5, -1.0, 0.0] for k in range(6)]))
    return ["insert", str(imported / "scene.xml"), "--object",
            str(imported / "scene.xml") + ":object_0", "--track", str(track),
            "--frames", "0:2", "--spp", "1", "--samples", "2", "-o", str(tmp_path / "ins")]


@dataclass
class Case:
    input_class: str
    command: str
    build: Callable
    code: int
    fragment: str            # expected in the error line (or a warning for code 0)
    marks: tuple = ()


CASES = [
    # input class, command, builder, exit code, message fragment
    Case("missing file", "import", b_missing_input, 2, "nowhere: input folder not found"),
    Case("corrupt file", "import", b_bin_size, 2, "000002.bin: size"),
    Case("missing file", "import", b_missing_calib, 2, "calib.txt: calibration file not found"),
    Case("corrupt file", "import", b_calib_words, 2, "calib.txt: entry 'P2' is not a list of numbers"),
    Case("bad calibration", "import", b_singular_tr, 2, "calib.txt: entry 'Tr' is not a rotation"),
    Case("NaN and inf", "import", b_nan_tr, 2, "calib.txt: entry 'Tr' holds a NaN"),
    Case("bad calibration", "import", b_bad_p2, 2, "calib.txt: entry 'P2' is not a camera projection"),
    Case("bad poses", "import", b_nan_pose, 2, "00.txt: line 3 holds a NaN"),
    Case("bad poses", "import", b_sheared_pose, 2, "00.txt: line 2 is not a rotation"),
    Case("NaN and inf", "import", b_nan_times, 2, "times.txt: line 2 is not a finite number"),
    Case("bad image", "import", b_image_size, 2, "000003.png: image is 32x24, the calibration's"),
    Case("corrupt file", "import", b_corrupt_image, 2, "000002.png: not a readable image"),
    Case("bad sweep", "import", b_origin_sweep, 2, "000001.bin: all"),
    Case("NaN and inf", "import", b_nan_inf_points, 0, "000001.bin: dropped 10"),
    Case("bad flag", "import", b_import_azimuth_0, 2, "--azimuth-steps must be at least 8"),
    Case("bad flag", "import", b_import_not_xml, 2, "the output must be a scene file"),
    Case("missing file", "fit", b_fit_missing_scene, 2, "scene.xml: scene file not found"),
    Case("bad flag", "fit", b_fit_huge_weight, 2, "--weights: rgb=1e+30 is too large"),
    Case("unwritable output", "fit", b_fit_unwritable, 2, "/proc/self: cannot write here"),
    Case("unwritable output", "fit", b_fit_output_is_file, 2, "afile: not a folder"),
    Case("misused output", "fit", b_fit_resume_nothing, 2, "fit: nothing to resume"),
    Case("misused output", "fit", b_fit_into_finished, 2, "holds a finished fit; pass --resume"),
    Case("misused output", "fit", b_fit_into_interrupted, 2, "holds an interrupted fit"),
    Case("missing file", "fit", b_fit_missing_lidar_exr, 2, "lidar_0002.exr: LiDAR scan of frame 2 not found"),
    Case("missing file", "render", b_render_missing, 2, "none.xml: scene file not found"),
    Case("corrupt file", "render", b_render_broken_xml, 2, "broken.xml: cannot load scene"),
    Case("bad scene", "render", b_render_unreferenced, 2, 'unreferenced property in shape plugin of type "sphere": - float "radiu"'),
    Case("bad flag", "render", b_render_spp, 2, "--spp must be >= 0"),
    Case("bad flag", "render", b_render_sensor, 2, "--sensor camera_9999: "),
    Case("bad scene", "render", b_gaussians_unknown_param, 2,
         "plane.xml (line 33, col 6): failed to instantiate shape plugin of type \"gaussians\": "
         "gaussians 'ground': unknown parameter(s) 'extnt'"),
    Case("degenerate Gaussians", "render", b_gaussians_nan, 2, "gaussians_plane.ply: field 'centers' holds NaN/inf"),
    Case("degenerate Gaussians", "render", b_gaussians_zero_quaternion, 2,
         "zq.ply: 1 zero-length rotation quaternion"),
    Case("corrupt file", "render", b_gaussians_truncated, 2, "gaussians_plane.ply: truncated PLY"),
    Case("missing file", "render", b_gaussians_missing, 2, "none.ply: file not found"),
    Case("missing file", "fit", b_fit_missing_frames, 2, "frames.json: frames.json not found"),
    Case("corrupt file", "fit", b_fit_corrupt_frames, 2, "frames.json: not valid JSON"),
    Case("NaN and inf", "fit", b_fit_nan_frames, 2, "frames.json: not valid JSON (non-standard JSON constant NaN)"),
    Case("degenerate Gaussians", "render", b_gaussians_zero_scale, 0, ""),
    Case("bad flag", "lidar", b_lidar_intensity_scale, 2, "--intensity-scale must be a positive number"),
    Case("bad flag", "lidar", b_lidar_azimuth_0, 2, "--azimuth-steps must be at least 1"),
    Case("bad flag", "relight", b_relight_no_light, 2, "no new lighting given"),
    Case("environment", "render", b_cuda_without_gpu, 2, "-m cuda_ad_rgb: variant 'cuda_ad_rgb' needs an NVIDIA GPU"),
    Case("misused output", "relight", b_relight_into_fit, 2, "holds a finished fit; choose another folder"),
    Case("misused output", "render", b_render_into_scene_folder, 2, "holds the input"),
    Case("misused output", "lidar", b_lidar_into_import, 2, "holds the results of 'mi-invrgbl import'"),
    Case("misused output", "eval", b_eval_onto_scene, 2, "scene.xml: the metrics file is an input"),
    Case("misused output", "eval", b_eval_onto_user_file, 2, "results.json: exists and was not written by mi-invrgbl"),
    Case("misused output", "make-scene", b_make_scene_existing, 2, "street: the output folder already exists"),
    Case("corrupt file", "eval", b_eval_renamed_channels, 2, "lidar_0004.exr"),
    Case("bad input", "insert", b_insert_track, 0, ""),
]


def _run(argv, capsys):
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    return code, err


@pytest.mark.parametrize("case", [pytest.param(c, id="%s-%s-%s" % (c.command, c.build.__name__[2:],
                                                                     c.input_class.replace(" ", "_")),
                                               marks=c.marks) for c in CASES])
def test_bad_input(case, street, imported, tmp_path, capsys, monkeypatch):
    if case.build is b_cuda_without_gpu and dr.has_backend(dr.JitBackend.CUDA):
        pytest.skip("this machine has a CUDA GPU")
    if case.command == "fit" and case.build not in (b_fit_missing_lidar_exr, b_fit_missing_frames,
                                                    b_fit_corrupt_frames, b_fit_nan_frames):
        _no_fit(monkeypatch)
    argv = case.build(street, imported, tmp_path)
    monkeypatch.chdir(tmp_path)
    code, err = _run(argv, capsys)
    assert "Traceback" not in err
    errors = [l for l in err.splitlines() if ": error: " in l]
    if case.code == 0:
        assert code == 0, err
        assert errors == []
        assert case.fragment in err
    else:
        assert code == case.code, err
        assert len(errors) == 1, err
        assert case.fragment in errors[0], errors[0]
        leftovers = [p for p in tmp_path.rglob(".*partial*")]
        assert leftovers == []


# ----------------------------------------------------------------------------
# Misused output folders: nothing that existed before may change
# ----------------------------------------------------------------------------
def _snapshot(root: Path) -> dict:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def _unchanged(before: dict, root: Path) -> list:
    after = _snapshot(root)
    return [k for k, v in before.items() if after.get(k) != v]


def _user_folder(tmp_path) -> Path:
    user = tmp_path / "mine"
    user.mkdir()
    (user / "notes.txt").write_text("my notes")
    (user / "scene.xml").write_text("<!-- my own scene -->")
    return user


def _targets(command, tmp_path, data, inputs_parent):
    """(name, -o value, cwd) for every misuse of ``command``'s output folder."""
    xml = "/scene.xml" if command == "import" else ""
    return [
        ("the input itself", str(data) + xml, tmp_path),
        ("the input's parent", str(inputs_parent) + xml, tmp_path),
        ("the current folder", "." + xml if command == "import" else ".", data),
        ("a user's folder", str(_user_folder(tmp_path)) + xml, tmp_path),
    ]


MISUSE = [(cmd, k, ow) for cmd in ("import", "fit", "relight") for k in range(4)
          for ow in (False, True)]


@pytest.mark.parametrize("command,which,overwrite", MISUSE,
                         ids=["%s-%d-%s" % (c, k, "overwrite" if o else "plain") for c, k, o in MISUSE])
def test_misused_output_folder(command, which, overwrite, street, imported, tmp_path, capsys,
                               monkeypatch):
    _no_fit(monkeypatch)
    if command == "import":
        data = _copy_street(street, tmp_path)
        name, out, cwd = _targets(command, tmp_path, data, data.parent)[which]
        argv = ["import", str(data), "-o", out] + IMPORT_ARGS
    elif command == "fit":
        data = _copy_import(imported, tmp_path)
        name, out, cwd = _targets(command, tmp_path, data / "scene.xml", data)[which]
        if which == 2:
            cwd = data
        argv = ["fit", str(data / "scene.xml"), "-o", out]
    else:
        data = _copy_street(street, tmp_path, gt=True)
        scene = data / "gt" / "scene_time_a.xml"
        name, out, cwd = _targets(command, tmp_path, scene, scene.parent)[which]
        if which == 2:
            cwd = scene.parent
        argv = ["relight", str(scene), "--sun-elevation", "30", "--spp", "1", "--frames", "0",
                "-o", out]
    if overwrite:
        argv.append("--overwrite")
    before = _snapshot(tmp_path)
    monkeypatch.chdir(cwd)
    code, err = _run(argv, capsys)
    assert code == 2, "%s accepted as output (%s): %s" % (name, out, err)
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert any(r in err for r in ("current folder", "is an input", "holds the input",
                                  "not written by mi-invrgbl")), err
    assert _unchanged(before, tmp_path) == []
    assert list(tmp_path.rglob(".*partial*")) == []


def test_overwrite_keeps_what_the_tool_did_not_write(street, tmp_path, capsys):
    """import --overwrite into its own folder: its files replaced, a user's file kept."""
    out = tmp_path / "scene"
    argv = ["import", str(street), "-o", str(out / "scene.xml"), "--frames", "0:3"] + IMPORT_ARGS
    assert _run(argv, capsys)[0] == 0
    marker = outdir.read_marker(out)
    assert marker.command == "import" and "scene.xml" in marker.files
    (out / "notes.txt").write_text("mine")
    (out / "observations" / "my.png").write_bytes(b"\x89PNG mine")
    code, err = _run(argv[:4] + ["--frames", "0:2"] + IMPORT_ARGS, capsys)
    assert code == 2 and "--overwrite" in err
    assert _run(argv[:4] + ["--frames", "0:2", "--overwrite"] + IMPORT_ARGS, capsys)[0] == 0
    assert (out / "notes.txt").read_text() == "mine"
    assert (out / "observations" / "my.png").read_bytes() == b"\x89PNG mine"
    assert not (out / "observations" / "image_0002.png").exists()     # the old import's
    assert len(json.loads((out / "frames.json").read_text())["frames"]) == 2
    assert [p.name for p in tmp_path.iterdir()] == ["scene"]
    umask = os.umask(0)
    os.umask(umask)
    assert out.stat().st_mode & 0o777 == 0o777 & ~umask        # not a private 0700 folder


def test_unwritable_output_before_any_work(imported, tmp_path, capsys, monkeypatch):
    """A folder the user cannot write is refused before the fit starts."""
    if os.geteuid() == 0:
        pytest.skip("root writes into read-only folders (the /proc case in the table covers it)")
    _no_fit(monkeypatch)
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    try:
        code, err = _run(["fit", str(imported / "scene.xml"), "-o", str(locked / "fit")], capsys)
    finally:
        locked.chmod(0o755)
    assert code == 2 and "locked: cannot write here" in err


# ----------------------------------------------------------------------------
# The output folder machinery itself
# ----------------------------------------------------------------------------
def test_staged_folder_replaces_only_its_own_files(tmp_path):
    target = tmp_path / "out"
    with outdir.staged(target, "render") as out:
        (out.path / "a.png").write_text("1")
        (out.path / "sub").mkdir()
        (out.path / "sub" / "b.exr").write_text("1")
        assert not target.exists()              # nothing appears before the end
    assert outdir.read_marker(target).files == ["a.png", "sub/b.exr"]
    (target / "user.txt").write_text("u")
    (target / "sub" / "user.exr").write_text("u")
    # the same command again: refused without --overwrite
    with pytest.raises(outdir.UserError, match="--overwrite"):
        outdir.prepare(target, "render")
    # another command: refused even with --overwrite
    with pytest.raises(outdir.UserError, match="holds the results of 'mi-invrgbl render'"):
        outdir.prepare(target, "relight", overwrite=True)
    with outdir.staged(target, "render", overwrite=True) as out:
        (out.path / "c.png").write_text("2")
    assert sorted(p.relative_to(target).as_posix() for p in target.rglob("*") if p.is_file()) == \
        [outdir.MARKER, "c.png", "sub/user.exr", "user.txt"]
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


def test_interrupted_run_leaves_the_old_folder(tmp_path):
    target = tmp_path / "out"
    with outdir.staged(target, "render") as out:
        (out.path / "a.png").write_text("old")
    with pytest.raises(KeyboardInterrupt):
        with outdir.staged(target, "render", overwrite=True) as out:
            (out.path / "a.png").write_text("new")
            (out.path / "b.png").write_text("new")
            raise KeyboardInterrupt
    assert (target / "a.png").read_text() == "old" and not (target / "b.png").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


def test_a_user_file_in_the_way_stops_the_swap(tmp_path):
    target = tmp_path / "out"
    with outdir.staged(target, "render") as out:
        (out.path / "a.png").write_text("old")
    (target / "b.png").write_text("user's")
    out = outdir.prepare(target, "render", overwrite=True)
    (out.path / "b.png").write_text("new")
    with pytest.raises(outdir.UserError, match="b.png: was not written by mi-invrgbl"):
        out.commit()
    assert (target / "b.png").read_text() == "user's" and (target / "a.png").read_text() == "old"
    out.discard()


def test_resume_starts_from_a_copy(tmp_path):
    target = tmp_path / "fit"
    with outdir.staged(target, "fit") as out:
        (out.path / "checkpoints").mkdir()
        (out.path / "checkpoints" / "latest.npz").write_text("ck")
        out.commit(complete=False)
    assert outdir.read_marker(target).complete is False
    out = outdir.prepare(target, "fit", resume=True)
    assert (out.path / "checkpoints" / "latest.npz").read_text() == "ck"
    out.commit()
    assert outdir.read_marker(target).complete is True


def test_single_files(tmp_path):
    mine = tmp_path / "m.json"
    outdir.write_file(mine, "{}", "eval")
    outdir.write_file(mine, "{\"a\": 1}", "eval")           # listed: may be replaced
    theirs = tmp_path / "theirs.json"
    theirs.write_text("user")
    with pytest.raises(outdir.UserError, match="theirs.json: exists and was not written"):
        outdir.write_file(theirs, "{}", "eval")
    assert theirs.read_text() == "user"
    # a marker listing only files does not make the folder an output folder
    with pytest.raises(outdir.UserError, match="not written by mi-invrgbl"):
        outdir.prepare(tmp_path, "render", overwrite=True)


# ----------------------------------------------------------------------------
# Cases that are not a command line
# ----------------------------------------------------------------------------
@pytest.mark.parametrize("rows", [
    [{"wall_s": 1.0, "heldout_psnr": "nan", "heldout_intensity_rmse": "nan"}],
    [{"wall_s": 1.0, "heldout_psnr": "20", "heldout_intensity_rmse": "nan"},
     {"wall_s": 2.0, "heldout_psnr": "nan", "heldout_intensity_rmse": "0.1"},
     {"wall_s": 3.0, "heldout_psnr": "21", "heldout_intensity_rmse": "inf"}],
    []])
def test_end_of_fit_plot_with_nan(rows, tmp_path):
    """log.csv holds NaN when every weight is 0 or an import has one frame."""
    import cv2
    from mi_invrgbl.fit.progress import plot_error_vs_time
    path = tmp_path / "plot.png"
    plot_error_vs_time(rows, str(path))
    assert cv2.imread(str(path)) is not None


def test_mitsuba_message_keeps_the_useful_lines():
    from mi_invrgbl.errors import mitsuba_message
    text = ('[parser.cpp:1718] At /x/s.xml (line 33, col 6): failed to instantiate shape plugin '
            'of type "gaussians": Traceback (most recent call last):\n  File "<string>", line 6, '
            'in <module>\n  File "/p/gaussians.py", line 210, in make_gaussians\n'
            "ValueError: gaussians 'ground': unknown parameter(s) 'extnt'")
    assert mitsuba_message(RuntimeError(text)) == (
        'At /x/s.xml (line 33, col 6): failed to instantiate shape plugin of type "gaussians": '
        "gaussians 'ground': unknown parameter(s) 'extnt'")
    two = ('[parser.cpp:444] While loading /x/b.xml (line 1, col 25): Found 1 unreferenced '
           'property in shape plugin of type "sphere":\n  - float "radiu": 1')
    assert mitsuba_message(RuntimeError(two)).endswith(': - float "radiu": 1')


def _other_import(street, tmp_path) -> Path:
    """The same street imported with fewer frames: another scene for the fit."""
    from mi_invrgbl.io.importer import ImportOptions, import_scene
    out = tmp_path / "other" / "scene.xml"
    import_scene(street, out, ImportOptions(frames="0:4", max_points=20000, azimuth_steps=256),
                 log=_quiet)
    return out


@pytest.mark.slow
def test_fit_folder_lifecycle(street, imported, tmp_path, capsys):
    """A real fit outside its import folder: refused again, resumed, replaced
    (a user's file kept), and scored from the fit folder alone."""
    fit = tmp_path / "elsewhere" / "fit"
    base = ["fit", str(imported / "scene.xml"), "-o", str(fit), "--stage1", "2", "--width", "64",
            "--lidar-columns", "64", "--batch", "512", "--render-samples", "4"]
    assert _run(base + ["--stage2", "2"], capsys)[0] == 0
    assert outdir.read_marker(fit).complete and (fit / "checkpoints" / "latest.npz").is_file()
    fitted = (fit / "scene.xml").read_bytes()
    code, err = _run(base + ["--stage2", "2"], capsys)
    assert code == 2 and "holds a finished fit" in err
    assert (fit / "scene.xml").read_bytes() == fitted
    (fit / "notes.txt").write_text("mine")
    code = main(base + ["--stage2", "3", "--resume"])
    out = capsys.readouterr().out
    assert code == 0 and "resuming from %s" % (fit / "checkpoints" / "latest.npz") in out
    assert json.loads((fit / "metrics.json").read_text())["config"]["stage2_iterations"] == 3
    assert _run(base + ["--stage2", "2", "--overwrite"], capsys)[0] == 0
    assert (fit / "notes.txt").read_text() == "mine"
    # another scene's checkpoint is refused, naming the fit folder's file
    before = _snapshot(fit)
    code, err = _run(["fit", str(_other_import(street, tmp_path)), "-o", str(fit), "--stage1", "2",
                      "--stage2", "2", "--width", "64", "--lidar-columns", "64", "--resume"], capsys)
    assert code == 2 and "%s: checkpoint is of another fit" % (fit / "checkpoints" / "latest.npz") in err
    assert _unchanged(before, fit) == []
    assert list((tmp_path / "elsewhere").iterdir()) == [fit]
    code, err = _run(["eval", str(fit), "--frames", "4", "--no-baseline", "--no-relight"], capsys)
    assert code == 0, err
    assert "mean" in json.loads((fit / "metrics.json").read_text())


def _dead_pid() -> int:
    import subprocess
    import sys
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def _killed_run(target, command, pid):
    """What a run killed after writing a checkpoint leaves beside ``target``."""
    out = outdir.prepare(target, command)
    (out.path / "checkpoints").mkdir()
    (out.path / "checkpoints" / "latest.npz").write_text("killed run")
    marker = outdir.read_marker(out.path)
    marker.pid = pid
    (out.path / outdir.MARKER).write_text(marker.to_json())
    return out.path


def test_a_killed_fit_is_resumed_from_its_temporary_folder(tmp_path):
    target = tmp_path / "fit"
    staging = _killed_run(target, "fit", _dead_pid())
    assert not target.exists()
    # a new run says what was left; --resume continues from it
    with pytest.warns(UserWarning, match="left by a run of 'mi-invrgbl fit' that was killed"):
        outdir.prepare(target, "fit").discard()
    with pytest.warns(UserWarning, match="continuing from .fit.partial"):
        out = outdir.prepare(target, "fit", resume=True)
    assert out.path == staging
    assert (out.path / "checkpoints" / "latest.npz").read_text() == "killed run"
    out.commit()
    assert (target / "checkpoints" / "latest.npz").read_text() == "killed run"
    assert [p.name for p in tmp_path.iterdir()] == ["fit"]


def test_two_runs_never_write_one_folder(tmp_path):
    target = tmp_path / "fit"
    _killed_run(target, "fit", os.getppid())       # a live process
    with pytest.raises(outdir.UserError, match="another 'mi-invrgbl fit' \\(process %d\\)"
                       % os.getppid()):
        outdir.prepare(target, "fit")


@pytest.mark.parametrize("name", ["metrics.json", "albedo.exr", "latest.npz", "background.ply"])
def test_atomic_write_keeps_the_old_file_when_writing_fails(name, tmp_path):
    """Every writer goes through ``outdir.atomic_write``: the temporary file
    keeps the extension (Mitsuba and ``np.savez`` choose the format by it), a
    writer that fails halfway leaves the old file and no temporary behind."""
    path = tmp_path / "sub" / name
    outdir.atomic_write_text(path, "old")
    assert path.read_text() == "old"
    seen = []

    def broken(tmp):
        seen.append(Path(tmp))
        Path(tmp).write_text("half")
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError):
        outdir.atomic_write(path, broken)
    assert path.read_text() == "old"
    assert seen[0].suffix == path.suffix and seen[0].parent == path.parent
    assert sorted(p.name for p in path.parent.iterdir()) == [name]
    # np.savez appends ".npz" to a name without it: the temporary must already end so
    outdir.atomic_write(tmp_path / "x.npz", lambda tmp: np.savez(tmp, a=np.arange(3)))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sub", "x.npz"]
    assert np.load(tmp_path / "x.npz")["a"].tolist() == [0, 1, 2]
    # A file of the user's with a temporary-looking name is left alone, and
    # the result gets the usual permissions (not mkstemp's private 0600).
    mine = tmp_path / "x.npz.part.npz"
    mine.write_text("user's")
    outdir.atomic_write_text(tmp_path / "x.npz", "new")
    assert mine.read_text() == "user's"
    umask = os.umask(0)
    os.umask(umask)
    assert (tmp_path / "x.npz").stat().st_mode & 0o777 == 0o666 & ~umask
