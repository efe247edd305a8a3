"""Tracked objects for the import: which move, their per-frame poses, their
LiDAR points and their initial Gaussians.

Object frame (what ``object_<track>.ply`` and the poses in ``frames.json``
use): origin at the centre of the 3D box, x forward (along the length, the
heading), y left, z up. The box spans ``[-l/2, l/2] x [-w/2, w/2] x
[-h/2, h/2]``. KITTI tracking labels give the box's *bottom* centre in
camera coordinates and a rotation about the camera's y axis, with the KITTI
box frame x = heading, y = down, z = x cross y; so

    world_from_object = world_from_cam0 @ cam_from_kitti_box @ KITTI_BOX_FROM_OBJECT(h)

with ``KITTI_BOX_FROM_OBJECT(h)`` mapping (x, y, z) -> (x, -z - h/2, y)
(see :func:`kitti_box_from_object`).

Frames where an object is not labelled get a pose too: linear interpolation
(translation; slerp for rotation) between the nearest labelled frames, and
the nearest labelled pose before the first / after the last label ("hold";
tracks registered from the LiDAR instead move on at their end's velocity,
see :func:`fill_poses`).
``labelled`` records which frames carried a label.

An object is *moving* when its box centre travels more than
``MOVING_THRESHOLD`` metres (largest distance from its first labelled
position, in the world frame) over the imported frames.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .init_gaussians import matrix_to_quaternion_fast

#: metres of travel above which a tracked object counts as moving
MOVING_THRESHOLD = 0.5
#: LiDAR points within this height above the box bottom stay in the background
#: (the road under a car)
GROUND_CLEARANCE = 0.15
#: horizontal / upward margin of the box when collecting an object's points
BOX_MARGIN = 0.25
#: How far above the top beam's hits a vehicle may rise (metres, object z): a
#: truck beside the car rises far above the LiDAR's top beam, which cuts its
#: points at about the sensor's height. The import extends such an object's
#: Gaussians this far up (:func:`extend_object_top`); the fit's sky mask keeps
#: the same headroom free of sky (``mi_invrgbl.fit.sky_mask``). 2 m covers a
#: 4 m truck seen from a car's roof.
OBJECT_HEADROOM = 2.0
#: A point counts as cut by the top beam within this many degrees of it.
TOP_BEAM_MARGIN_DEG = 0.6
#: Fewer cut points than this on an object is a stray return, not a cut top.
MIN_CUT_POINTS = 10


def kitti_box_from_object(h: float) -> np.ndarray:
    """Our object frame (centre, x fwd, y left, z up) -> KITTI's box frame
    (bottom centre, x heading, y down, z = x cross y)."""
    T = np.eye(4)
    T[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]
    T[1, 3] = -h / 2.0
    return T


def _quat_to_matrix(q):
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _slerp(q0, q1, t):
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + t * (q1 - q0)
    else:
        a = np.arccos(d)
        q = (np.sin((1 - t) * a) * q0 + np.sin(t * a) * q1) / np.sin(a)
    return q / np.linalg.norm(q)


#: Labelled frames at each end of a track whose positions give its velocity
#: for :func:`fill_poses`'s ``extrapolate``.
VELOCITY_FRAMES = 5


def _end_velocity(positions, centres, last: bool) -> np.ndarray:
    """Least-squares velocity (metres per frame) over the first or last
    :data:`VELOCITY_FRAMES` labelled positions (zero from a single one)."""
    sl = slice(-VELOCITY_FRAMES, None) if last else slice(0, VELOCITY_FRAMES)
    f, c = np.asarray(positions[sl], np.float64), np.asarray(centres[sl], np.float64)
    if len(f) < 2:
        return np.zeros(3)
    f = f - f.mean()
    return (f[:, None] * (c - c.mean(axis=0))).sum(axis=0) / float((f * f).sum())


def fill_poses(positions, poses, n_frames: int, extrapolate: bool = False) -> np.ndarray:
    """Poses for every frame 0..n_frames-1 from poses at (sorted) ``positions``:
    interpolated between labels; before the first and after the last, held
    -- or, with ``extrapolate``, moved on at the velocity of the track's
    end (heading held). A track registered from the LiDAR ends where the
    registration loses the object, not where the object stops: on the
    KITTI excerpt the truck cab beside the car, held after its track ended,
    was 0.4-0.5 m off every two frames in the images."""
    positions = np.asarray(positions, np.int64)
    poses = np.asarray(poses, np.float64)
    quats = matrix_to_quaternion_fast(poses[:, :3, :3])
    ends = {}
    if extrapolate:
        ends = {False: _end_velocity(positions, poses[:, :3, 3], last=False),
                True: _end_velocity(positions, poses[:, :3, 3], last=True)}
    out = np.empty((n_frames, 4, 4))
    for f in range(n_frames):
        k = int(np.searchsorted(positions, f))
        if k < len(positions) and positions[k] == f:
            out[f] = poses[k]
        elif k == 0:
            out[f] = poses[0]
            if ends:
                out[f, :3, 3] += (f - positions[0]) * ends[False]
        elif k == len(positions):
            out[f] = poses[-1]
            if ends:
                out[f, :3, 3] += (f - positions[-1]) * ends[True]
        else:
            a, b = positions[k - 1], positions[k]
            t = (f - a) / (b - a)
            T = np.eye(4)
            T[:3, :3] = _quat_to_matrix(_slerp(quats[k - 1], quats[k], t))
            T[:3, 3] = (1 - t) * poses[k - 1][:3, 3] + t * poses[k][:3, 3]
            out[f] = T
    return out


@dataclass
class ObjectTrack:
    """One tracked object over the imported frames."""
    name: str                 # shape id: object_<track>
    track_id: int
    kind: str
    size_hwl: np.ndarray      # (3,) height, width, length (median over labels)
    poses: np.ndarray         # (N, 4, 4) world_from_object for every imported frame
    labelled: np.ndarray      # (N,) bool: labelled in that frame
    displacement_m: float     # largest distance of the centre from its first labelled position
    moving: bool
    dynamic: bool             # gets its own gaussians node (moving, or --dynamic all)
    # filled while accumulating: LiDAR points in the object frame
    points: list = field(default_factory=list)      # (M, 3) arrays
    intensity: list = field(default_factory=list)   # (M,)
    distance: list = field(default_factory=list)    # (M,) metres from the sensor
    view: list = field(default_factory=list)        # (M, 3) unit point -> sensor, object frame
    elevation: list = field(default_factory=list)   # (M,) radians above the sensor's horizon

    @property
    def half_extent(self) -> np.ndarray:
        h, w, l = self.size_hwl
        return np.array([l / 2, w / 2, h / 2])

    def active(self, i: int) -> bool:
        """Whether frame ``i`` lies within the labelled span (labelled or
        interpolated), i.e. the object is known to be where ``poses[i]`` says."""
        lab = np.nonzero(self.labelled)[0]
        return lab.size > 0 and lab[0] <= i <= lab[-1]


def tracks_to_objects(tracks: dict, frame_numbers, mode: str = "moving",
                      threshold: float = MOVING_THRESHOLD) -> list:
    """KITTI tracks (from :func:`mi_invrgbl.io.kitti.read_tracking_labels`
    with world poses) -> :class:`ObjectTrack` per object labelled in at
    least one imported frame. ``mode``: 'moving' (only moving objects are
    dynamic), 'all' or 'none'."""
    if mode not in ("moving", "all", "none"):
        raise ValueError(f"unknown --dynamic mode {mode!r}")
    position = {int(f): i for i, f in enumerate(frame_numbers)}
    n = len(position)
    out = []
    for tid, tr in sorted(tracks.items()):
        if tr.poses_world is None:
            raise ValueError("tracks need world poses (read them with world_from_cam)")
        keep = [k for k, f in enumerate(tr.frames) if int(f) in position]
        if not keep:
            continue
        h = float(np.median(tr.dimensions[keep, 0]))
        w = float(np.median(tr.dimensions[keep, 1]))
        l = float(np.median(tr.dimensions[keep, 2]))
        poses = np.stack([tr.poses_world[k] @ kitti_box_from_object(tr.dimensions[k, 0])
                          for k in keep])
        pos = [position[int(tr.frames[k])] for k in keep]
        order = np.argsort(pos)
        pos = np.asarray(pos)[order]
        poses = poses[order]
        centres = poses[:, :3, 3]
        disp = float(np.linalg.norm(centres - centres[0], axis=1).max())
        moving = disp > threshold
        dynamic = mode == "all" or (mode == "moving" and moving)
        labelled = np.zeros(n, bool)
        labelled[pos] = True
        out.append(ObjectTrack(
            name=f"object_{tid}", track_id=int(tid), kind=str(tr.type),
            size_hwl=np.array([h, w, l]), poses=fill_poses(pos, poses, n),
            labelled=labelled, displacement_m=disp, moving=moving, dynamic=dynamic))
    return out


def in_box(points_obj: np.ndarray, half_extent, margin: float = BOX_MARGIN,
           ground_clearance: float = GROUND_CLEARANCE) -> np.ndarray:
    """Points (object frame) inside the box grown by ``margin`` sideways and
    upwards, excluding the ``ground_clearance`` above its bottom."""
    hx, hy, hz = half_extent
    p = points_obj
    return ((np.abs(p[:, 0]) <= hx + margin) & (np.abs(p[:, 1]) <= hy + margin)
            & (p[:, 2] >= -hz + ground_clearance) & (p[:, 2] <= hz + margin))


def box_surface_samples(half_extent, n: int, rng: np.random.Generator):
    """``n`` points uniformly on the box's sides and top (not its bottom, which
    rests on the road), with outward normals. Returns (points, normals)."""
    hx, hy, hz = (float(v) for v in half_extent)
    # faces: +x, -x, +y, -y, +z with their areas
    faces = [(0, +1, 4 * hy * hz), (0, -1, 4 * hy * hz), (1, +1, 4 * hx * hz),
             (1, -1, 4 * hx * hz), (2, +1, 4 * hx * hy)]
    area = np.array([f[2] for f in faces])
    which = rng.choice(len(faces), size=n, p=area / area.sum())
    pts = rng.uniform(-1, 1, (n, 3)) * np.array([hx, hy, hz])
    normals = np.zeros((n, 3))
    for k, (axis, sign, _) in enumerate(faces):
        sel = which == k
        pts[sel, axis] = sign * (hx, hy, hz)[axis]
        normals[sel, axis] = sign
    return pts, normals


def object_to_world_quaternion(T: np.ndarray) -> np.ndarray:
    """Rotation of a pose as a w-first quaternion (for reports)."""
    return matrix_to_quaternion_fast(T[None, :3, :3])[0]


def extend_object_top(points, normals, tangents, cut, headroom=OBJECT_HEADROOM,
                      cell=0.15, step=0.15):
    """Gaussian centres that continue an object's surfaces above the top beam.

    ``points`` (object frame, z up) are the object's Gaussian centres from
    its LiDAR points, ``cut`` marks those measured within
    :data:`TOP_BEAM_MARGIN_DEG` of the top beam. In each ``cell`` x ``cell``
    column of the object's footprint whose highest point was cut (the scan
    ended there, not the object), that point is repeated every ``step``
    metres up to ``headroom`` above it, with its normal and tangent -- the
    object counterpart of the import's wall extension. The cameras see
    these parts (a truck's tank, a bus's upper half); stage 1 of ``fit``
    makes the copies above the real roof transparent.

    Returns ``(centres, normals, tangents, seed index per new centre)``,
    empty when fewer than :data:`MIN_CUT_POINTS` points were cut.
    """
    points = np.asarray(points, np.float64).reshape(-1, 3)
    cut = np.asarray(cut, bool).reshape(-1)
    empty = (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64))
    if headroom <= 0 or int(cut.sum()) < MIN_CUT_POINTS:
        return empty
    keys = np.floor(points[:, :2] / cell).astype(np.int64)
    _, col = np.unique(keys, axis=0, return_inverse=True)
    col = col.ravel()
    zmax = np.full(int(col.max()) + 1, -np.inf)
    np.maximum.at(zmax, col, points[:, 2])
    top = np.nonzero(cut & (points[:, 2] >= zmax[col] - 1e-6))[0]
    if top.size == 0:
        return empty
    k = np.arange(1, int(round(headroom / step)) + 1)
    seeds = np.repeat(top, k.size)
    new = points[seeds].copy()
    new[:, 2] += np.tile(k * step, top.size)
    return (new, np.asarray(normals, np.float64)[seeds],
            np.asarray(tangents, np.float64)[seeds], seeds)
