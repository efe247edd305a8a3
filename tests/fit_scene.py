"""A small imported-layout scene with known truth, for fit tests.

The bundled street's Gaussians (road, sidewalks, facade) are the truth. Five
frames of a camera and a LiDAR moving along the street are rendered from it
(``invrgbl`` and ``lidar_return``, the paper's cos/d^2 response) and written
as observations; the scene to fit starts from the same geometry with grey
albedo and a flat LiDAR albedo, as ``import`` would leave it.
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import mitsuba as mi
import variant_choice

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PLY = os.path.join(ROOT, "scenes", "street_assets", "street_gaussians.ply")
SUN = (-0.4, 0.55, 0.75)


def _camera_xml(i, to_world, width, height):
    m = " ".join("%.9g" % v for v in to_world.ravel())
    return ('<sensor type="perspective" id="camera_%04d"><float name="fov" value="80"/>'
            '<string name="fov_axis" value="x"/><transform name="to_world"><matrix value="%s"/>'
            '</transform><sampler type="independent"><integer name="sample_count" value="4"/></sampler>'
            '<film type="hdrfilm"><integer name="width" value="%d"/><integer name="height" value="%d"/>'
            '<rfilter type="box"/></film></sensor>' % (i, m, width, height))


def _lidar_xml(i, to_world, columns):
    m = " ".join("%.9g" % v for v in to_world.ravel())
    return ('<sensor type="lidar" id="lidar_%04d"><string name="preset" value="hdl64"/>'
            '<transform name="to_world"><matrix value="%s"/></transform>'
            '<film type="hdrfilm"><integer name="width" value="%d"/><integer name="height" value="64"/>'
            '<rfilter type="box"/></film></sensor>' % (i, m, columns))


def scene_xml(ply_name, n_frames, width, height, columns, sun=True, extra=""):
    cams, lids = poses(n_frames)
    body = ['<scene version="3.0.0">', '<integrator type="invrgbl"><integer name="samples" value="16"/></integrator>',
            '<emitter type="shsun" id="sky"><integer name="order" value="1"/>'
            '<string name="sh" value="1.6 1.8 2.3 0 0 0 0.5 0.5 0.7 0 0 0"/>'
            '<vector name="sun_direction" x="%g" y="%g" z="%g"/>'
            '<rgb name="sun_irradiance" value="%s"/></emitter>' % (SUN + ("3.0, 2.8, 2.5" if sun else "0",)),
            '<shape type="gaussians" id="background"><string name="filename" value="%s"/></shape>' % ply_name,
            extra]
    for i in range(n_frames):
        body.append(_camera_xml(i, cams[i] @ np.diag([-1.0, -1, 1, 1]), width, height))
        body.append(_lidar_xml(i, lids[i], columns))
    body.append("</scene>")
    return "\n".join(body)


def poses(n_frames):
    """Dataset-convention camera (x right, y down, z forward) and LiDAR poses."""
    cams, lids = [], []
    for i in range(n_frames):
        x = 1.0 * i
        # camera looking along +x, slightly down
        fwd = np.array([1.0, 0, -0.04]); fwd /= np.linalg.norm(fwd)
        right = np.array([0, -1.0, 0])
        down = np.cross(fwd, right)
        c = np.eye(4)
        c[:3, 0], c[:3, 1], c[:3, 2], c[:3, 3] = right, down, fwd, (x, 0, 1.6)
        cams.append(c)
        li = np.eye(4)
        li[:3, 3] = (x, 0, 1.8)
        lids.append(li)
    return cams, lids


def build(out_dir, n_frames=5, width=96, height=32, columns=256, sun=True, truth_extra=""):
    """Write the scene, its truth and observations into ``out_dir``; return the scene path.

    ``truth_extra`` (XML) is added to the truth only: something the
    observations show (e.g. a shadow) that the scene to fit lacks.
    """
    from mi_invrgbl.io.images import write_exr
    from mi_invrgbl.physics.gaussian_ply import read_ply, write_ply
    import cv2
    os.makedirs(os.path.join(out_dir, "observations"), exist_ok=True)
    truth = read_ply(PLY)
    write_ply(os.path.join(out_dir, "truth.ply"), truth)
    with open(os.path.join(out_dir, "truth.xml"), "w") as f:
        f.write(scene_xml("truth.ply", n_frames, width, height, columns, sun, truth_extra))
    scene = mi.load_file(os.path.join(out_dir, "truth.xml"))
    lidar_int = mi.load_dict({"type": "lidar_return"})
    cams, lids = poses(n_frames)
    frames = []
    sensors = {s.id(): s for s in scene.sensors()}
    for i in range(n_frames):
        img = np.array(mi.render(scene, sensor=sensors["camera_%04d" % i], spp=8))[..., :3]
        srgb = np.clip(np.where(img <= 0.0031308, img * 12.92, 1.055 * np.power(np.maximum(img, 0), 1 / 2.4) - 0.055), 0, 1)
        cv2.imwrite(os.path.join(out_dir, "observations", "image_%04d.png" % i),
                    cv2.cvtColor((srgb * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGB2BGR))
        scan = np.array(mi.render(scene, sensor=sensors["lidar_%04d" % i], integrator=lidar_int))
        write_exr(os.path.join(out_dir, "observations", "lidar_%04d.exr" % i), scan[..., :3],
                  ["intensity", "range", "hit"])
        frames.append({"index": i, "time": 0.1 * i, "held_out": i % 5 == 4,
                       "camera": "camera_%04d" % i, "lidar": "lidar_%04d" % i,
                       "image": "observations/image_%04d.png" % i,
                       "lidar_scan": "observations/lidar_%04d.exr" % i,
                       "camera_to_world": cams[i].tolist(), "lidar_to_world": lids[i].tolist(),
                       "objects": {}})
    start = read_ply(PLY)
    start.albedo = np.full_like(start.albedo, 0.5)
    start.lidar_albedo = np.full_like(start.lidar_albedo, 0.3)
    start.roughness = np.full_like(start.roughness, 0.5)
    write_ply(os.path.join(out_dir, "background.ply"), start)
    with open(os.path.join(out_dir, "scene.xml"), "w") as f:
        f.write(scene_xml("background.ply", n_frames, width, height, columns, sun).replace(
            '<rgb name="sun_irradiance" value="3.0, 2.8, 2.5"/>', '<rgb name="sun_irradiance" value="1"/>'))
    fx = width / 2 / np.tan(np.radians(40))
    meta = {"format": "mi-invrgbl-frames/1", "source": "tests/fit_scene.py",
            "camera": {"width": width, "height": height, "fx": fx, "fy": fx,
                       "cx": width / 2, "cy": height / 2},
            "lidar": {"beams": 64, "azimuth_steps": columns,
                      "elevations_deg": list(np.linspace(2.0, -24.9, 64)), "intensity": "raw"},
            "objects": {}, "frames": frames}
    with open(os.path.join(out_dir, "frames.json"), "w") as f:
        json.dump(meta, f)
    return os.path.join(out_dir, "scene.xml")


def build_with_block(out_dir, n_frames=4, width=32, height=12, columns=64):
    """:func:`build`, then ``object_1``: a 1 m block of 125 Gaussians 0.6 m
    above the road that drives 2.5 m further down the street at every frame
    (a moving node, its poses in frames.json). Returns the scene path."""
    from mi_invrgbl.physics.gaussian_ply import GaussianCloud, write_ply
    path = build(out_dir, n_frames=n_frames, width=width, height=height, columns=columns)
    g = (np.stack(np.meshgrid(*[np.linspace(-0.5, 0.5, 5)] * 3, indexing="ij"), -1)
         .reshape(-1, 3).astype(np.float32))
    n = len(g)
    write_ply(os.path.join(out_dir, "object_1.ply"), GaussianCloud(
        centers=g, scales=np.full((n, 3), 0.15, np.float32),
        quaternions=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
        opacities=np.full(n, 0.9, np.float32), normals=np.tile(np.float32([0, 0, 1]), (n, 1))))
    placed = []
    for i in range(n_frames):
        T = np.eye(4)
        T[:3, 3] = (3.0 + 2.5 * i, 0.8, 0.6)
        placed.append(T)
    matrix = " ".join("%.9g" % v for v in placed[0].ravel())
    xml = open(path).read().replace(
        "</scene>", '<shape type="gaussians" id="object_1"><string name="filename" '
        'value="object_1.ply"/><transform name="to_world"><matrix value="%s"/></transform>'
        "</shape></scene>" % matrix)
    open(path, "w").write(xml)
    meta = json.load(open(os.path.join(out_dir, "frames.json")))
    meta["objects"] = {"object_1": {"track_id": 1, "kind": "Car", "size_hwl": [1, 1, 1],
                                    "moving": True, "ply": "object_1.ply"}}
    for i, f in enumerate(meta["frames"]):
        f["objects"] = {"object_1": placed[i].tolist()}
    json.dump(meta, open(os.path.join(out_dir, "frames.json"), "w"))
    return path


def small_config(out, **kw):
    """A fit configuration small enough for a test on :func:`build`'s scene."""
    from mi_invrgbl.fit.runner import FitConfig
    base = dict(output=str(out), stage1_iterations=10, stage2_iterations=24, fit_width=48,
                lidar_columns=128, batch_rays=1024, eval_every=8, checkpoint_every=8,
                samples=8, lobe_iterations=10, sun_candidates=12, seed=1)
    base.update(kw)
    return FitConfig(**base)


def narrow_sun_rejection(choose):
    """``choose_lighting`` made to reject its sun narrowly (gain 0.03, bar
    0.05), so that the sun trial runs."""
    def narrowly_rejected(state):
        choice = choose(state)
        sun = choice.report["sun"]
        sun.update(gain=0.03, use_sun=False, direction=sun.get("direction", [0.3, 0.4, 0.866]))
        choice.use_sun, choice.sun_direction, choice.sun_irradiance = False, None, 0.0
        return choice
    return narrowly_rejected


@pytest.fixture(scope="module")
def scene_path(tmp_path_factory):
    """:func:`build`'s scene, once per test module (import it to use it)."""
    d = tmp_path_factory.mktemp("fitscene")
    return build(str(d), n_frames=5, width=48, height=16, columns=128)

if __name__ == "__main__":
    import sys
    variant_choice.use()
    import mi_invrgbl  # noqa: F401
    print(build(sys.argv[1]))

