"""``mi-invrgbl lidar SCENE``: simulate LiDAR sweeps of a scene from new poses.

Poses come from ``--pose`` (repeatable), ``--trajectory``, or by default the
scene's own LiDAR poses. Each sweep is rendered with the ``lidar_return``
integrator (the fitted sensor response when the fit's ``scene_lidar.xml`` is
beside the scene) and written as a KITTI ``.bin``, a range-image EXR
(intensity, range, hit, lidar_albedo, alpha) and PNG previews, plus
``sequence.{mp4,gif}``. See docs/applications.md.
"""

from __future__ import annotations

import os
import time

import numpy as np

from .. import outdir
from ..apps import lidar_resimulation, sequence, video
from ..apps.frame_set import FrameSet, parse_selection
from ..apps.pose_input import check_inside, parse_pose, read_trajectory, scene_bounds
from ..scene.xml import SceneDoc
from ..errors import UserError


def add_parser(sub):
    p = sub.add_parser("lidar", help="simulate LiDAR sweeps (KITTI .bin + range-image EXR) from new poses",
                       description=__doc__.replace("``", ""))
    p.add_argument("scene", help="Mitsuba XML scene (fitted, imported, or any scene of our plugins)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--pose", action="append", default=None, metavar="X,Y,Z[,YAW]",
                       help="sensor pose in the world (x forward, y left, z up at yaw 0; repeatable)")
    where.add_argument("--trajectory", metavar="FILE",
                       help="poses: .json (list of x,y,z,yaw or 4x4; or frames.json / trajectory.json) "
                            "or text (KITTI 3x4 rows, or x y z yaw per line)")
    p.add_argument("--sensor", default="scene", metavar="NAME",
                   help="hdl64, vlp32, vlp16, a custom .json, or 'scene': the scene's recorded "
                        "LiDAR if known, else hdl64 (default)")
    p.add_argument("--azimuth-steps", type=int, default=None, help="columns per sweep (default: the sensor's)")
    p.add_argument("--near", type=float, default=None, help="minimum range in m (default: the sensor's)")
    p.add_argument("--far", type=float, default=None, help="maximum range in m (default: the sensor's)")
    p.add_argument("--lidar-model", choices=("pbr", "lambertian"), default=None,
                   help="reflectance model (default: the fitted one, else pbr)")
    p.add_argument("--intensity-scale", type=float, default=None,
                   help="multiply intensities by this before clipping to [0, 1] "
                        "(default 1; the generator's scale for a synthetic street)")
    p.add_argument("--drop-rate", type=float, default=0.0,
                   help="drop this fraction of returns at random (default 0)")
    p.add_argument("--seed", type=int, default=0, help="seed of the random drops")
    p.add_argument("-o", "--output", default=None,
                   help="output folder (default: <scene>_lidar beside the scene)")
    p.add_argument("-D", dest="defines", action="append", default=[], metavar="KEY=VALUE",
                   help="set a <default> parameter of the scene (repeatable)")
    p.add_argument("--frames", default=None, metavar="A:B",
                   help="poses to simulate, python-slice style (default: all)")
    outdir.add_overwrite_option(p)
    p.set_defaults(run=run)


def _poses(args, doc):
    """[(frame number, world_from_lidar)], and whether they are the scene's own frames."""
    if args.pose:
        return [(k, parse_pose(t)) for k, t in enumerate(args.pose)], False
    if args.trajectory:
        poses = read_trajectory(args.trajectory)
        return [(k, poses[k]) for k in parse_selection(args.frames, len(poses))], False
    from ..scene import xml as xml_edit
    sensors = xml_edit.load_parts(doc, ("sensor",), "its sensors")
    try:
        found = FrameSet(args.scene, sensors, args.frames).lidar_poses(sensors)
    except UserError:
        found = []
    if not found:
        raise UserError("%s: the scene has no LiDAR poses of its own: give --pose or --trajectory"
                        % args.scene)
    return found, True


