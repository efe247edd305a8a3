"""``frames.json``: the per-frame records of an imported scene.

See ``docs/scene_format.md`` for the files. This module reads, checks and
writes ``frames.json``; :func:`mi_invrgbl.scene.posing.set_frame` places the
dynamic objects for a frame::

    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    import mi_invrgbl
    from mi_invrgbl.scene.frames import Frames
    from mi_invrgbl.scene.posing import set_frame

    scene = mi.load_file("DIR/scene.xml")
    frames = Frames.load("DIR/scene.xml")      # or DIR/frames.json or DIR
    for i in frames.train_indices():
        cam, lidar = set_frame(scene, frames, i)   # the frame's two sensors
        img = mi.render(scene, sensor=cam)

Records (all paths resolved to absolute ``Path`` objects; matrices are
``(4, 4)`` float64 numpy arrays):

``Frames``
    ``path`` (the frames.json file), ``root`` (its folder), ``source``,
    ``camera`` (:class:`CameraInfo`), ``lidar`` (:class:`LidarInfo`),
    ``objects`` (``{name: ObjectRecord}``, ordered as in the file),
    ``ground_truth`` (``Path`` or ``None``), ``frames`` (list of
    :class:`FrameRecord`), ``extra`` (unknown top-level keys, kept on save).
    ``len(frames)``, ``frames[i]``, ``iter(frames)`` go over the frame records;
    ``train_indices()`` / ``held_out_indices()``; ``save(path)`` writes the
    file again with paths relative to the new location.
``FrameRecord``
    ``index``, ``time``, ``held_out``, ``camera`` / ``lidar`` (sensor ids),
    ``image``, ``lidar_scan``, ``points`` (Paths), ``camera_to_world`` (dataset
    camera frame: x right, y down, z forward), ``lidar_to_world`` (x forward,
    y left, z up), ``objects`` (``{name: object_to_world}``), ``priors``
    (``{kind: Path}``), ``masks`` (``{"camera" | "lidar": Path}``, pixels and
    beams the fit leaves out, see :mod:`mi_invrgbl.fit.observations`),
    ``extra``. ``camera_to_world_mitsuba`` is the
    sensor's ``to_world`` (``camera_to_world @ diag(-1, -1, 1, 1)``).
``ObjectRecord``
    ``name`` (the shape id, ``object_<track>``), ``track_id``, ``kind``,
    ``size_hwl`` (height, width, length in metres), ``moving``, ``ply``
    (Path), ``extra``. Object frame: origin at the box centre, x forward
    (along the length), y left, z up.

Every number read must be finite, and a record that is not is refused with
one :class:`~mi_invrgbl.errors.UserError` naming the file and the entry.
Writing refuses NaN and infinity as well (standard JSON has neither, and
Python's ``json`` would otherwise write the non-standard ``NaN``):
:func:`write_json` is the one writer of the scene's JSON files.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import json
import math
import os
from pathlib import Path

import numpy as np

from ..errors import UserError
from ..outdir import atomic_write_text

FORMAT = "mi-invrgbl-frames/1"
#: Mitsuba camera (x left, y up, z forward) from dataset camera (x right, y down, z forward)
CAMERA_FLIP = np.diag([-1.0, -1.0, 1.0, 1.0])


def _matrix(value, where: str) -> np.ndarray:
    try:
        m = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        raise UserError(f"{where}: not a 4x4 matrix of numbers") from None
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise UserError(f"{where}: not a finite 4x4 matrix (shape {m.shape})")
    return m


def _number(value, where: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise UserError(f"{where}: not a number ({value!r})") from None
    if not math.isfinite(v):
        raise UserError(f"{where}: not a finite number ({value!r})")
    return v


def _reject_constant(name):
    """``json.loads`` hook: Python reads NaN / Infinity, standard JSON has neither."""
    raise ValueError(f"non-standard JSON constant {name}")


def _non_finite(value, where: str):
    """Where in a JSON-bound value a NaN or infinity sits (None if nowhere)."""
    if isinstance(value, dict):
        for k, v in value.items():
            found = _non_finite(v, f"{where}.{k}")
            if found:
                return found
    elif isinstance(value, (list, tuple)):
        for k, v in enumerate(value):
            found = _non_finite(v, f"{where}[{k}]")
            if found:
                return found
    elif isinstance(value, (float, np.floating)) and not math.isfinite(float(value)):
        return f"{where} = {float(value)}"
    return None


def json_safe(value, pos_inf=None):
    """``value`` made writable by :func:`write_json`: NaN and -inf become
    null, +inf becomes ``pos_inf`` (default null), numpy scalars and arrays
    Python numbers and lists. A score that could not be computed (no frames,
    a diverged fit) is then written as null instead of the non-standard
    ``NaN`` that other JSON readers refuse."""
    if isinstance(value, dict):
        return {k: json_safe(v, pos_inf) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v, pos_inf) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist(), pos_inf)
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, (float, np.floating)):
        v = float(value)
        if math.isfinite(v):
            return v
        return pos_inf if v > 0 else None
    return value


def write_json(path, data, indent=1) -> Path:
    """Write ``data`` as standard JSON to ``path`` atomically (temp file, then
    rename). NaN or infinity anywhere is refused with one error naming the
    file and the entry, and nothing is written."""
    path = Path(path)
    where = _non_finite(data, path.name)
    if where is not None:
        raise UserError(f"{path}: refusing to write a non-finite number ({where})")
    text = json.dumps(data, indent=indent, allow_nan=False, default=_json_default)
    return atomic_write_text(path, text)


def _json_default(value):
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.floating):
        return float(value)
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def _list(m) -> list:
    return [[float(v) for v in row] for row in np.asarray(m, np.float64)]


@dataclass
class CameraInfo:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    extra: dict = field(default_factory=dict)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    def to_json(self) -> dict:
        return {"width": self.width, "height": self.height, "fx": self.fx,
                "fy": self.fy, "cx": self.cx, "cy": self.cy, **self.extra}


@dataclass
class LidarInfo:
    beams: int
    azimuth_steps: int
    elevations_deg: list
    intensity: str = "raw"     # 'raw' or 'reflectivity'
    extra: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        return {"beams": self.beams, "azimuth_steps": self.azimuth_steps,
                "elevations_deg": [float(e) for e in self.elevations_deg],
                "intensity": self.intensity, **self.extra}


@dataclass
class ObjectRecord:
    name: str
    track_id: int
    kind: str
    size_hwl: list
    moving: bool
    ply: Path
    extra: dict = field(default_factory=dict)


@dataclass
class FrameRecord:
    index: int
    time: float
    held_out: bool
    camera: str
    lidar: str
    image: Path | None
    lidar_scan: Path | None
    points: Path | None
    camera_to_world: np.ndarray
    lidar_to_world: np.ndarray
    objects: dict = field(default_factory=dict)   # name -> (4, 4) object -> world
    priors: dict = field(default_factory=dict)    # kind -> Path
    masks: dict = field(default_factory=dict)     # "camera" / "lidar" -> Path (255 = exclude)
    extra: dict = field(default_factory=dict)

    @property
    def camera_to_world_mitsuba(self) -> np.ndarray:
        """The camera sensor's ``to_world`` (Mitsuba's camera frame)."""
        return self.camera_to_world @ CAMERA_FLIP


_FRAME_KEYS = {"index", "time", "held_out", "camera", "lidar", "image", "lidar_scan",
               "points", "camera_to_world", "lidar_to_world", "objects", "priors",
               "masks"}
_TOP_KEYS = {"format", "source", "camera", "lidar", "objects", "ground_truth", "frames"}


@dataclass(eq=False)
class Frames:
    """The contents of ``frames.json`` (see the module docstring)."""

    path: Path
    source: str | None
    camera: CameraInfo
    lidar: LidarInfo
    objects: dict                 # name -> ObjectRecord, ordered as in the file
    ground_truth: Path | None
    frames: list                  # FrameRecord per frame
    extra: dict = field(default_factory=dict)

    def __post_init__(self):
        self.path = Path(self.path).absolute()
        self.extra = dict(self.extra or {})

    @property
    def root(self) -> Path:
        """The folder of frames.json (paths in the file are relative to it)."""
        return self.path.parent

    # -- sequence protocol ----------------------------------------------
    def __len__(self):
        return len(self.frames)

    def __getitem__(self, i) -> FrameRecord:
        return self.frames[i]

    def __iter__(self):
        return iter(self.frames)

    def train_indices(self) -> list:
        return [f.index for f in self.frames if not f.held_out]

    def held_out_indices(self) -> list:
        return [f.index for f in self.frames if f.held_out]

    def moving_objects(self) -> list:
        return [name for name, o in self.objects.items() if o.moving]

    # -- loading ---------------------------------------------------------
    @staticmethod
    def find(path) -> Path:
        """frames.json for a scene.xml, a folder or the file itself. For a
        scene in a sub-folder without its own frames.json (``DIR/fit/``) the
        parent folder's is used."""
        p = Path(path)
        if p.is_dir():
            candidates = [p / "frames.json"]
        elif p.suffix.lower() == ".json":
            candidates = [p]
        else:
            candidates = [p.parent / "frames.json", p.parent.parent / "frames.json"]
        for c in candidates:
            if c.is_file():
                return c
        raise UserError(f"{candidates[0]}: frames.json not found (written by "
                        "'mi-invrgbl import' next to scene.xml)")

    @classmethod
    def load(cls, path) -> "Frames":
        jpath = cls.find(path)
        try:
            data = json.loads(jpath.read_text(), parse_constant=_reject_constant)
        except (json.JSONDecodeError, ValueError) as exc:
            raise UserError(f"{jpath}: not valid JSON ({exc})") from None
        if not isinstance(data, dict) or data.get("format") != FORMAT:
            raise UserError(f"{jpath}: not a {FORMAT} file "
                            f"(format = {data.get('format') if isinstance(data, dict) else None!r})")
        root = jpath.parent.absolute()

        def rel(value):
            if value is None:
                return None
            return Path(os.path.normpath(root / value))

        try:
            c = dict(data["camera"])
            camera = CameraInfo(int(c.pop("width")), int(c.pop("height")),
                                *(_number(c.pop(k), f"{jpath}, camera.{k}")
                                  for k in ("fx", "fy", "cx", "cy")), extra=c)
            if camera.width < 1 or camera.height < 1 or camera.fx <= 0:
                raise UserError(f"{jpath}: camera: width, height and fx must be positive")
            li = dict(data["lidar"])
            lidar = LidarInfo(int(li.pop("beams")), int(li.pop("azimuth_steps")),
                              [_number(e, f"{jpath}, lidar.elevations_deg")
                               for e in li.pop("elevations_deg")],
                              str(li.pop("intensity", "raw")), extra=li)
            objects = {}
            for name, o in (data.get("objects") or {}).items():
                o = dict(o)
                objects[name] = ObjectRecord(
                    name=name, track_id=int(o.pop("track_id")), kind=str(o.pop("kind", "")),
                    size_hwl=[_number(v, f"{jpath}, objects.{name}.size_hwl")
                              for v in o.pop("size_hwl", [0, 0, 0])],
                    moving=bool(o.pop("moving", True)),
                    ply=rel(o.pop("ply", f"{name}.ply")), extra=o)
            frames = []
            for k, f in enumerate(data["frames"]):
                where = f"{jpath}, frames[{k}]"
                frames.append(FrameRecord(
                    index=int(f["index"]), time=_number(f.get("time", 0.0), where + ".time"),
                    held_out=bool(f.get("held_out", False)),
                    camera=str(f.get("camera", "camera_%04d" % int(f["index"]))),
                    lidar=str(f.get("lidar", "lidar_%04d" % int(f["index"]))),
                    image=rel(f.get("image")), lidar_scan=rel(f.get("lidar_scan")),
                    points=rel(f.get("points")),
                    camera_to_world=_matrix(f["camera_to_world"], where + ".camera_to_world"),
                    lidar_to_world=_matrix(f["lidar_to_world"], where + ".lidar_to_world"),
                    objects={n: _matrix(m, f"{where}.objects.{n}")
                             for n, m in (f.get("objects") or {}).items()},
                    priors={n: rel(p) for n, p in (f.get("priors") or {}).items()},
                    masks={n: rel(p) for n, p in (f.get("masks") or {}).items()},
                    extra={kk: v for kk, v in f.items() if kk not in _FRAME_KEYS}))
        except KeyError as exc:
            raise UserError(f"{jpath}: missing key {exc.args[0]!r}") from None
        except (TypeError, ValueError, AttributeError) as exc:
            raise UserError(f"{jpath}: malformed entry ({exc})") from None
        indices = [f.index for f in frames]
        if len(set(indices)) != len(indices):
            raise UserError(f"{jpath}: frame indices repeat")
        gt = data.get("ground_truth")
        gt_dir = rel(gt["dir"]) if isinstance(gt, dict) and gt.get("dir") else None
        return cls(jpath, data.get("source"), camera, lidar, objects, gt_dir, frames,
                   extra={k: v for k, v in data.items() if k not in _TOP_KEYS})

    # -- saving ----------------------------------------------------------
    def to_json(self, root=None) -> dict:
        """The file's contents, paths relative to ``root`` (default: this
        file's folder)."""
        root = Path(root if root is not None else self.root).absolute()

        def rel(p):
            if p is None:
                return None
            return Path(os.path.relpath(Path(p).absolute(), root)).as_posix()

        objects = {}
        for name, o in self.objects.items():
            objects[name] = {"track_id": o.track_id, "kind": o.kind,
                             "size_hwl": [float(v) for v in o.size_hwl],
                             "moving": bool(o.moving), "ply": rel(o.ply), **o.extra}
        frames = []
        for f in self.frames:
            d = {"index": f.index, "time": float(f.time), "held_out": bool(f.held_out),
                 "camera": f.camera, "lidar": f.lidar, "image": rel(f.image),
                 "lidar_scan": rel(f.lidar_scan), "points": rel(f.points),
                 "camera_to_world": _list(f.camera_to_world),
                 "lidar_to_world": _list(f.lidar_to_world),
                 "objects": {n: _list(m) for n, m in f.objects.items()}}
            if f.priors:
                d["priors"] = {n: rel(p) for n, p in f.priors.items()}
            if f.masks:
                d["masks"] = {n: rel(p) for n, p in f.masks.items()}
            d.update(f.extra)
            frames.append(d)
        out = {"format": FORMAT, "source": self.source, "camera": self.camera.to_json(),
               "lidar": self.lidar.to_json(), "objects": objects}
        if self.ground_truth is not None:
            out["ground_truth"] = {"dir": str(Path(self.ground_truth).absolute())}
        out.update(self.extra)
        out["frames"] = frames
        return out

    def save(self, path=None) -> Path:
        """Write frames.json (atomically) to ``path`` (a file or a folder;
        default: where it was loaded from)."""
        path = Path(path) if path is not None else self.path
        if path.is_dir() or path.suffix.lower() != ".json":
            path = path / "frames.json"
        return write_json(path, self.to_json(path.parent))

    def object_to_world(self, i: int, name: str) -> np.ndarray | None:
        """Object ``name``'s pose at frame position ``i`` (None if unlisted)."""
        return self.frames[i].objects.get(name)
