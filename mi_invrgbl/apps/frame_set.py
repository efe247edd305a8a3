"""The frames of a scene: which camera renders frame i, and where things are then.

Three kinds of scene are understood, recognised by the files next to the
original XML:

``frames.json`` (an imported scene, or its fit in ``DIR/fit/``, which uses
``DIR/frames.json``; see ``docs/scene_format.md``)
    Frame ``i`` is rendered by the sensor ``camera_NNNN``; dynamic objects are
    placed with :func:`mi_invrgbl.scene.posing.set_frame`.
``trajectory.json`` (the synthetic street's ground truth, ``gt/scene_*.xml``)
    The XML holds frame 0; frame ``i`` moves its sensor to the recorded camera
    pose and the moving car (and its headlights at night) to theirs, with
    :func:`mi_invrgbl.scene.posing.place`.
neither (any other scene)
    Every camera sensor (not ``lidar``) is one frame, in file order.

Applications render edited copies of a scene, so the frames are looked up
beside the *original* file and applied to the loaded *edited* scene. Each
edited scene is written with a ``source.json`` naming its original, so the
output of one application is a valid input of the next (relight, then insert)
and keeps the original's frames, lamps and LiDAR.
"""

from __future__ import annotations

import dataclasses
import json
import os

import numpy as np

from ..errors import UserError
from ..scene.frames import CAMERA_FLIP, Frames
from ..scene.loading import is_lidar
from ..scene.posing import place, set_frame


@dataclasses.dataclass
class Frame:
    index: int          #: frame number (frames.json / trajectory index, or sensor order)
    sensor_id: str      #: id of the camera sensor that renders it ("" = by position)
    sensor_pos: int     #: position among scene.sensors() (plain scenes)

    @property
    def name(self) -> str:
        return "frame_%04d" % self.index


#: Written beside an edited scene: {"scene": the original scene it was made from}.
SOURCE_FILE = "source.json"


def origin_scene(scene_path: str) -> str:
    """The original scene an application's output was made from (or ``scene_path``)."""
    path = os.path.abspath(scene_path)
    for _ in range(32):   # a chain of edits; a loop would be a hand-made mistake
        source = os.path.join(os.path.dirname(path), SOURCE_FILE)
        if not os.path.isfile(source):
            break
        try:
            with open(source) as f:
                previous = json.load(f).get("scene")
        except (OSError, ValueError):
            break
        if not previous or os.path.abspath(previous) == path or not os.path.isfile(previous):
            break
        path = os.path.abspath(previous)
    return path


def write_origin(out_dir: str, scene_path: str) -> None:
    """Record which scene an edited copy in ``out_dir`` was made from."""
    with open(os.path.join(out_dir, SOURCE_FILE), "w") as f:
        json.dump({"scene": origin_scene(scene_path)}, f, indent=1)


def find_frames_json(scene_path: str) -> str | None:
    """``frames.json`` of a scene (beside it, or one folder up for ``DIR/fit/``), or None."""
    try:
        return str(Frames.find(origin_scene(scene_path)))
    except UserError:
        return None


def parse_selection(text: str | None, count: int) -> list[int]:
    """``--frames`` (``A``, ``A:B``, ``A:B:S``, python-slice semantics) -> positions."""
    if not text:
        return list(range(count))
    try:
        parts = [int(p) if p.strip() else None for p in text.split(":")]
    except ValueError:
        raise UserError("--frames: expected A, A:B or A:B:S, got '%s'" % text) from None
    if len(parts) == 1:
        idx = [parts[0]] if 0 <= parts[0] < count else []
    elif len(parts) <= 3:
        idx = list(range(count))[slice(*parts)]
    else:
        raise UserError("--frames: expected A, A:B or A:B:S, got '%s'" % text)
    if not idx:
        raise UserError("--frames %s selects no frame (the scene has %d)" % (text, count))
    return idx


