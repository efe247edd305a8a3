"""What ``eval`` reads: the scene to score, the frames, the observations.

:func:`resolve_inputs` finds ``scene.xml`` and ``scene_lidar.xml`` of a fit
folder; :func:`select_frames` reads ``--frames``; :func:`read_png`,
:func:`read_channels` (EXR channels by name) and :func:`read_map` read the
observed images, LiDAR scans and ground-truth maps, each refusing a missing
or unreadable file with one error naming it.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from ..errors import UserError


def resolve_inputs(path):
    """``(scene.xml, scene_lidar.xml or None)`` for a fit folder or a scene file."""
    p = Path(path)
    if not p.exists():
        raise UserError("%s: no such fit folder or scene file" % p)
    if p.is_dir():
        scene = p / "scene.xml"
        if not scene.is_file():
            raise UserError("%s: not a fit folder (no scene.xml in it)" % p)
    else:
        if p.suffix.lower() != ".xml":
            raise UserError("%s: expected a fit folder or a scene .xml file" % p)
        scene = p
    lidar = scene.parent / "scene_lidar.xml"
    return scene, (lidar if lidar.is_file() and lidar != scene else None)


def select_frames(frames, spec: str) -> list:
    """Positions in ``frames`` (not indices) chosen by ``--frames``."""
    spec = (spec or "held-out").strip()
    by_index = {f.index: k for k, f in enumerate(frames.frames)}
    if spec in ("held-out", "held_out", "heldout", "test"):
        pos = [k for k, f in enumerate(frames.frames) if f.held_out]
        if not pos:
            raise UserError("%s: no held-out frame (use --frames all or A:B)" % frames.path)
        return pos
    if spec == "all":
        return list(range(len(frames.frames)))
    try:
        if ":" in spec:
            a, b = spec.split(":", 1)
            lo = int(a) if a.strip() else min(by_index)
            hi = int(b) if b.strip() else max(by_index) + 1
            wanted = [i for i in sorted(by_index) if lo <= i < hi]
        else:
            wanted = [int(v) for v in spec.split(",") if v.strip()]
    except ValueError:
        raise UserError("--frames: expected held-out, all, A:B or a list of indices, got '%s'"
                        % spec) from None
    missing = [i for i in wanted if i not in by_index]
    if missing:
        raise UserError("--frames: frame(s) %s not in %s" % (missing, frames.path))
    if not wanted:
        raise UserError("--frames %s selects no frame" % spec)
    return [by_index[i] for i in wanted]


def read_png(path):
    """An 8-bit (sRGB) image as float (H, W, 3) in [0, 1]."""
    import mitsuba as mi
    if not os.path.isfile(path):
        raise UserError("%s: observation image not found" % path)
    try:
        bmp = mi.Bitmap(str(path))
    except Exception as exc:
        raise UserError("%s: cannot read image: %s" % (path, exc)) from None
    arr = np.array(bmp)
    if arr.ndim == 2:
        arr = arr[..., None]
    scale = 255.0 if arr.dtype == np.uint8 else (65535.0 if arr.dtype == np.uint16 else 1.0)
    arr = arr.astype(np.float64) / scale
    if arr.shape[2] == 1:
        arr = np.repeat(arr, 3, axis=2)
    return arr[..., :3]


def read_channels(path, names, what="file"):
    """Named channels of an EXR as a dict of (H, W) arrays.

    Channels are matched by name (case-insensitive), never by position: EXR
    files store channels sorted by name, and a file whose channels are named
    otherwise cannot be read right by guessing. A missing channel is refused
    with one error naming the file, the channel and the channels it has.
    """
    from ..io.images import read_exr
    if not os.path.isfile(path):
        raise UserError("%s: %s not found" % (path, what))
    try:
        arr, chans = read_exr(str(path))
    except Exception as exc:
        raise UserError("%s: cannot read EXR: %s" % (path, exc)) from None
    lower = [c.lower() for c in chans]
    missing = [n for n in names if n.lower() not in lower]
    if missing:
        raise UserError("%s: %s has no channel %s (it has %s)"
                        % (path, what, ", ".join("'%s'" % n for n in missing),
                           ", ".join(chans) or "none"))
    return {n: arr[..., lower.index(n.lower())] for n in names}


def read_map(path):
    """A ground-truth map as (H, W) or (H, W, 3) float array (None if absent)."""
    from ..io.images import read_exr
    if not os.path.isfile(path):
        return None
    arr, _ = read_exr(str(path))
    return arr[..., 0] if arr.shape[2] == 1 else arr[..., :3]


def read_json_dict(path):
    """A JSON file's object (None if absent, unreadable or not an object)."""
    try:
        with open(path) as f:
            data = json.load(f)
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None
