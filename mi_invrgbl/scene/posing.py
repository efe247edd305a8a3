"""Moving the parts of a loaded scene: the one way objects are posed per frame.

:func:`place` is the single function that moves things in a loaded Mitsuba
scene, whoever asks: the frames of an imported scene (:func:`set_frame`),
the synthetic street's moving car, its headlights and its camera, an object
inserted along a ``--track``, the evaluation's frames. A pose is a 4x4
``world_from_object`` matrix (rotation, translation, optionally a uniform
scale). For each named node, ``place`` applies ``target @ inv(now)`` to the
node's parameters in place:

* ``gaussians`` shapes: ``data`` (centres, scales, quaternions x y z w) and
  ``normal``;
* meshes: ``vertex_positions`` and ``vertex_normals``;
* anything else with a ``to_world`` (sensors, emitters such as spot lights,
  analytic shapes).

Transforming in place, rather than rewriting from stored local coordinates,
keeps parameter edits made in between (an optimiser step). The pose "now" of
each node is tracked per scene: the first time a node is placed it is
``loaded[name]`` (the pose it was loaded at, i.e. its XML ``to_world``), or
its current ``to_world`` parameter, or the identity.

Parameters are written through ``mi.traverse(scene)``, never
``mi.traverse(shape)``: with Mitsuba 3.9.1, updating a shape's own
parameters leaves the scene's acceleration structure at the old bounds, and
rays keep hitting the old positions (measured: max pixel error 0.73 against
the object loaded at its new pose; 0.001 through the scene's parameters).
Updating in place also keeps Dr.Jit's compiled kernels valid, and the
``invrgbl`` integrator notices the new geometry (its visibility cache is
keyed on the parameter arrays).
"""

from __future__ import annotations

import weakref

import numpy as np

from ..errors import UserError
from .frames import Frames

# id(scene) -> (weakref or scene, {node name: current world_from_object})
_placed: dict = {}


def _tracked(scene) -> dict:
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


def reset_tracking(scene) -> None:
    """Forget where :func:`place` put this scene's nodes (call after reloading
    parameters that put them back where they were loaded)."""
    _placed.pop(id(scene), None)


def _split(m):
    """(rotation, uniform scale, translation) of a similarity transform."""
    m = np.asarray(m, np.float64)
    lin = m[:3, :3]
    det = np.linalg.det(lin)
    if not det > 1e-12:
        raise UserError("pose: the 3x3 part is singular or mirrored (det %.3g)" % det)
    scale = float(np.cbrt(det))
    return lin / scale, scale, m[:3, 3]


def _quat_mul(a, b):
    """Hamilton product of (N, 4) quaternions stored x y z w."""
    ax, ay, az, aw = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bx, by, bz, bw = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return np.stack([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz], axis=-1)


def rotation_to_quat_xyzw(R) -> np.ndarray:
    from ..physics.gaussian_ply import matrix_to_quaternion
    q = matrix_to_quaternion(np.asarray(R, np.float64)[None])[0]  # w x y z
    return np.array([q[1], q[2], q[3], q[0]])


def _read(params, key) -> np.ndarray:
    return np.array(params[key], np.float64)


def _write(params, key, values) -> None:
    """Assign ``values`` to ``params[key]`` in the parameter's own type and
    shape (a flat ``Float`` for ``data``/``normal``, a tensor elsewhere)."""
    old = params[key]
    params[key] = type(old)(np.asarray(values, np.float32).reshape(tuple(old.shape)))


def to_world_of(params, name: str) -> np.ndarray | None:
    """The current ``to_world`` of a node (None if it has none)."""
    key = name + ".to_world"
    if key not in params:
        return None
    m = np.array(params[key].matrix, np.float64)
    return m.reshape(4, 4, -1)[..., 0] if m.ndim == 3 else m.reshape(4, 4)


