"""``mi-invrgbl relight SCENE``: render the frames under a new sky and sun.

One of ``--sun-elevation/--sun-azimuth``, ``--time`` or ``--light-from``
picks the new lighting; shadows are traced for the new sun. Writes the edited
``scene.xml`` (+ ``scene.diff``), ``frame_NNNN.{exr,png}`` and
``sequence.{mp4,gif}`` into the output folder. See docs/applications.md.
"""

from __future__ import annotations

from .. import outdir
from ..apps import lighting_edit, relight, sequence
from ..apps.frame_set import FrameSet
from ..scene.xml import SceneDoc


def _floats(text):
    from ..errors import UserError
    try:
        return [float(t) for t in text.replace(",", " ").split()]
    except ValueError:
        raise UserError("expected numbers separated by commas, got '%s'" % text) from None


def add_parser(sub):
    p = sub.add_parser("relight", help="render a scene under a new sun and sky (moving shadows)",
                       description=__doc__.replace("``", ""))
    p.add_argument("scene", help="Mitsuba XML scene (fitted, imported, or any scene of our plugins)")
    g = p.add_argument_group("new lighting (one of)")
    g.add_argument("--sun-elevation", type=float, default=None, metavar="DEG",
                   help="sun elevation above the horizon (degrees)")
    g.add_argument("--sun-azimuth", type=float, default=None, metavar="DEG",
                   help="sun azimuth, from world +x towards +y (degrees)")
    g.add_argument("--time", default=None, metavar="WHEN",
                   help="time of day: HH:MM or YYYY-MM-DDTHH:MM[+HH:MM]; the sun's position "
                        "follows from --latitude/--longitude")
    g.add_argument("--light-from", default=None, metavar="OTHER",
                   help="copy the sky and sun of another scene XML (or lights.json:KEY)")
    s = p.add_argument_group("sun position from --time")
    s.add_argument("--date", default=None, help="day for a bare HH:MM --time (default 2024-06-21)")
    s.add_argument("--utc-offset", type=float, default=None,
                   help="hours ahead of UTC when --time has no zone (default 2, CEST)")
    s.add_argument("--latitude", type=float, default=None, help="degrees north (default 49.01, Karlsruhe)")
    s.add_argument("--longitude", type=float, default=None, help="degrees east (default 8.40)")
    s.add_argument("--north", type=float, default=90.0,
                   help="world azimuth of geographic north (default 90: +x east, +y north)")
    o = p.add_argument_group("light levels (override any mode)")
    o.add_argument("--sun-irradiance", type=_floats, default=None, metavar="R,G,B",
                   help="sun irradiance (default: the scene's)")
    o.add_argument("--sky-radiance", type=_floats, default=None, metavar="R,G,B",
                   help="replace the sky by a constant one of this radiance")
    o.add_argument("--sky-scale", type=float, default=None, help="multiply the sky by this")
    sequence.add_render_options(p)
    outdir.add_overwrite_option(p)
    p.set_defaults(run=run)


#: Options that change the lighting; relight without any of them would only
#: render the scene's own light again.
LIGHTING_OPTIONS = ("sun_elevation", "sun_azimuth", "time", "light_from", "sun_irradiance",
                    "sky_radiance", "sky_scale")


def run(args):
    from ..errors import UserError
    if all(getattr(args, name) is None for name in LIGHTING_OPTIONS):
        raise UserError("no new lighting given: use --sun-elevation/--sun-azimuth, --time or "
                        "--light-from (or --sun-irradiance, --sky-radiance, --sky-scale)")
    doc = SceneDoc.load(args.scene)
    base = lighting_edit.lighting_of_doc(doc)
    if base is not None:
        print("[relight] scene lighting: %s" % base.describe())
    lighting = relight.new_lighting(
        base, elevation=args.sun_elevation, azimuth=args.sun_azimuth, time=args.time,
        date=args.date, utc_offset=args.utc_offset, latitude=args.latitude,
        longitude=args.longitude, north=args.north, light_from=args.light_from,
        sun_irradiance=args.sun_irradiance, sky_radiance=args.sky_radiance,
        sky_scale=args.sky_scale)
    print("[relight] new lighting:   %s" % lighting.describe())
    edited = relight.relight_doc(doc, lighting)
    sequence.apply_integrator_options(edited, args)
    target = sequence.output_dir(args, "relight")
    with outdir.staged(target, "relight", inputs=[args.scene, light_source(args.light_from)],
                       overwrite=args.overwrite) as out:
        out_dir = str(out.path)
        scene, _ = sequence.write_and_load(edited, doc, out_dir, "relight", log=out.log,
                                           defines=sequence.defines(args))
        frames = FrameSet(args.scene, scene, args.frames)
        result = sequence.render_frames(scene, frames, out_dir, args.spp, exposure=args.exposure,
                                        tag="relight", log=out.log)
    print("[relight] %d frame(s) in %.1f s; results in %s"
          % (len(frames.frames), result["seconds"], target))
    return 0


def light_source(value):
    """The file named by ``--light-from FILE[:KEY]`` (None without one)."""
    if not value:
        return None
    import os
    if not os.path.exists(value) and ":" in value:
        return value.rsplit(":", 1)[0]
    return value
