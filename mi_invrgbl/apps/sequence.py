"""Render the frames of an edited scene to EXR + PNG per frame and an animation.

Shared by every camera application: it loads the edited XML (written first,
so what is rendered is exactly the file the user can open), renders each
selected frame with ``mi.render``, writes ``frame_NNNN.exr`` (all channels
the integrator produces, e.g. ``invrgbl``'s AOVs) and ``frame_NNNN.png``
(sRGB, times ``exposure``), then ``sequence.mp4`` / ``sequence.gif``.
"""

from __future__ import annotations

import os
import time

import numpy as np

from ..errors import UserError
from ..scene.loading import load_scene, parse_defines
from . import video
from .frames import FrameSet, write_origin


def render_frames(scene, frames: FrameSet, out_dir: str, spp: int = 0, hooks=(),
                  exposure: float = 1.0, tag: str = "render", log=print, seed: int = 0) -> dict:
    """Render every selected frame; returns ``{'files': [...], 'images': {index: rgb}, 'seconds': t}``.

    ``hooks`` are called as ``hook(scene, frame, sensor)`` after the frame is
    posed and before it renders (headlights follow the camera, an inserted
    object follows its track).
    """
    import mitsuba as mi
    from ..io.images import write_exr, write_png
    os.makedirs(out_dir, exist_ok=True)
    files, images, previews = [], {}, []
    t0 = time.time()
    for frame in frames.frames:
        t = time.time()
        sensor = frames.apply(scene, frame)
        for hook in hooks:
            hook(scene, frame, sensor)
        image = np.array(mi.render(scene, sensor=sensor, spp=spp, seed=seed + frame.index),
                         np.float32)
        names = [f.name for f in sensor.film().bitmap().struct_()]
        if len(names) != image.shape[-1]:
            names = ["R", "G", "B"] + ["ch%d" % i for i in range(3, image.shape[-1])]
        exr = os.path.join(out_dir, frame.name + ".exr")
        png = os.path.join(out_dir, frame.name + ".png")
        write_exr(exr, image, names)
        write_png(png, image[..., :3], exposure)
        previews.append(video.to_srgb8(image[..., :3], exposure))
        images[frame.index] = image[..., :3]
        files += [exr, png]
        log("[%s] %s %.1f s -> %s, %s" % (tag, frame.name, time.time() - t, exr, png))
    animation = video.write_animation(out_dir, previews) if len(previews) > 1 else []
    if len(previews) > 1 and not animation:
        log("[%s] this OpenCV build writes neither MP4 nor GIF: the PNG frames are the sequence"
            % tag)
    for path in animation:
        log("[%s] animation -> %s" % (tag, path))
    return {"files": files + animation, "images": images, "seconds": time.time() - t0}


def write_and_load(doc, original, out_dir: str, tag: str, log=print, defines=None):
    """Write the edited XML (+ diff) into ``out_dir``, print where, and load it.

    ``defines`` set the scene's ``<default>`` parameters (``-D key=value``).
    """
    os.makedirs(out_dir, exist_ok=True)
    path = os.path.join(out_dir, "scene.xml")
    written = doc.write(path, original)
    write_origin(out_dir, original.path)
    log("[%s] edited scene -> %s (edit: %s)" % (tag, written[0], written[-1]))
    try:
        return load_scene(path, defines), path
    except UserError as exc:
        raise UserError("%s (the edit of %s)" % (exc, original.path)) from None


def add_render_options(p, default_exposure: float = 1.0) -> None:
    """Options every camera application shares."""
    p.add_argument("-o", "--output", default=None,
                   help="output folder (default: <scene>_<command> beside the scene)")
    p.add_argument("-D", dest="defines", action="append", default=[], metavar="KEY=VALUE",
                   help="set a <default> parameter of the scene (repeatable)")
    p.add_argument("--frames", default=None, metavar="A:B",
                   help="frames to render, python-slice style (default: all)")
    p.add_argument("--spp", type=int, default=0, help="samples per pixel (default: the sensor's)")
    p.add_argument("--samples", type=int, default=0,
                   help="sky samples M per Gaussian of the invrgbl integrator (default: the scene's)")
    p.add_argument("--exposure", type=float, default=default_exposure,
                   help="multiplier applied before writing PNGs and animations (default: %g)"
                   % default_exposure)


def apply_integrator_options(doc, args) -> None:
    """``--samples``: the ``invrgbl`` integrator's M."""
    from ..scene import xml
    integrator = doc.integrator()
    if getattr(args, "samples", 0):
        if args.samples < 1:
            raise UserError("--samples must be at least 1")
        if integrator is not None and integrator.get("type") == "invrgbl":
            xml.set_child_param(integrator, "integer", "samples", args.samples)
    if getattr(args, "spp", 0) < 0:
        raise UserError("--spp must be at least 1 (or 0: the sensor's own count)")


def defines(args) -> dict:
    return parse_defines(getattr(args, "defines", []) or [])


def output_dir(args, command: str) -> str:
    return args.output or os.path.splitext(args.scene)[0] + "_" + command