class FrameSet:
    """Frames of a scene (see the module docstring) and how to pose each."""

    def __init__(self, scene_path: str, scene, selection: str | None = None):
        self.scene_path = origin_scene(scene_path)
        folder = os.path.dirname(self.scene_path)
        self.frames_json = find_frames_json(self.scene_path)
        self.trajectory_json = os.path.join(folder, "trajectory.json")
        self.lights_json = os.path.join(folder, "lights.json")
        sensors = list(scene.sensors())
        ids = [s.id() for s in sensors]
        self._params = None
        self.all = []
        if self.frames_json is not None:
            self.kind = "frames.json"
            self._read_frames_json(ids)
        if not self.all:   # not an imported scene, or not one of its sensors
            if os.path.isfile(self.trajectory_json) and "sensor" in ids:
                self.kind = "synthetic"
                self._read_trajectory(ids)
            else:
                self.kind = "sensors"
                self.all = [Frame(k, ids[k], k) for k, s in enumerate(sensors) if not is_lidar(s)]
        if not self.all:
            raise UserError("%s: the scene has no camera sensor to render" % scene_path)
        self.frames = [self.all[k] for k in parse_selection(selection, len(self.all))]

    # ------------------------------------------------------------- reading
    def _read_frames_json(self, ids):
        self.records = Frames.load(self.frames_json)
        self._positions = {r.index: k for k, r in enumerate(self.records)}
        self.all = [Frame(r.index, r.camera, ids.index(r.camera))
                    for r in self.records if r.camera in ids]

    def _read_trajectory(self, ids):
        try:
            with open(self.trajectory_json) as f:
                self.info = json.load(f)
            self._cams = [np.asarray(m, np.float64) @ CAMERA_FLIP
                          for m in self.info["world_from_cam"]]
            self._cars = np.asarray(self.info.get("world_from_moving_car", []), np.float64)
        except (OSError, ValueError, KeyError) as exc:
            raise UserError("%s: cannot read (%s)" % (self.trajectory_json, exc)) from None
        self._headlights = []
        if os.path.isfile(self.lights_json):
            try:
                with open(self.lights_json) as f:
                    lights = json.load(f)
            except (OSError, ValueError) as exc:
                raise UserError("%s: cannot read (%s)" % (self.lights_json, exc)) from None
            count = len(lights.get("night", {}).get("headlights", []))
            self._headlights = ["headlight_%d" % k for k in range(count)]
        self.all = [Frame(i, "sensor", ids.index("sensor")) for i in range(len(self._cams))]

    # ------------------------------------------------------------- posing
    def apply(self, scene, frame: Frame):
        """Put ``scene`` into the state of ``frame``; returns the sensor that renders it."""
        sensor = scene.sensors()[frame.sensor_pos]
        if self.kind == "synthetic":
            params = self._parameters(scene)
            poses = {"sensor": self._cams[frame.index]}
            loaded = {}
            if len(self._cars) and "moving_car.vertex_positions" in params:
                # The car and its headlights were loaded at the car's frame-0 pose.
                for name in ["moving_car"] + [h for h in self._headlights
                                              if h + ".to_world" in params]:
                    poses[name], loaded[name] = self._cars[frame.index], self._cars[0]
            place(scene, poses, loaded, params)
        elif self.kind == "frames.json" and self.records.objects:
            set_frame(scene, self.records, self._positions[frame.index])
        return sensor

    def _parameters(self, scene):
        import mitsuba as mi
        if self._params is None:
            self._params = mi.traverse(scene)
        return self._params

    # ------------------------------------------------------------ queries
    def camera_to_world(self, scene, frame: Frame) -> np.ndarray:
        """``to_world`` of the frame's camera (Mitsuba convention: +z forward, +y up)."""
        if self.kind == "synthetic":
            return np.asarray(self._cams[frame.index])
        sensor = scene.sensors()[frame.sensor_pos]
        return np.array(sensor.world_transform().matrix, np.float64).reshape(4, 4)

    def lidar_poses(self, scene) -> list[tuple[int, np.ndarray]]:
        """(frame index, world_from_lidar) of the scene's own LiDAR, per selected frame."""
        if self.kind == "frames.json":
            return [(f.index, self.records[self._positions[f.index]].lidar_to_world)
                    for f in self.frames]
        if self.kind == "synthetic" and "world_from_velo" in self.info:
            return [(f.index, np.asarray(self.info["world_from_velo"][f.index], np.float64))
                    for f in self.frames]
        return [(k, np.array(s.world_transform().matrix, np.float64).reshape(4, 4))
                for k, s in enumerate(s for s in scene.sensors() if is_lidar(s))]
