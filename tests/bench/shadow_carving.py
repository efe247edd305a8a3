"""Shadow carving applied to a fit made without it, for a paired comparison.

    python tests/bench/shadow_carving.py FIT_DIR [--write] [--min-weight 0.1]

``fit`` leaves out of its scene the Gaussians no camera or LiDAR beam sees
that block the fitted sun from Gaussians the images show sunlit
(``mi_invrgbl/fit/shadow_carving.py``). On a fit made with
``--no-shadow-carving`` this script does the same from the fitted scene
alone, so one fit can be scored with and without it (``eval`` on both):

* camera-seen: the summed blend weight over every pixel centre of every
  frame not held out (the fit counts its training and validation frames,
  with their masks; no masks here);
* LiDAR-seen: the same over the rays to every raw return of those frames;
* receivers: static Gaussians seen by a camera, facing the sun, whose
  learned sun visibility is at least one half; droppable: static Gaussians seen by neither.

It prints what the fit's log prints, and with ``--write`` writes the carved
scene next to the fit (``FIT_DIR_carved``: its scene files with the carved
``.ply`` files), under a temporary name renamed into place; an existing
folder of that name is left alone and the run stops.
"""

import sys as _sys, pathlib as _pathlib
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parents[1]))
import variant_choice  # noqa: E402  (--variant NAME, default $MI_INVRGBL_VARIANT or llvm_ad_rgb)
variant_choice.from_argv()

import argparse  # noqa: E402
import glob  # noqa: E402
import os  # noqa: E402
import shutil  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

import mi_invrgbl  # noqa: E402,F401
from mi_invrgbl.eval.inputs import resolve_inputs  # noqa: E402
from mi_invrgbl.eval.lidar_novel_view import frame_rays  # noqa: E402
from mi_invrgbl.fit import shadow_carving as sc  # noqa: E402
from mi_invrgbl.physics import hits as hitlib  # noqa: E402
from mi_invrgbl.physics.gaussian_ply import read_ply, write_ply  # noqa: E402
from mi_invrgbl.physics.host_arrays import jit_array  # noqa: E402
from mi_invrgbl.physics.lighting import GaussianTable, point_lights  # noqa: E402
from mi_invrgbl.scene.frames import Frames  # noqa: E402
from mi_invrgbl.scene.loading import load_scene  # noqa: E402
from mi_invrgbl.scene.posing import set_frame  # noqa: E402
from mi_invrgbl.synthetic.groundtruth import camera_rays  # noqa: E402


def summed_weight(scene, nodes, table, rays):
    """Per Gaussian of ``table``: its blend weight summed over ``rays``."""
    h = hitlib.trace(scene, rays, 64, 1e-3, nodes)
    g = hitlib.eval_gaussian_hits(nodes, rays, h)
    w, _ = hitlib.blend_weights(g)
    gi = np.array(table.global_index(g.node_ids, g.prims), np.int64)
    w = np.where(np.array(g.active, bool), np.array(w, np.float64), 0.0)
    return np.bincount(gi, w, minlength=table.total)


def seen_weights(scene, frames, nodes, table):
    """``(camera, lidar)`` summed blend weights over the frames not held out."""
    camera = np.zeros(table.total)
    lidar = np.zeros(table.total)
    with dr.suspend_grad():
        for k, rec in enumerate(frames.frames):
            if rec.held_out:
                continue
            sensor, _ = set_frame(scene, frames, k)
            if sensor is not None:
                w, h = (int(v) for v in sensor.film().crop_size())
                camera += summed_weight(scene, nodes, table, camera_rays(sensor, w, h))
            if rec.points is not None and os.path.isfile(rec.points):
                fr = frame_rays(rec, None, frames.lidar.elevations_deg)
                o = np.broadcast_to(fr.origin, fr.directions.shape).astype(np.float32)
                d = fr.directions.astype(np.float32)
                rays = mi.Ray3f(mi.Point3f(*[jit_array(mi.Float, o[:, i]) for i in range(3)]),
                                mi.Vector3f(*[jit_array(mi.Float, d[:, i]) for i in range(3)]))
                rays.maxt = jit_array(mi.Float, (fr.range + 0.5).astype(np.float32))
                lidar += summed_weight(scene, nodes, table, rays)
    return camera, lidar


