"""Build, render and write a synthetic street, one timed step after another.

Everything is written into a temporary sibling of OUT and renamed to OUT at
the very end, so a street that exists under its final name is complete.

Output layout (N = frame number, 6 digits)::

    OUT/sequences/00/image_2/N.png      time-A render, 8-bit sRGB
    OUT/sequences/00/velodyne/N.bin     float32 x, y, z, intensity (sensor frame)
    OUT/sequences/00/calib.txt          P0..P3 (3x4), Tr (velodyne -> camera 0)
    OUT/sequences/00/times.txt          seconds
    OUT/poses/00.txt                    camera-0 poses relative to frame 0 (3x4 rows)
    OUT/label_02/0000.txt               KITTI tracking labels (moving + parked car)
    OUT/gt/{time_a,time_b,night}/N.exr  linear RGB renders
    OUT/gt/maps/N_{albedo,roughness,normal,lidar_albedo,sun_visibility,depth,mesh_id}.exr
    OUT/gt/lidar/N.exr                  range image: channels intensity, range, hit
    OUT/gt/scene_time_{a,b,night}.xml   the Mitsuba scenes (frame 0), meshes/, textures/
    OUT/gt/materials.json               true material per mesh (+ mesh_id order)
    OUT/gt/lights.json                  sun/sky of A and B, night lights
    OUT/gt/trajectory.json              world poses of camera, LiDAR and cars; intrinsics
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import time

import numpy as np

from ..errors import UserError
from . import (config as config_mod, groundtruth, labels, layout as layout_mod, lidar_sim,
               lights, materials, rgb_frames, scene_xml, sensors, trajectory, writers)

KINDS = ("time_a", "time_b", "night")


class Steps:
    """Prints and records how long each step takes."""

    def __init__(self, log=print):
        self.log = log
        self.times = {}
        self._t0 = time.perf_counter()

    def run(self, name, fn, *args, **kwargs):
        t = time.perf_counter()
        result = fn(*args, **kwargs)
        self.times[name] = time.perf_counter() - t
        self.log("[make-scene] %-28s %7.2f s" % (name, self.times[name]))
        return result

    def total(self):
        return time.perf_counter() - self._t0


def _matrix_list(ms):
    return [np.asarray(m).tolist() for m in ms]


def _write_assets(root, cfg, lay, rng_tex, light_info, cams, car_poses):
    gt = os.path.join(root, "gt")
    mesh_dir = os.path.join(gt, "meshes")
    tex_dir = os.path.join(gt, "textures")
    os.makedirs(mesh_dir)
    os.makedirs(tex_dir)
    albedo, lidar = materials.road_textures(rng_tex)
    writers.write_png_srgb(os.path.join(tex_dir, "road_albedo.png"), albedo)
    writers.write_png_linear_grey(os.path.join(tex_dir, "road_lidar.png"), lidar)
    mesh_files = {}
    for part in lay.parts:
        rel = "meshes/%s.ply" % part.name
        part.mesh.export(os.path.join(gt, rel), file_type="ply")
        mesh_files[part.name] = rel
    sensor0 = cams[0] @ trajectory.KITTI_FROM_MITSUBA
    for kind in KINDS:
        if kind == "night" and not cfg.night:
            continue
        text = scene_xml.scene_xml(kind, cfg, lay, mesh_files, sensor0, car_poses[0], light_info)
        with open(os.path.join(gt, "scene_%s.xml" % kind), "w") as f:
            f.write(text)
    table = {"meshes": [{"mesh_id": i, "name": p.name, "file": mesh_files[p.name],
                         "material": p.material, "dynamic": p.dynamic}
                        for i, p in enumerate(lay.parts)],
             "materials": {k: m.to_json() for k, m in lay.materials.items()},
             "uniform_wall": lay.wall,
             "notes": "mesh_id indexes gt/maps/*_mesh_id.exr (-1 = sky). Road albedo and "
                      "LiDAR albedo vary with its textures (sRGB PNG / linear 8-bit PNG); "
                      "its 'albedo'/'lidar_albedo' are nominal."}
    with open(os.path.join(gt, "materials.json"), "w") as f:
        json.dump(table, f, indent=1)
    with open(os.path.join(gt, "lights.json"), "w") as f:
        json.dump(light_info, f, indent=1)


def _write_kitti(root, cfg, K, cams, egos, car_poses, parked, pattern):
    seq = os.path.join(root, "sequences", "00")
    for d in ("image_2", "velodyne"):
        os.makedirs(os.path.join(seq, d))
    os.makedirs(os.path.join(root, "poses"))
    os.makedirs(os.path.join(root, "label_02"))
    writers.write_calib(os.path.join(seq, "calib.txt"), K, trajectory.cam_from_velo())
    writers.write_times(os.path.join(seq, "times.txt"),
                        [i / cfg.frame_rate for i in range(cfg.frames)])
    writers.write_poses(os.path.join(root, "poses", "00.txt"), trajectory.kitti_poses(cams))
    rows = labels.tracking_rows(car_poses, parked, cams, K, cfg.width, cfg.height)
    writers.write_tracking_labels(os.path.join(root, "label_02", "0000.txt"), rows)
    info = {"world_frame": "z up, x along the street, y left",
            "camera_frame": "KITTI camera: x right, y down, z forward",
            "velo_frame": "x forward, y left, z up",
            "world_from_cam": _matrix_list(cams),
            "world_from_velo": _matrix_list([trajectory.world_from_velo(e) for e in egos]),
            "world_from_moving_car": _matrix_list(car_poses),
            "world_from_parked_car": np.asarray(parked).tolist(),
            "car_hwl": list(layout_mod.CAR_HWL),
            "K": K.tolist(), "width": cfg.width, "height": cfg.height, "fov_x_deg": cfg.fov,
            "lidar": {"beams": pattern.n_beams, "azimuth_steps": cfg.azimuth_steps,
                      "elevation_deg": [float(pattern.elevations_deg[0]),
                                        float(pattern.elevations_deg[-1])],
                      "intensity": cfg.intensity, **pattern.to_json(),
                      "far_range": lidar_sim.FAR_RANGE,
                      "min_range": lidar_sim.MIN_RANGE, "power": lidar_sim.POWER,
                      "intensity_scale": lidar_sim.INTENSITY_SCALE,
                      "range_noise": lidar_sim.RANGE_NOISE,
                      "intensity_noise": lidar_sim.INTENSITY_NOISE,
                      "drop_rate": lidar_sim.DROP_RATE,
                      "azimuth": "phi_j = pi - 2 pi (j + 0.5) / W, row 0 = top beam"},
            "config": vars(cfg)}
    with open(os.path.join(root, "gt", "trajectory.json"), "w") as f:
        json.dump(info, f, indent=1)


def _ground_truth(root, cfg, lay, cams, egos, car_poses, sun, pattern):
    import mitsuba as mi
    gt = os.path.join(root, "gt")
    scene = mi.load_file(os.path.join(gt, "scene_time_a.xml"))
    table = groundtruth.MaterialTable(scene, lay.parts, lay.materials, gt)
    poser = rgb_frames.FramePoser(scene, car_poses)
    map_dir = os.path.join(gt, "maps")
    lidar_dir = os.path.join(gt, "lidar")
    os.makedirs(map_dir)
    os.makedirs(lidar_dir)
    seq = os.path.join(root, "sequences", "00", "velodyne")
    for i in range(cfg.frames):
        poser.set_frame(i, cams[i] @ trajectory.KITTI_FROM_MITSUBA)
        maps = groundtruth.camera_maps(scene, table, cfg.width, cfg.height, cams[i], sun)
        for name, data in maps.items():
            writers.write_exr(os.path.join(map_dir, "%06d_%s.exr" % (i, name)), data)
        rng = np.random.default_rng([cfg.seed, i, 7])
        scan = lidar_sim.sweep(scene, table, trajectory.world_from_velo(egos[i]), pattern, rng,
                               cfg.intensity)
        writers.write_velodyne(os.path.join(seq, "%06d.bin" % i), scan["points"])
        image = np.stack([scan["intensity"], scan["range"], scan["hit"]], axis=-1)
        writers.write_exr(os.path.join(lidar_dir, "%06d.exr" % i), image,
                          channels=("intensity", "range", "hit"))


def generate_street(out: str, cfg: "config_mod.StreetConfig", log=print) -> dict:
    """Generate the street into ``out``; returns the time of each step (seconds)."""
    cfg.validate()
    out, parent = config_mod.check_output(out)
    steps = Steps(log)
    try:
        tmp = tempfile.mkdtemp(prefix=".%s.partial-" % os.path.basename(out), dir=parent)
    except OSError as exc:   # read-only file system, or root-squashed/locked folder
        raise UserError("cannot write into '%s' (%s)" % (parent, exc.strerror)) from None
    try:
        rng = np.random.default_rng(cfg.seed)
        sun = lights.sun_a_direction()
        lay = steps.run("layout", layout_mod.build, cfg.frames, cfg.step, rng, sun)
        egos = trajectory.ego_poses(cfg.frames, cfg.step)
        cams = np.array([trajectory.world_from_cam(e) for e in egos])
        car_poses = trajectory.moving_car_poses(cfg.frames, cfg.step)
        parked = trajectory.parked_car_pose()
        K = trajectory.intrinsics(cfg.width, cfg.height, cfg.fov)
        light_info = lights.all_lights(lay.lamps, lay.headlights)
        os.makedirs(os.path.join(tmp, "gt"))
        steps.run("meshes, textures, scenes", _write_assets, tmp, cfg, lay,
                  np.random.default_rng([cfg.seed, 1]), light_info, cams, car_poses)
        pattern = sensors.make_pattern(cfg.lidar, cfg.beams, cfg.azimuth_steps, cfg.seed)
        if pattern.rays_file is not None:
            # Keep the pattern with the street (the user's file is only read).
            np.save(os.path.join(tmp, "gt", "lidar_rays.npy"),
                    np.hstack([pattern.origins, pattern.directions, pattern.beam[:, None]]))
            pattern.rays_file = "gt/lidar_rays.npy"
        steps.run("KITTI calib, poses, labels", _write_kitti, tmp, cfg, K, cams, egos,
                  car_poses, parked, pattern)
        steps.run("ground-truth maps + LiDAR", _ground_truth, tmp, cfg, lay, cams, egos,
                  car_poses, sun, pattern)
        cam_sensors = cams @ trajectory.KITTI_FROM_MITSUBA
        gt = os.path.join(tmp, "gt")
        for k, kind in enumerate(KINDS):
            if kind == "night" and not cfg.night:
                continue
            png = os.path.join(tmp, "sequences", "00", "image_2") if kind == "time_a" else None
            headlights = light_info["night"]["headlights"] if kind == "night" else ()
            steps.run("render %s (%d spp)" % (kind, cfg.spp), rgb_frames.render_sequence,
                      os.path.join(gt, "scene_%s.xml" % kind), os.path.join(gt, kind),
                      cam_sensors, car_poses, headlights, cfg.spp, cfg.seed * 3 + k, png_dir=png)
        os.rename(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    steps.times["total"] = steps.total()
    log("[make-scene] %-28s %7.2f s -> %s" % ("total", steps.times["total"], out))
    return steps.times
