"""The per-frame side of an imported scene: ``frames.json`` and ``set_frame``.

See ``docs/scene_format.md`` for the files. This module reads (and writes)
``frames.json`` and places dynamic objects for a frame::

    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    import mi_invrgbl
    from mi_invrgbl.scene_graph import Frames, set_frame

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
    (``{kind: Path}``), ``extra``. ``camera_to_world_mitsuba`` is the
    sensor's ``to_world`` (``camera_to_world @ diag(-1, -1, 1, 1)``).
``ObjectRecord``
    ``name`` (the shape id, ``object_<track>``), ``track_id``, ``kind``,
    ``size_hwl`` (height, width, length in metres), ``moving``, ``ply``
    (Path), ``extra``. Object frame: origin at the box centre, x forward
    (along the length), y left, z up.

``set_frame(scene, frames, i)`` moves every dynamic object's Gaussians
(shape id = object name) from where they are now to their pose at frame
``i``: the shapes' ``data`` (centres, rotations) and ``normal`` parameters
are transformed in place by ``pose_i @ inv(pose_now)``, so parameter edits
made in between (an optimiser step) are kept. The pose "now" is tracked per
scene, starting at frame 0's pose (the ``to_world`` written in the XML). An
object missing from the scene (removed by editing the XML) is skipped; a
frame that lists no pose for an object leaves it where it is. Returns
``(camera_sensor, lidar_sensor)`` of frame ``i`` (``None`` where the scene
lacks one).
"""

from __future__ import annotations

from dataclasses import dataclass, field
import json
import os
from pathlib import Path
import weakref

import numpy as np

from .errors import UserError

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
    extra: dict = field(default_factory=dict)

    @property
    def camera_to_world_mitsuba(self) -> np.ndarray:
        """The camera sensor's ``to_world`` (Mitsuba's camera frame)."""
        return self.camera_to_world @ CAMERA_FLIP


_FRAME_KEYS = {"index", "time", "held_out", "camera", "lidar", "image", "lidar_scan",
               "points", "camera_to_world", "lidar_to_world", "objects", "priors"}
_TOP_KEYS = {"format", "source", "camera", "lidar", "objects", "ground_truth", "frames"}


class Frames:
    """The contents of ``frames.json`` (see the module docstring)."""

    def __init__(self, path, source, camera, lidar, objects, ground_truth, frames,
                 extra=None):
        self.path = Path(path).absolute()
        self.root = self.path.parent
        self.source = source
        self.camera = camera
        self.lidar = lidar
        self.objects = objects
        self.ground_truth = ground_truth
        self.frames = frames
        self.extra = dict(extra or {})

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
            data = json.loads(jpath.read_text())
        except json.JSONDecodeError as exc:
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
                                float(c.pop("fx")), float(c.pop("fy")),
                                float(c.pop("cx")), float(c.pop("cy")), extra=c)
            li = dict(data["lidar"])
            lidar = LidarInfo(int(li.pop("beams")), int(li.pop("azimuth_steps")),
                              [float(e) for e in li.pop("elevations_deg")],
                              str(li.pop("intensity", "raw")), extra=li)
            objects = {}
            for name, o in (data.get("objects") or {}).items():
                o = dict(o)
                objects[name] = ObjectRecord(
                    name=name, track_id=int(o.pop("track_id")), kind=str(o.pop("kind", "")),
                    size_hwl=[float(v) for v in o.pop("size_hwl", [0, 0, 0])],
                    moving=bool(o.pop("moving", True)),
                    ply=rel(o.pop("ply", f"{name}.ply")), extra=o)
            frames = []
            for k, f in enumerate(data["frames"]):
                where = f"{jpath}, frames[{k}]"
                frames.append(FrameRecord(
                    index=int(f["index"]), time=float(f.get("time", 0.0)),
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
                    extra={kk: v for kk, v in f.items() if kk not in _FRAME_KEYS}))
        except KeyError as exc:
            raise UserError(f"{jpath}: missing key {exc.args[0]!r}") from None
        except (TypeError, ValueError) as exc:
            raise UserError(f"{jpath}: malformed entry ({exc})") from None
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
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".part")
        tmp.write_text(json.dumps(self.to_json(path.parent), indent=1))
        os.replace(tmp, path)
        return path

    def object_to_world(self, i: int, name: str) -> np.ndarray | None:
        """Object ``name``'s pose at frame position ``i`` (None if unlisted)."""
        return self.frames[i].objects.get(name)


