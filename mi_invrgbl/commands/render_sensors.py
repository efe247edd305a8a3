"""``mi-invrgbl render SCENE``: render every sensor of a scene to EXR and PNG.

Camera sensors are rendered with the scene's integrator (normally ``invrgbl``:
RGB + AOVs), ``lidar`` sensors with the ``lidar_return`` integrator (range
image with intensity, range, hit, LiDAR albedo, alpha).
"""

from __future__ import annotations

import os
import time

import numpy as np

from ..errors import UserError
from ..scene.loading import is_lidar, load_scene, parse_defines


def add_parser(sub):
    p = sub.add_parser("render", help="render all sensors of a scene (RGB + AOVs, LiDAR range images)")
    p.add_argument("scene", help="Mitsuba XML scene file")
    p.add_argument("-o", "--output", default=None, help="output folder (default: <scene>_render)")
    p.add_argument("-D", dest="defines", action="append", default=[], metavar="KEY=VALUE",
                   help="set a <default> parameter of the scene (repeatable)")
    p.add_argument("--spp", type=int, default=0, help="samples per pixel for cameras (default: the sensor's)")
    p.add_argument("--lidar-model", choices=("pbr", "lambertian"), default="pbr",
                   help="LiDAR reflectance model for lidar sensors (default: pbr)")
    p.add_argument("--sensor", action="append", default=None,
                   help="render only the sensor with this id (repeatable)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace this command's earlier results in the output folder "
                        "(only the files it wrote; anything else there is kept)")
    p.set_defaults(run=run)


def sensor_name(sensor, index):
    name = sensor.id()
    return name if name else "sensor%02d" % index


def render_camera(scene, sensor, spp, out_dir, name):
    import mitsuba as mi
    from ..io.images import write_exr, write_png
    image = mi.render(scene, sensor=sensor, spp=spp)
    bitmap = sensor.film().bitmap()
    names = [f.name for f in bitmap.struct_()]
    array = np.array(image, np.float32)
    write_exr(os.path.join(out_dir, name + ".exr"), array, names)
    write_png(os.path.join(out_dir, name + ".png"), array[..., :3])
    written = [name + ".exr", name + ".png"]
    for aov in ("albedo", "normal"):
        idx = [i for i, c in enumerate(names) if c.startswith(aov + ".")]
        if len(idx) == 3:
            data = array[..., idx]
            if aov == "normal":
                data = data * 0.5 + 0.5
            write_png(os.path.join(out_dir, "%s_%s.png" % (name, aov)), data)
            written.append("%s_%s.png" % (name, aov))
    return written


def render_lidar(scene, sensor, model, out_dir, name):
    import mitsuba as mi
    from ..io.images import write_exr, write_false_colour_png
    from ..plugins.lidar_return import CHANNELS
    integrator = mi.load_dict({"type": "lidar_return", "model": model})
    array = np.array(mi.render(scene, sensor=sensor, integrator=integrator), np.float32)
    write_exr(os.path.join(out_dir, name + "_lidar.exr"), array, list(CHANNELS))
    hit = array[..., 2] > 0
    write_false_colour_png(os.path.join(out_dir, name + "_intensity.png"), array[..., 0], hit)
    write_false_colour_png(os.path.join(out_dir, name + "_range.png"), array[..., 1], hit)
    return [name + "_lidar.exr", name + "_intensity.png", name + "_range.png"], float(hit.mean())


def run(args):
    from .. import outdir
    scene_path = args.scene
    if args.spp < 0:
        raise UserError("--spp must be >= 0 (0: the sensor's own), got %d" % args.spp)
    target = args.output or os.path.splitext(scene_path)[0] + "_render"
    t0 = time.time()
    scene = load_scene(scene_path, parse_defines(args.defines))
    sensors = list(scene.sensors())
    if not sensors:
        raise UserError("%s: the scene has no sensor" % scene_path)
    names = [sensor_name(s, i) for i, s in enumerate(sensors)]
    wanted = set(args.sensor or [])
    unknown = sorted(wanted - set(names))
    if unknown:
        raise UserError("--sensor %s: %s has no sensor of that id (it has: %s)"
                        % (", ".join(unknown), scene_path, _shorten(names)))
    print("[render] %s: %d sensor(s), loaded in %.1f s" % (scene_path, len(sensors), time.time() - t0))
    with outdir.staged(target, "render", inputs=[scene_path], overwrite=args.overwrite) as out:
        _render(args, scene, sensors, wanted, str(out.path))
    print("[render] done in %.1f s; results in %s" % (time.time() - t0, target))
    return 0


def _shorten(names, most=8):
    return ", ".join(names[:most]) + (", ... (%d in all)" % len(names) if len(names) > most else "")


def _render(args, scene, sensors, wanted, out_dir):
    for i, sensor in enumerate(sensors):
        name = sensor_name(sensor, i)
        if wanted and name not in wanted:
            continue
        t = time.time()
        if is_lidar(sensor):
            files, hit_rate = render_lidar(scene, sensor, args.lidar_model, out_dir, name)
            extra = ", %.0f %% of beams return" % (100 * hit_rate)
        else:
            files = render_camera(scene, sensor, args.spp, out_dir, name)
            extra = ""
        print("[render] %-10s %.1f s%s -> %s" % (name, time.time() - t, extra, ", ".join(files)))
