"""``mi-invrgbl night``: the scene is lit only near its lights.

The synthetic street's time-A scene is turned into night with the command
(sky switched off here, so that only the added lights shine); the world
position behind every pixel (Mitsuba's ``aov`` integrator, same camera) says
how far each visible surface is from the nearest light and whether it lies
inside that light's cone. Surfaces outside every cone, or far from every
light, only receive light inter-reflected from the lit ones (the scene's
``path`` integrator follows 4 bounces): their mean radiance must stay below
``FAR_RATIO`` of the surfaces close under the lights. Measured (128x48,
16 spp): 0.06 for the streetlights, 0.04 for the headlights (the road ahead
of the camera is black without them); with no lights and no sky the render
is black.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import mitsuba as mi

from mi_invrgbl.cli import main
from mi_invrgbl.synthetic import StreetConfig, generate_street
from mi_invrgbl.synthetic.writers import read_exr
import variant_choice

CFG = dict(seed=2, frames=1, width=128, height=48, spp=16, azimuth_steps=256, night=False)
#: Far surfaces (outside every cone, or beyond FAR_M of every light) vs lit ones
#: (inside a cone, within NEAR_M of its light).
FAR_RATIO = 0.1
FAR_M = 25.0
NEAR_M = 8.0


@pytest.fixture(scope="module")
def street(tmp_path_factory):
    variant_choice.use()
    import mi_invrgbl  # noqa: F401
    out = tmp_path_factory.mktemp("night") / "street"
    generate_street(str(out), StreetConfig(**CFG), log=lambda *a: None)
    return out


def rgb(path):
    ch = read_exr(str(path))
    return np.stack([ch["R"], ch["G"], ch["B"]], axis=-1)


def positions(scene_xml):
    """World position of the surface behind each pixel (NaN where the sky is seen)."""
    scene = mi.load_file(str(scene_xml))
    integrator = mi.load_dict({"type": "aov", "aovs": "p:position,d:depth"})
    out = np.array(mi.render(scene, integrator=integrator, spp=1))
    p = out[..., :3].copy()
    p[out[..., 3] <= 0] = np.nan
    return p


def spots(scene_xml):
    """(position, axis, cutoff in degrees) of every spot light of a scene."""
    from mi_invrgbl.scene.xml import SceneDoc, child_param
    doc = SceneDoc.load(str(scene_xml))
    scene = mi.load_file(str(scene_xml))
    out = []
    for e in scene.emitters():
        if e.class_name() == "SpotLight":
            m = np.array(e.world_transform().matrix, np.float64).reshape(4, 4)
            cutoff = float(child_param(doc.by_id(e.id()), "cutoff_angle"))
            out.append((m[:3, 3], m[:3, 2] / np.linalg.norm(m[:3, 2]), cutoff))
    return out


def lit_masks(p, lights):
    """Pixels near (inside a cone, < NEAR_M) and far (outside every cone or > FAR_M)."""
    near = np.zeros(p.shape[:2], bool)
    far = np.isfinite(p[..., 0])
    for pos, axis, cutoff in lights:
        v = p - pos
        d = np.linalg.norm(v, axis=-1)
        cos = np.sum(v * axis, axis=-1) / np.maximum(d, 1e-9)
        inside = cos > math.cos(math.radians(cutoff))
        near |= inside & (d < NEAR_M)
        far &= ~(inside & (d < FAR_M))
    return near & np.isfinite(p[..., 0]), far


def luminance(img):
    return img @ np.array([0.2126, 0.7152, 0.0722])


def test_night_lit_only_near_streetlights(street, tmp_path):
    out = tmp_path / "night"
    assert main(["night", str(street / "gt" / "scene_time_a.xml"), "-o", str(out),
                 "--headlights", "0", "--sky-scale", "0", "--spp", "16"]) == 0
    lamps = json.loads((street / "gt" / "lights.json").read_text())["night"]["streetlights"]
    lights = spots(out / "scene.xml")
    assert len(lights) == len(lamps)     # the street's own lamps, no headlights
    for (pos, axis, cutoff), lamp in zip(lights, lamps):
        assert pos == pytest.approx(lamp["position"], abs=1e-5)
        assert axis == pytest.approx([0, 0, -1], abs=1e-6)
    night = luminance(rgb(out / "frame_0000.exr"))
    day = luminance(rgb(street / "gt" / "time_a" / "000000.exr"))
    near, far = lit_masks(positions(out / "scene.xml"), lights)
    assert near.sum() > 50 and far.sum() > 500
    ratio = night[far].mean() / night[near].mean()
    print("night: mean radiance under the lamps %.4f, far from them %.5f (ratio %.4f); day %.3f"
          % (night[near].mean(), night[far].mean(), ratio, day.mean()))
    assert ratio < FAR_RATIO
    assert night.mean() < 0.1 * day.mean()
    assert (out / "frame_0000.png").is_file()


def test_no_lights_no_sky_is_black(street, tmp_path):
    """The sun is gone: with no lamps and the sky scaled to 0 nothing is lit."""
    out = tmp_path / "black"
    assert main(["night", str(street / "gt" / "scene_time_a.xml"), "-o", str(out), "--spp", "2",
                 "--headlights", "0", "--streetlights", "0", "--sky-scale", "0"]) == 0
    assert np.abs(rgb(out / "frame_0000.exr")).max() == 0.0


def test_headlights_follow_the_camera_and_light_the_road_ahead(street, tmp_path):
    dark = tmp_path / "dark"
    lit = tmp_path / "lit"
    base = ["night", str(street / "gt" / "scene_time_a.xml"), "--streetlights", "0", "--sky-scale", "0",
            "--spp", "16"]
    assert main(base + ["-o", str(dark), "--headlights", "0"]) == 0
    assert main(base + ["-o", str(lit), "--headlights", "2", "--headlight-colour", "1,1,1"]) == 0
    lights = spots(lit / "scene.xml")
    assert len(lights) == 2
    cam = np.array(json.loads((street / "gt" / "trajectory.json").read_text())["world_from_cam"][0])
    for pos, axis, cutoff in lights:
        # 0.7 m either side of the camera, 0.95 m below it, looking ahead (KITTI camera: +z forward).
        local = np.linalg.inv(cam) @ np.append(pos, 1.0)
        assert abs(abs(local[0]) - 0.7) < 1e-4 and local[1] == pytest.approx(0.95, abs=1e-4)
        assert np.dot(axis, cam[:3, 2]) > 0.99
    near, far = lit_masks(positions(lit / "scene.xml"), lights)
    img_lit = luminance(rgb(lit / "frame_0000.exr"))
    img_dark = luminance(rgb(dark / "frame_0000.exr"))
    gain = img_lit[near].mean() / max(img_dark[near].mean(), 1e-9)
    ratio = img_lit[far].mean() / img_lit[near].mean()
    print("headlights: road ahead %.1fx brighter with them; far/near %.4f" % (gain, ratio))
    assert gain > 5 and ratio < FAR_RATIO


def test_streetlights_along_the_path_when_none_are_recorded():
    from mi_invrgbl.apps.night import path_streetlights
    cams = []
    for x in range(0, 20, 5):
        m = np.eye(4)
        m[:3, :3] = [[0, 0, 1], [1, 0, 0], [0, 1, 0]]   # Mitsuba camera: +z along world +x, +x left (+y)
        m[:3, 3] = [x, 0.0, 1.65]
        cams.append(m)
    lamps = path_streetlights(cams, 4, 10.0, 5.0, 3.0)
    assert len(lamps) == 4
    xs = [p[0] for p, _ in lamps]
    assert xs == pytest.approx([5, 15, 25, 35], abs=1e-6)
    assert [p[1] for p, _ in lamps] == pytest.approx([3, -3, 3, -3])
    assert all(p[2] == pytest.approx(5.0) for p, _ in lamps)


@pytest.mark.parametrize("args, message", [
    (["--headlights", "3"], "invalid choice"),
    (["--streetlight", "1,2"], "expected x,y,z"),
    (["--sky-scale", "-1"], "--sky-scale must be >= 0"),
    (["--streetlight-cutoff", "120"], "--streetlight-cutoff must lie in (0, 90]"),
    (["--headlight-colour", "0,0,0"], "--headlight-colour"),
])
def test_bad_input_gives_one_clear_error(street, tmp_path, capsys, args, message):
    try:
        code = main(["night", str(street / "gt" / "scene_time_a.xml"), "-o", str(tmp_path / "o")] + args)
    except SystemExit as exc:   # argparse's own errors
        code = exc.code
    err = [line for line in capsys.readouterr().err.strip().splitlines() if "error" in line]
    assert code == 2 and len(err) == 1 and message in err[0], err
