"""``mi-invrgbl night SCENE``: the scene at night, lit by headlights and streetlights.

Removes the sun, dims the sky, adds headlights (spot lights at the camera,
moving with it) and streetlights (spot lights pointing down) with 1/d^2
falloff. Writes the edited ``scene.xml`` (+ ``scene.diff``),
``frame_NNNN.{exr,png}`` and ``sequence.{mp4,gif}``. See docs/applications.md.
"""

from __future__ import annotations

from .. import outdir
from ..apps import lighting_edit, night, sequence
from ..scene import xml as xml_edit
from ..apps.frame_set import FrameSet
from ..apps.pose_input import parse_pose
from ..scene.xml import SceneDoc
from ..errors import UserError
from .relight import _floats


def add_parser(sub):
    p = sub.add_parser("night", help="render a scene at night with headlights and streetlights",
                       description=__doc__.replace("``", ""))
    p.add_argument("scene", help="Mitsuba XML scene (fitted, imported, or any scene of our plugins)")
    g = p.add_argument_group("sky")
    g.add_argument("--sky-scale", type=float, default=0.02,
                   help="multiply the day sky by this (default 0.02)")
    g.add_argument("--sky-radiance", type=_floats, default=None, metavar="R,G,B",
                   help="use a constant night sky of this radiance instead")
    s = p.add_argument_group("streetlights")
    s.add_argument("--streetlight", action="append", default=[], metavar="X,Y,Z",
                   help="a streetlight at this world position, pointing down (repeatable)")
    s.add_argument("--streetlights", type=int, default=6, metavar="N",
                   help="number of automatic streetlights when no --streetlight is given (default 6)")
    s.add_argument("--streetlight-spacing", type=float, default=15.0, metavar="M",
                   help="automatic streetlights: distance along the camera path (default 15 m)")
    s.add_argument("--streetlight-offset", type=float, default=4.0, metavar="M",
                   help="automatic streetlights: distance left/right of the path (default 4 m)")
    s.add_argument("--streetlight-height", type=float, default=5.7, metavar="M",
                   help="automatic streetlights: height above the road (default 5.7 m)")
    _spot_options(s, "streetlight", night.STREETLIGHT)
    h = p.add_argument_group("headlights")
    h.add_argument("--headlights", type=int, default=2, choices=(0, 1, 2),
                   help="headlights at the camera: 0, 1 or 2 (default 2)")
    _spot_options(h, "headlight", night.HEADLIGHT)
    sequence.add_render_options(p)
    outdir.add_overwrite_option(p)
    p.set_defaults(run=run)


def _spot_options(group, name, spec):
    group.add_argument("--%s-intensity" % name, type=float, default=spec.intensity, metavar="W_SR",
                       help="radiant intensity of the brightest channel (W/sr, default %g)"
                       % spec.intensity)
    group.add_argument("--%s-colour" % name, "--%s-color" % name, dest="%s_colour" % name,
                       type=_floats, default=list(spec.colour), metavar="R,G,B",
                       help="colour (default %s)" % ",".join("%g" % c for c in spec.colour))
    group.add_argument("--%s-cutoff" % name, type=float, default=spec.cutoff, metavar="DEG",
                       help="cone half-angle (default %g deg)" % spec.cutoff)


def _spec(args, name, default):
    return night.SpotSpec(getattr(args, name + "_intensity"), tuple(getattr(args, name + "_colour")),
                          getattr(args, name + "_cutoff"),
                          default.beam_width * getattr(args, name + "_cutoff") / default.cutoff
                          ).check(name)


def run(args):
    if args.sky_scale < 0:
        raise UserError("--sky-scale must be >= 0, got %g" % args.sky_scale)
    doc = SceneDoc.load(args.scene)
    base = lighting_edit.lighting_of_doc(doc)
    lighting = night.night_lighting(base, args.sky_scale, args.sky_radiance)
    street_spec = _spec(args, "streetlight", night.STREETLIGHT)
    head_spec = _spec(args, "headlight", night.HEADLIGHT)

    # Camera poses from the sensors alone (the shapes are loaded once, edited).
    cameras_scene = xml_edit.load_parts(doc, ("sensor",), "its sensors")
    cam_frames = FrameSet(args.scene, cameras_scene, args.frames)
    cameras = [cam_frames.camera_to_world(cameras_scene, f) for f in cam_frames.all]

    if args.streetlight:
        lamps = [(parse_pose(t, "--streetlight")[:3, 3], (0.0, 0.0, -1.0)) for t in args.streetlight]
        where = "given"
    else:
        if args.streetlights < 0:
            raise UserError("--streetlights must be >= 0")
        lamps, where = night.recorded_streetlights(args.scene)
        if lamps is not None:
            lamps = lamps[:args.streetlights]
        else:
            lamps = night.path_streetlights(cameras, args.streetlights, args.streetlight_spacing,
                                            args.streetlight_height, args.streetlight_offset)
            where = "along the camera path"
    for p, _ in lamps:
        print("[night] streetlight at (%.2f, %.2f, %.2f) (%s)" % (tuple(p) + (where,)))

    first = cam_frames.frames[0]
    edited, head_ids = night.night_doc(doc, lighting, lamps, street_spec, args.headlights,
                                       head_spec, cam_frames.camera_to_world(cameras_scene, first))
    sequence.apply_integrator_options(edited, args)
    target = sequence.output_dir(args, "night")
    with outdir.staged(target, "night", inputs=[args.scene], overwrite=args.overwrite) as out:
        out_dir = str(out.path)
        scene, _ = sequence.write_and_load(edited, doc, out_dir, "night", log=out.log,
                                           defines=sequence.defines(args))
        frames = FrameSet(args.scene, scene, args.frames)
        hook = night.HeadlightHook(head_ids, frames)
        result = sequence.render_frames(scene, frames, out_dir, args.spp, hooks=[hook],
                                        exposure=args.exposure, tag="night", log=out.log)
    print("[night] %d frame(s) in %.1f s; results in %s"
          % (len(frames.frames), result["seconds"], target))
    return 0