def transform_node(params, name: str, delta) -> bool:
    """Apply the 4x4 similarity ``delta`` to node ``name``'s parameters
    (without ``params.update()``). False if the node has nothing to move."""
    import mitsuba as mi
    delta = np.asarray(delta, np.float64)
    R, s, t = _split(delta)
    if name + ".data" in params:                      # gaussians
        data = _read(params, name + ".data").reshape(-1, 10)
        data[:, :3] = (s * (R @ data[:, :3].T)).T + t     # not data @ R.T: slow in numpy
        data[:, 3:6] *= s
        q = rotation_to_quat_xyzw(R)
        qn = _quat_mul(np.broadcast_to(q, data[:, 6:10].shape), data[:, 6:10])
        data[:, 6:10] = qn / np.linalg.norm(qn, axis=1, keepdims=True)
        _write(params, name + ".data", data)
        if name + ".normal" in params:
            n = _read(params, name + ".normal").reshape(-1, 3)
            _write(params, name + ".normal", (R @ n.T).T)
        return True
    if name + ".vertex_positions" in params:          # meshes
        v = _read(params, name + ".vertex_positions").reshape(-1, 3)
        _write(params, name + ".vertex_positions", (s * (R @ v.T)).T + t)
        key = name + ".vertex_normals"
        if key in params and dr_width(params[key]):
            n = _read(params, key).reshape(-1, 3)
            _write(params, key, (R @ n.T).T)
        return True
    now = to_world_of(params, name)
    if now is not None:                               # sensors, emitters, analytic shapes
        old = params[name + ".to_world"]
        params[name + ".to_world"] = type(old)(mi.ScalarMatrix4f((delta @ now).tolist()))
        return True
    return False


def dr_width(value) -> int:
    import drjit as dr
    return dr.width(value)


def place(scene, poses: dict, loaded: dict | None = None, params=None) -> None:
    """Move nodes of a loaded scene to new ``world_from_object`` poses.

    ``poses``: ``{node id: 4x4}``. ``loaded``: the pose each node was loaded
    at, used the first time it is placed (default: its ``to_world``
    parameter, else the identity). ``params``: the scene's
    ``mi.traverse(scene)`` if the caller holds one (default: a fresh one, so
    that parameters replaced elsewhere, as an optimiser does, are seen). A
    node the scene lacks, or one with nothing to move, is refused with a
    :class:`~mi_invrgbl.errors.UserError`.
    """
    import mitsuba as mi
    if not poses:
        return
    params = params if params is not None else mi.traverse(scene)
    current = _tracked(scene)
    changed = False
    for name, target in poses.items():
        target = np.asarray(target, np.float64)
        if target.shape != (4, 4) or not np.all(np.isfinite(target)):
            raise UserError("pose of '%s': not a finite 4x4 matrix" % name)
        now = current.get(name)
        if now is None:
            now = (loaded or {}).get(name)
        if now is None:
            now = to_world_of(params, name)
        if now is None:
            now = np.eye(4)
        delta = target @ np.linalg.inv(np.asarray(now, np.float64))
        if not np.allclose(delta, np.eye(4), atol=1e-9):
            if not transform_node(params, name, delta):
                raise UserError("'%s' cannot be moved: the scene has no Gaussians, mesh or "
                                "to_world under that id" % name)
            changed = True
        current[name] = target
    if changed:
        params.update()


def _find(items, name):
    for item in items:
        if item.id() == name:
            return item
    return None


def set_frame(scene, frames: Frames, i: int):
    """Place the dynamic objects of ``frames`` for frame position ``i``.

    Moves every object of ``frames.objects`` present in the scene (shape id
    = object name; one removed by editing the XML is skipped) to its pose at
    frame ``i`` (a frame listing no pose for an object leaves it where it
    is). Objects start at frame 0's pose, the ``to_world`` the importer
    wrote. Returns ``(camera_sensor, lidar_sensor)`` of frame ``i`` (None
    where the scene lacks one).
    """
    if not 0 <= i < len(frames):
        raise IndexError(f"frame {i} out of range (0..{len(frames) - 1})")
    record = frames[i]
    shapes = {s.id() for s in scene.shapes()}
    poses = {name: record.objects[name] for name in frames.objects
             if name in record.objects and name in shapes}
    loaded = {name: frames[0].objects.get(name, pose) for name, pose in poses.items()}
    place(scene, poses, loaded)
    return _find(scene.sensors(), record.camera), _find(scene.sensors(), record.lidar)