def write_carved(fit, dropped_by_node):
    """The fit's scene with the carved Gaussians left out, as ``FIT_carved``."""
    target = os.path.normpath(fit) + "_carved"
    if os.path.exists(target):
        raise SystemExit("%s: exists; not overwritten" % target)
    tmp = tempfile.mkdtemp(prefix=os.path.basename(target) + ".", dir=os.path.dirname(target) or ".")
    try:
        for f in ("scene.xml", "scene_lidar.xml", "frames.json"):
            if os.path.isfile(os.path.join(fit, f)):
                shutil.copy2(os.path.join(fit, f), os.path.join(tmp, f))
        for path in glob.glob(os.path.join(fit, "*.ply")):
            name = os.path.splitext(os.path.basename(path))[0]
            if name in dropped_by_node:
                write_ply(os.path.join(tmp, name + ".ply"), read_ply(path).subset(~dropped_by_node[name]))
            else:
                shutil.copy2(path, os.path.join(tmp, name + ".ply"))
        os.rename(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return target


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("fit", help="fitted scene folder (made with fit --no-shadow-carving)")
    ap.add_argument("--min-weight", type=float, default=sc.MIN_WEIGHT,
                    help="summed blend weight on sunlit Gaussians' shadow rays that drops one")
    ap.add_argument("--write", action="store_true", help="write FIT_DIR_carved for eval")
    args = ap.parse_args()
    if args.write and os.path.exists(os.path.normpath(args.fit) + "_carved"):
        raise SystemExit("%s_carved: exists; not overwritten" % os.path.normpath(args.fit))
    t0 = time.perf_counter()
    scene_xml, _ = resolve_inputs(args.fit)
    frames = Frames.load(scene_xml)
    scene = load_scene(str(scene_xml))
    suns = [e for kind, e in point_lights(scene) if kind == "sun"]
    if not suns:
        raise SystemExit("%s: the fitted scene has no sun; nothing to carve" % args.fit)
    nodes = hitlib.gaussian_nodes(scene)
    table = GaussianTable.build(nodes)
    camera, lidar = seen_weights(scene, frames, nodes, table)
    params = mi.traverse(scene)
    moving = set(frames.objects)
    direction = np.array(dr.detach(suns[0].sun_direction_world()), np.float64).ravel()
    static = np.zeros(table.total, bool)
    lit = np.zeros(table.total, bool)
    for node, off in zip(table.nodes, table.offsets):
        name = node.shape.id()
        key = name + ".sun_visibility"
        if name in moving or key not in params.keys():
            continue
        static[off:off + node.count] = True
        lit[off:off + node.count] = sc.sunlit(np.array(params[key], np.float64),
                                              np.array(params[name + ".normal"], np.float64), direction)
    seen = camera > sc.SEEN
    dropped, report = sc.carve_unseen_blockers(scene, static & seen & lit,
                                               static & ~seen & (lidar <= sc.SEEN), direction,
                                               min_weight=args.min_weight)
    by_node = {node.shape.id(): dropped[off:off + node.count]
               for node, off in zip(table.nodes, table.offsets) if dropped[off:off + node.count].any()}
    print("%s: %d Gaussians, %d seen by a camera, %d by the LiDAR only; %d sunlit receivers, "
          "%.1f %% of them shadowed; %d unseen blockers left out (%s) over %d rounds, then %.1f %%; %.1f s"
          % (args.fit, table.total, seen.sum(), np.sum(~seen & (lidar > sc.SEEN)), report.receivers,
             100 * report.shadowed_before, dropped.sum(),
             ", ".join("%s %d" % (n, m.sum()) for n, m in by_node.items()) or "none",
             len(report.dropped), 100 * report.shadowed_after, time.perf_counter() - t0))
    if args.write:
        print("wrote %s" % write_carved(args.fit, by_node))


if __name__ == "__main__":
    main()
