"""``mi-invrgbl insert SCENE --object OBJ``: place an object into a scene and render it.

OBJ is a node of another scene (``OTHER.xml:NODE``, e.g. a fitted car's
Gaussians with their materials), a mesh (``.obj``/``.ply``) or a Gaussian
``.ply``. The target scene's lights light it and shadows fall both ways.
Writes the edited ``scene.xml`` (+ ``scene.diff``), ``frame_NNNN.{exr,png}``
and ``sequence.{mp4,gif}``. See docs/applications.md.
"""

from __future__ import annotations

from .. import outdir
from ..apps import insert, sequence
from ..apps.frame_set import FrameSet
from ..apps.pose_input import check_inside, parse_pose, read_trajectory
from ..scene.xml import SceneDoc
from ..errors import UserError
from .relight import _floats


def add_parser(sub):
    p = sub.add_parser("insert", help="insert a fitted node or a mesh into a scene and render it",
                       description=__doc__.replace("``", ""))
    p.add_argument("scene", help="target Mitsuba XML scene")
    p.add_argument("--object", required=True, metavar="OBJ",
                   help="OTHER.xml:NODE, mesh.obj, mesh.ply or gaussians.ply")
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--pose", metavar="X,Y,Z[,YAW]",
                       help="world position of the object's bottom centre and its yaw (degrees "
                            "about +z); or 16 numbers of a 4x4 matrix")
    where.add_argument("--track", metavar="POSES",
                       help="one pose per frame: .json list (x,y,z,yaw or 4x4 each) or text lines")
    p.add_argument("--keep-origin", action="store_true",
                   help="place the object's frame origin rather than its bottom centre")
    p.add_argument("--id", default="inserted", help="id of the inserted shape (default: inserted)")
    m = p.add_argument_group("material of a mesh file (cooktorrance)")
    m.add_argument("--albedo", type=_floats, default=[0.5, 0.5, 0.5], metavar="R,G,B",
                   help="diffuse albedo (default 0.5 grey)")
    m.add_argument("--roughness", type=float, default=0.5, help="roughness (default 0.5)")
    m.add_argument("--lidar-albedo", type=float, default=0.5, help="LiDAR albedo (default 0.5)")
    sequence.add_render_options(p)
    outdir.add_overwrite_option(p)
    p.set_defaults(run=run)


def run(args):
    if len(args.albedo) not in (1, 3):
        raise UserError("--albedo: expected one or three numbers")
    doc = SceneDoc.load(args.scene)
    obj = insert.load_object(args.object, doc, args.id, args.albedo, args.roughness,
                             args.lidar_albedo, args.keep_origin)
    print("[insert] object: %s" % obj.description)
    track = read_trajectory(args.track) if args.track else [parse_pose(args.pose)]
    edited, switched = insert.insert_doc(doc, obj, track[0])
    if switched:
        print("[insert] the scene's integrator cannot shade Gaussians: it now uses 'invrgbl'")
    sequence.apply_integrator_options(edited, args)
    target = sequence.output_dir(args, "insert")
    with outdir.staged(target, "insert", inputs=[args.scene, _object_file(args.object),
                                                 args.track], overwrite=args.overwrite) as out:
        out_dir = str(out.path)
        scene, _ = sequence.write_and_load(edited, doc, out_dir, "insert", log=out.log,
                                           defines=sequence.defines(args))
        shape_id = obj.shape.get("id")
        bounds = insert.scene_bounds_without(scene, shape_id)
        for k, pose in enumerate(track):
            check_inside(pose[:3, 3], bounds, "--pose" if args.pose else "--track pose %d" % k)
        frames = FrameSet(args.scene, scene, args.frames)
        hooks = [insert.TrackHook(shape_id, track, track[0])] if args.track else []
        result = sequence.render_frames(scene, frames, out_dir, args.spp, hooks=hooks,
                                        exposure=args.exposure, tag="insert", log=out.log)
    print("[insert] %d frame(s) in %.1f s; results in %s"
          % (len(frames.frames), result["seconds"], target))
    return 0


def _object_file(value):
    """The file of ``--object`` (``OTHER.xml:NODE`` names OTHER.xml)."""
    import os
    if not os.path.exists(value) and ":" in value:
        return value.rsplit(":", 1)[0]
    return value