def run(args):
    if not 0.0 <= args.drop_rate < 1.0:
        raise UserError("--drop-rate must lie in [0, 1), got %g" % args.drop_rate)
    if args.azimuth_steps is not None and args.azimuth_steps < 1:
        raise UserError("--azimuth-steps must be at least 1, got %d" % args.azimuth_steps)
    if args.intensity_scale is not None and not 0 < args.intensity_scale < float("inf"):
        raise UserError("--intensity-scale must be a positive number, got %g"
                        % args.intensity_scale)
    for name in ("near", "far"):
        value = getattr(args, name)
        if value is not None and not 0 <= value < float("inf"):
            raise UserError("--%s must be a distance >= 0 in metres, got %g" % (name, value))
    doc = SceneDoc.load(args.scene)
    target = args.output or os.path.splitext(args.scene)[0] + "_lidar"
    poses, own_frames = _poses(args, doc)
    with outdir.staged(target, "lidar", inputs=[args.scene, args.trajectory,
                                                args.sensor if os.path.isfile(args.sensor) else None],
                       overwrite=args.overwrite) as out:
        _simulate(args, doc, str(out.path), poses, own_frames, out.log)
    print("[lidar] results in %s" % target)
    return 0


def _simulate(args, doc, out_dir, poses, own_frames, log=print):
    import mitsuba as mi
    from ..io.images import write_exr, write_false_colour_png
    from ..io.velodyne import write_velodyne
    spec = lidar_resimulation.sensor_spec(args.sensor, args.azimuth_steps,
                                 lidar_resimulation.recorded_sensor(args.scene), out_dir, args.near, args.far)
    scale = (args.intensity_scale if args.intensity_scale is not None
             else lidar_resimulation.default_intensity_scale(args.scene))
    print("[lidar] sensor %s: %d beams x %d azimuth steps; %d pose(s); intensity scale %g"
          % (spec.name, spec.height, spec.width, len(poses), scale))
    edited, ident = lidar_resimulation.lidar_doc(doc, spec, poses[0][1], args.lidar_model)
    scene, _ = sequence.write_and_load(edited, doc, out_dir, "lidar", log=log,
                                       defines=sequence.defines(args))
    sensor = next(s for s in scene.sensors() if s.id() == ident)
    bounds = scene_bounds(scene)
    for k, pose in poses:
        check_inside(pose[:3, 3], bounds, "pose %d" % k)
    # At the scene's own frames, moving objects go where they were then.
    frames = FrameSet(args.scene, scene) if own_frames else None
    by_index = {f.index: f for f in frames.all} if frames is not None else {}
    params = mi.traverse(sensor)
    directions = sensor.ray_directions_local()
    rng = np.random.default_rng(args.seed)
    previews, t0 = [], time.time()
    for k, pose in poses:
        t = time.time()
        if k in by_index:
            frames.apply(scene, by_index[k])
        params["to_world"] = mi.Transform4f(mi.ScalarMatrix4f(pose))
        params.update()
        image = np.array(mi.render(scene, sensor=sensor), np.float32)
        sweep = lidar_resimulation.sweep_outputs(image, directions, scale, args.drop_rate, rng)
        stem = os.path.join(out_dir, "frame_%04d" % k)
        write_velodyne(stem + ".bin", sweep["points"], sweep["intensity"])
        write_exr(stem + ".exr", sweep["image"], list(lidar_resimulation.CHANNELS))
        write_false_colour_png(stem + ".png", sweep["image"][..., 0], sweep["hit"])
        write_false_colour_png(stem + "_range.png", sweep["image"][..., 1], sweep["hit"])
        previews.append(lidar_resimulation.preview(sweep["image"]))
        print("[lidar] frame_%04d %.1f s, %d points (%.0f %% of beams return) -> %s.bin, %s.exr, %s.png"
              % (k, time.time() - t, len(sweep["points"]), 100 * sweep["hit"].mean(),
                 *(os.path.basename(stem),) * 3))
    for path in (video.write_animation(out_dir, previews) if len(previews) > 1 else []):
        print("[lidar] animation -> %s" % os.path.basename(path))
    print("[lidar] %d sweep(s) in %.1f s" % (len(poses), time.time() - t0))
