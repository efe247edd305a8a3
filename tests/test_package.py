"""Package-level promises: variant checks, registration, libLLVM detection, the CLI."""

import os
import pathlib
import subprocess
import sys

import numpy as np
import pytest
import mitsuba as mi

ROOT = pathlib.Path(__file__).resolve().parents[1]
PLUGINS = ["gaussians", "cooktorrance", "shsun", "lidar", "laser", "lidar_return", "invrgbl"]


def run_python(code, env=None):
    full_env = dict(os.environ)
    full_env.update(env or {})
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env=full_env, cwd=ROOT, timeout=300)


def test_import_without_variant_gives_one_clear_error():
    r = run_python("import mi_invrgbl")
    assert r.returncode != 0
    assert "mi.set_variant('llvm_ad_rgb')" in r.stderr


def test_scalar_variant_is_refused():
    r = run_python("import mitsuba as mi; mi.set_variant('scalar_rgb'); import mi_invrgbl")
    assert r.returncode != 0
    assert "not 'scalar_rgb'" in r.stderr


# LLVM 15 loads but aborts inside Mitsuba's kernels; 14 is refused by Dr.Jit itself.
@pytest.mark.parametrize("lib", ["libLLVM-15.so.1"])
def test_unusable_libllvm_is_reported_before_it_can_abort(lib):
    path = pathlib.Path("/usr/lib/x86_64-linux-gnu") / lib
    if not path.exists():
        pytest.skip("%s not installed on this machine" % lib)
    r = run_python("import mitsuba as mi; mi.set_variant('llvm_ad_rgb'); import mi_invrgbl",
                   env={"DRJIT_LIBLLVM_PATH": str(path)})
    assert r.returncode == 1          # a Python exception, not an abort (134)
    last = r.stderr.strip().splitlines()[-1]
    assert "libllvm19" in last and "aborts" in last


def test_variant_change_registers_plugins_again():
    code = (
        "import mitsuba as mi\n"
        "mi.set_variant('llvm_ad_rgb')\n"
        "import mi_invrgbl\n"
        "mi.set_variant('scalar_rgb')\n"
        "mi.set_variant('llvm_ad_rgb')\n"
        "b = mi.load_dict({'type': 'cooktorrance', 'albedo': 0.3})\n"
        "assert isinstance(b, mi.BSDF), type(b).__mro__\n"
        "print('ok')\n")
    r = run_python(code)
    assert r.returncode == 0, r.stderr
    assert "ok" in r.stdout


@pytest.mark.parametrize("name", PLUGINS)
def test_every_plugin_is_registered(name):
    kinds = {"gaussians": {"centers": mi.TensorXf(np.zeros((1, 3), np.float32))}}
    obj = mi.load_dict({"type": name, **kinds.get(name, {})})
    assert obj is not None


def test_example_scenes_load_and_render(scenes_dir):
    for xml in sorted(scenes_dir.glob("*.xml")):
        scene = mi.load_file(str(xml), **({"spp": "1"} if "spp" in xml.read_text() else {}))
        assert scene.sensors(), xml


def cli(*args):
    exe = pathlib.Path(sys.executable).with_name("mi-invrgbl")
    return subprocess.run([str(exe), *args], capture_output=True, text=True, cwd=ROOT, timeout=600)


def test_cli_missing_scene_is_one_line_error(tmp_path):
    r = cli("render", str(tmp_path / "nope.xml"))
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0
    assert "nope.xml" in r.stderr and "not found" in r.stderr


def test_cli_bad_define_and_variant(tmp_path):
    r = cli("render", "scenes/street.xml", "-D", "width")
    assert r.returncode == 2 and "KEY=VALUE" in r.stderr
    r = cli("-m", "no_such_variant", "render", "scenes/street.xml")
    assert r.returncode == 2 and "unknown Mitsuba variant" in r.stderr


def test_cli_render_of_bundled_street_writes_images(tmp_path):
    out = tmp_path / "street"
    r = cli("render", "scenes/street.xml", "-o", str(out), "-D", "width=48", "-D", "height=16",
            "-D", "spp=1", "-D", "samples=4", "-D", "azimuth_steps=64")
    assert r.returncode == 0, r.stderr
    for name in ["camera.exr", "camera.png", "camera_albedo.png", "lidar_lidar.exr",
                 "lidar_intensity.png", "lidar_range.png"]:
        assert (out / name).stat().st_size > 0, name
    from mi_invrgbl.io.images import read_exr
    lidar, channels = read_exr(str(out / "lidar_lidar.exr"))
    # EXR stores channels by name (sorted); look them up by name.
    assert sorted(channels) == sorted(["intensity", "range", "hit", "lidar_albedo", "alpha"])
    assert lidar.shape == (64, 64, 5)
    ch = {name: lidar[..., i] for i, name in enumerate(channels)}
    hit = ch["hit"] > 0
    assert 0.2 < hit.mean() < 1.0           # the ground and facade return, the sky does not
    assert np.all(np.isfinite(lidar)) and np.all(ch["range"][hit] > 0.5)
    rgb, names = read_exr(str(out / "camera.exr"))
    assert names[:3] == ["R", "G", "B"] and "albedo.R" in names and "alpha" in names
    assert np.all(np.isfinite(rgb)) and rgb[..., :3].mean() > 0.05