# ----------------------------------------------------------------------------
# Placing objects for a frame
# ----------------------------------------------------------------------------

# id(scene) -> (weakref or scene, {object name: current object->world pose})
_placed: dict = {}


def _state(scene) -> dict:
    key = id(scene)
    entry = _placed.get(key)
    if entry is not None:
        ref, poses = entry
        alive = ref() if isinstance(ref, weakref.ref) else ref
        if alive is scene:
            return poses
    try:
        ref = weakref.ref(scene, lambda _r, key=key: _placed.pop(key, None))
    except TypeError:
        ref = scene  # not weak-referenceable: keep it (scenes are few)
    poses = {}
    _placed[key] = (ref, poses)
    return poses


def _find_shape(scene, name):
    for shape in scene.shapes():
        if shape.id() == name:
            return shape
    return None


def _find_sensor(scene, name):
    for sensor in scene.sensors():
        if sensor.id() == name:
            return sensor
    return None


def _quat_mul(a, b):
    """Hamilton product of (N, 4) quaternions stored x y z w."""
    ax, ay, az, aw = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bx, by, bz, bw = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return np.stack([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz], axis=-1)


def _rotation_to_quat_xyzw(R) -> np.ndarray:
    from .physics.gaussian_ply import matrix_to_quaternion
    q = matrix_to_quaternion(np.asarray(R, np.float64)[None])[0]  # w x y z
    return np.array([q[1], q[2], q[3], q[0]])


class _ShapeParams:
    """The scene-level parameters of one shape under its own key names.

    Updating through ``mi.traverse(shape)`` changes the shape but not the
    scene's acceleration structure (Mitsuba 3.9.1): rays would still hit the
    old positions. Going through ``mi.traverse(scene)`` rebuilds it.
    """

    def __init__(self, scene_params, name):
        self.p, self.name = scene_params, name

    def __contains__(self, key):
        return self.name + "." + key in self.p

    def __getitem__(self, key):
        return self.p[self.name + "." + key]

    def __setitem__(self, key, value):
        self.p[self.name + "." + key] = value

    def update(self):
        self.p.update()


def transform_gaussians(shape, delta: np.ndarray, scene=None) -> None:
    """Apply a rigid 4x4 transform to a ``gaussians`` shape's parameters
    (pass ``scene`` so that its acceleration structure follows)."""
    import mitsuba as mi

    params = _ShapeParams(mi.traverse(scene), shape.id()) if scene is not None \
        else mi.traverse(shape)
    data = np.array(params["data"], np.float64).reshape(-1, 10)
    R, t = delta[:3, :3], delta[:3, 3]
    data[:, :3] = (R @ data[:, :3].T).T + t     # not data @ R.T: slow in numpy
    q = _rotation_to_quat_xyzw(R)
    qn = _quat_mul(np.broadcast_to(q, data[:, 6:10].shape), data[:, 6:10])
    data[:, 6:10] = qn / np.linalg.norm(qn, axis=1, keepdims=True)
    params["data"] = type(params["data"])(data.astype(np.float32).reshape(params["data"].shape))
    if "normal" in params:
        n = (R @ np.array(params["normal"], np.float64).reshape(-1, 3).T).T
        params["normal"] = type(params["normal"])(
            n.astype(np.float32).reshape(params["normal"].shape))
    params.update()


def set_frame(scene, frames: Frames, i: int):
    """Place the dynamic objects for frame position ``i`` (see module docstring).

    Returns ``(camera_sensor, lidar_sensor)`` of that frame (None if absent).
    """
    if not 0 <= i < len(frames):
        raise IndexError(f"frame {i} out of range (0..{len(frames) - 1})")
    record = frames[i]
    current = _state(scene)
    for name in frames.objects:
        target = record.objects.get(name)
        if target is None:
            continue
        shape = _find_shape(scene, name)
        if shape is None:
            continue
        now = current.get(name)
        if now is None:
            now = frames[0].objects.get(name, target)
        delta = target @ np.linalg.inv(now)
        if not np.allclose(delta, np.eye(4), atol=1e-9):
            transform_gaussians(shape, delta, scene)
        current[name] = target
    return _find_sensor(scene, record.camera), _find_sensor(scene, record.lidar)


def reset_tracking(scene) -> None:
    """Forget where ``set_frame`` placed this scene's objects (call after
    reloading parameters that put them back at frame 0)."""
    _placed.pop(id(scene), None)
