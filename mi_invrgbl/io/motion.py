"""Moving objects found from the LiDAR alone (drives without tracking labels).

Steps, all in the world frame given by the ego poses:

ground
    Per sweep, points less than ``ground_clearance`` above the lowest point
    of their ``ground_cell`` x ``ground_cell`` column are the road; points
    more than ``max_height`` above it, nearer than ``min_range`` or farther
    than ``max_range`` are not considered (far sweeps are too sparse to
    compare).
free space
    A point of sweep i *moved* when other sweeps j (``compare`` frames
    before and after) looked straight through where it was: j's return in
    the point's direction (the nearest over a 3 x 3 neighbourhood of
    ``az_step`` x ``el_step`` bins) lies more than ``margin`` (+ 3 % of the
    range) behind it. A static point seen again gives a return at its own
    range; one hidden in j gives a nearer return: neither counts. A point
    is dynamic when at least half of the sweeps that could tell say so.
clusters
    A sweep's above-ground points, rasterised on a ``cell`` grid (x, y) and
    split into 8-connected components (OpenCV). A component with at least
    ``min_points`` moving points is a cluster when they make up at least
    ``MIN_SEED_FRACTION`` of it (the free-space test sees only the ends of a
    slow vehicle that left their space); otherwise its moving points alone
    are split into components (see :func:`clusters_of`).
tracks
    Clusters of consecutive sweeps joined by nearest predicted centroid
    (constant velocity, gate ``gate`` metres, gaps up to ``max_gap``
    sweeps); per frame a rigid motion (yaw + translation in x, y) by
    point-to-point ICP against the previous frame's cluster.
nodes or masks
    A track seen in at least ``min_frames`` sweeps whose ICP residual is at
    most ``max_residual`` becomes a rigid node (an
    :class:`~mi_invrgbl.io.objects.ObjectTrack` with per-frame poses and a
    box fitted to its accumulated points, heading along its travel); with
    ``follow`` (``import --follow-nodes``) it is then followed by
    registration into the sweeps before and after the track, where the
    vehicle stood or the free-space test saw only a fragment of it
    (:func:`follow_node`). Every
    other dynamic point is masked: the import writes per-frame masks (see
    :func:`write_masks`) so that a fit can exclude those pixels and returns
    from its losses instead of smearing them into the static background.
standing vehicles
    Vehicle-sized components with only a few moving points (a parked or
    queued car whose edges the free-space test misreads as the view of it
    changes) are tracked too, on grids down to ``MIN_CELL`` where a queue
    is one component (:func:`standing_candidates`); one that stays put over
    ``min_frames`` sweeps is static, and none of its points is masked
    (:func:`standing_vehicles`).

Mask files (next to the observations, one pair per frame ``NNNN``):

``observations/motion_NNNN.png``
    8-bit single channel, the size of ``image_NNNN.png``: 255 where the
    camera sees a moving thing that no node models, 0 elsewhere.
``observations/motion_lidar_NNNN.png``
    8-bit single channel, the size of ``lidar_NNNN.exr`` (rows = beams,
    columns = azimuth steps): 255 where the return came from such a thing.

Both are listed in ``frames.json`` (the frame's ``masks``), and ``fit``
leaves the masked pixels and returns out of its losses, validation scores
and initialisations (:mod:`mi_invrgbl.fit.observations`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import init_gaussians as ig
from .objects import ObjectTrack, fill_poses, in_box

#: A track's ``from`` in frames.json's ``tracks`` when this module found it
#: (its box is what the LiDAR saw of the object, not a label's).
FROM_LIDAR_MOTION = "LiDAR motion"


#: a cluster grown around moving points must be at least this share moving
MIN_SEED_FRACTION = 0.25
#: A vehicle-sized component with at least ``min_points`` moving points
#: making up at least this share (and less than MIN_SEED_FRACTION) may be a
#: vehicle standing in a queue (:func:`standing_candidates`)...
MIN_STANDING_FRACTION = 0.005
#: ...and components larger than a vehicle are split for them on grids of
#: half the cell, down to this (metres).
MIN_CELL = 0.1
#: metres: a cluster longer or wider (along its principal axes) is not one vehicle
MAX_LENGTH = 15.0
MAX_WIDTH = 3.5
#: A node is followed past the sweeps its moving points were found in
#: (:func:`follow_node`): candidate points are taken this far (metres)
#: around its box at the predicted pose...
FOLLOW_MARGIN = 0.4
#: ...and a sweep is the node's when its box, registered there, holds at
#: least this share of the median number of points its moving clusters
#: had (and ``min_points``). The free-space test sees a vehicle only while
#: it moves clearly: on the KITTI excerpt the truck ahead was tracked over
#: 17 of the 40 sweeps and the tanker beside the ego vehicle lost its last
#: two, and their poses beyond, moved on at the tracks' end velocity, put
#: them 1.0 m and 0.6 m past where the LiDAR saw them by the last sweep.
FOLLOW_MIN_SHARE = 0.3


def footprint(points) -> tuple:
    """(length, width) of points' x, y extent along their principal axes."""
    xy = np.asarray(points, np.float64)[:, :2]
    if len(xy) < 3:
        return 0.0, 0.0
    c = xy - xy.mean(axis=0)
    _, v = np.linalg.eigh(c.T @ c)
    proj = c @ v
    ext = np.ptp(proj, axis=0)
    return float(ext.max()), float(ext.min())


def vehicle_sized(points) -> bool:
    length, width = footprint(points)
    return length <= MAX_LENGTH and width <= MAX_WIDTH


@dataclass
class MotionOptions:
    min_range: float = 2.0
    max_range: float = 40.0
    ground_cell: float = 2.0
    ground_clearance: float = 0.3
    max_height: float = 4.5
    compare: tuple = (-6, -3, 3, 6)     # sweep offsets that test a point's free space
    az_step_deg: float = 0.25
    el_step_deg: float = 0.5
    margin: float = 0.5
    cell: float = 0.4
    min_points: int = 20
    gate: float = 2.0
    max_gap: int = 2
    min_frames: int = 5
    max_residual: float = 0.15
    max_yaw_step_deg: float = 3.0
    #: metres a track must travel to become a node (less: masked, or, for a
    #: vehicle tracked whole, standing still, :func:`standing_vehicles`).
    #: 0.3 made fragments of a car beside the KITTI excerpt's ego vehicle
    #: (0.39 m over 24 sweeps by their registration) a node; the one
    #: 30-minute fit of that import scored 21.33 dB held-out against 21.70
    #: (docs/measurements.md, "Settling the stages"). Tracked whole, that car stands.
    min_travel: float = 0.5
    track_id_base: int = 1000
    #: follow each node past its track by registration (:func:`follow_node`;
    #: ``import --follow-nodes``). Off by default: on the KITTI excerpt
    #: neither stage 1 at 800 steps (21.13 and 20.95 dB on the validation
    #: frames against 20.94 and 21.01) nor a 30-minute fit (21.70 against
    #: 21.81 dB by ``eval``, one run each) scored better with it (docs/measurements.md,
    #: "Nodes followed past their tracks").
    follow: bool = False


@dataclass
class Cluster:
    frame: int
    points: np.ndarray          # (N, 3) world
    point_index: np.ndarray     # (N,) index into the sweep

    @property
    def centroid(self):
        return self.points.mean(axis=0)


@dataclass
class MotionTrack:
    clusters: list = field(default_factory=list)
    motions: list = field(default_factory=list)   # world 4x4: first frame -> this frame
    residuals: list = field(default_factory=list)

    @property
    def frames(self):
        return [c.frame for c in self.clusters]


@dataclass
class MotionResult:
    objects: list                       # ObjectTrack, dynamic
    dynamic: list                       # per frame: (N_i,) bool over the sweep's points
    masked: list                        # per frame: (N_i,) bool, dynamic and in no node
    tracks: list                        # MotionTrack (all, modelled or not)
    modelled: list                      # bool per track
    standing: list = field(default_factory=list)  # MotionTrack: vehicles that stayed put
    stats: dict = field(default_factory=dict)


# ----------------------------------------------------------------------------
# Per-sweep helpers
# ----------------------------------------------------------------------------

def above_ground(local: np.ndarray, opts: MotionOptions) -> np.ndarray:
    """Points (sensor frame) that are neither road nor out of range/height."""
    r = np.hypot(local[:, 0], local[:, 1])
    cells = np.floor(local[:, :2] / opts.ground_cell).astype(np.int64)
    _, inv = np.unique(cells, axis=0, return_inverse=True)
    inv = inv.ravel()
    zmin = np.full(inv.max() + 1 if len(inv) else 0, np.inf)
    np.minimum.at(zmin, inv, local[:, 2])
    h = local[:, 2] - zmin[inv]
    return ((r >= opts.min_range) & (r <= opts.max_range) & (h > opts.ground_clearance)
            & (h < opts.max_height))


class _SphericalImage:
    """Nearest return per (elevation, azimuth) bin of one sweep, with the
    3 x 3 minimum for the free-space test."""

    def __init__(self, local, opts: MotionOptions):
        self.az = np.radians(opts.az_step_deg)
        self.el = np.radians(opts.el_step_deg)
        self.el0 = np.radians(-40.0)
        self.W = int(np.ceil(2 * np.pi / self.az))
        self.H = int(np.ceil(np.radians(60.0) / self.el))
        col, row, rng = self._bins(local)
        ok = (row >= 0) & (row < self.H)
        img = np.full(self.H * self.W, np.inf)
        np.minimum.at(img, row[ok] * self.W + col[ok], rng[ok])
        img = img.reshape(self.H, self.W)
        self.valid = np.isfinite(img)
        pad = np.pad(img, ((1, 1), (1, 1)), mode="wrap")
        pad[0], pad[-1] = np.inf, np.inf
        stack = [pad[1 + dy:self.H + 1 + dy, 1 + dx:self.W + 1 + dx]
                 for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
        self.nearest = np.min(stack, axis=0)

    def _bins(self, local):
        rng = np.linalg.norm(local, axis=1)
        az = np.arctan2(local[:, 1], local[:, 0]) % (2 * np.pi)
        el = np.arcsin(np.clip(local[:, 2] / np.maximum(rng, 1e-9), -1, 1))
        col = np.minimum((az / self.az).astype(np.int64), self.W - 1)
        row = np.floor((el - self.el0) / self.el).astype(np.int64)
        return col, row, rng

    def seen_through(self, local, margin):
        """(evidence, decided): the sweep looked past each point / had a
        return in its direction at all."""
        col, row, rng = self._bins(local)
        inside = (row >= 0) & (row < self.H)
        rowc = np.clip(row, 0, self.H - 1)
        decided = inside & self.valid[rowc, col]
        past = self.nearest[rowc, col] > rng + margin + 0.03 * rng
        return decided & past, decided


def dynamic_points(scans, poses, opts: MotionOptions | None = None):
    """Per sweep, a bool per point: it moved (see the module docstring).
    ``scans``: (N_i, 3) sensor-frame points; ``poses``: world_from_sensor."""
    opts = opts or MotionOptions()
    n = len(scans)
    images = [_SphericalImage(np.asarray(s, np.float64), opts) for s in scans]
    out = []
    for i, pts in enumerate(scans):
        pts = np.asarray(pts, np.float64)
        cand = np.nonzero(above_ground(pts, opts))[0]
        world = ig.transform_points(pts[cand], poses[i])
        votes = np.zeros(len(cand))
        decided = np.zeros(len(cand))
        for d in opts.compare:
            j = i + d
            if not 0 <= j < n:
                continue
            local_j = ig.transform_points(world, np.linalg.inv(poses[j]))
            ev, dec = images[j].seen_through(local_j, opts.margin)
            votes += ev
            decided += dec
        dyn = np.zeros(len(pts), bool)
        dyn[cand] = (decided > 0) & (votes >= 0.5 * np.maximum(decided, 1))
        out.append(dyn)
    return out


def _components(xy, cell):
    """8-connected components of points on an x, y grid of ``cell`` metres
    (one-cell gaps closed: LiDAR rings leave stripes on a vehicle's side)."""
    import cv2

    q = np.floor(xy / cell).astype(np.int64)
    q -= q.min(axis=0) - 1
    grid = np.zeros((int(q[:, 1].max()) + 2, int(q[:, 0].max()) + 2), np.uint8)
    grid[q[:, 1], q[:, 0]] = 255
    grid = cv2.dilate(grid, np.ones((3, 3), np.uint8))
    n, labels = cv2.connectedComponents(grid, connectivity=8)
    return n, labels[q[:, 1], q[:, 0]]


def _seeded_components(world_points, sub, seeds, cell, min_points):
    """Components (on a ``cell`` grid) of the points ``sub`` (indices) that
    hold at least ``min_points`` of ``seeds``: (indices, seed share) each."""
    n, lab = _components(world_points[sub, :2], cell)
    count = np.bincount(lab, minlength=n)
    seed_count = np.bincount(lab[seeds[sub]], minlength=n)
    return [(sub[lab == k], seed_count[k] / count[k])
            for k in np.nonzero(seed_count >= min_points)[0]]


def clusters_of(frame, world_points, index, seeds, opts: MotionOptions) -> list:
    """Clusters of a sweep's moving points. ``world_points``/``index``: the
    sweep's above-ground points; ``seeds``: which of them moved.

    The free-space test catches only the parts of a slow object that left
    the space it held (its leading and trailing ends), so a cluster is the
    whole connected component of above-ground points around the seeds,
    provided seeds make up at least ``MIN_SEED_FRACTION`` of it and it is
    vehicle-sized (``MAX_LENGTH`` x ``MAX_WIDTH``); otherwise (an object
    touching a wall) only the seeds' own vehicle-sized components. Moving
    points in no cluster stay masked."""
    if seeds.sum() < opts.min_points:
        return []
    out = []
    loose = np.zeros(len(world_points), bool)
    for sel, share in _seeded_components(world_points, np.arange(len(world_points)), seeds,
                                         opts.cell, opts.min_points):
        p = world_points[sel]
        if share >= MIN_SEED_FRACTION and vehicle_sized(p):
            out.append(Cluster(frame, p, index[sel]))
        else:
            loose[sel] |= seeds[sel]
    if loose.sum() >= opts.min_points:
        sub = np.nonzero(loose)[0]
        n2, lab2 = _components(world_points[sub, :2], opts.cell)
        for k in range(1, n2):
            sel = sub[lab2 == k]
            if len(sel) >= opts.min_points and vehicle_sized(world_points[sel]):
                out.append(Cluster(frame, world_points[sel], index[sel]))
    return out


def standing_candidates(frame, world_points, index, seeds, opts: MotionOptions) -> list:
    """Vehicle-sized components of a sweep's above-ground points that hold
    a few moving points: at least ``min_points``, a share from
    :data:`MIN_STANDING_FRACTION` up to :data:`MIN_SEED_FRACTION`. A
    component larger than a vehicle is split again on a grid of half the
    cell, down to :data:`MIN_CELL`: in a queue the vehicles of neighbouring
    lanes stand closer than a cell's closing, and on the KITTI excerpt the
    whole queue beside the ego vehicle (21 x 10 m) was one component at
    0.4 m. :func:`detect_motion` tracks these and unmasks the ones that
    stay put."""
    if seeds.sum() < opts.min_points:
        return []
    out = []
    pending = [(np.arange(len(world_points)), opts.cell)]
    while pending:
        sub, cell = pending.pop()
        for sel, share in _seeded_components(world_points, sub, seeds, cell, opts.min_points):
            if vehicle_sized(world_points[sel]):
                if MIN_STANDING_FRACTION <= share < MIN_SEED_FRACTION:
                    out.append(Cluster(frame, world_points[sel], index[sel]))
            elif cell / 2 >= MIN_CELL:
                pending.append((sel, cell / 2))
    return out


# ----------------------------------------------------------------------------
# Tracking
# ----------------------------------------------------------------------------

class _NearestXY:
    """Nearest neighbour (x, y) among fixed points: OpenCV FLANN KD-tree."""

    def __init__(self, dst):
        import cv2

        self.dst = np.ascontiguousarray(np.asarray(dst, np.float32)[:, :2])
        self.index = cv2.flann_Index(self.dst, dict(algorithm=1, trees=1))

    def __call__(self, src):
        q = np.ascontiguousarray(np.asarray(src, np.float32)[:, :2])
        idx, d2 = self.index.knnSearch(q, 1, params=dict(checks=32))
        return idx[:, 0].astype(np.int64), np.sqrt(np.maximum(d2[:, 0], 0.0)).astype(np.float64)


def icp_2d(src, dst, init_t, iters: int = 15, trim: float = 0.8, rotate: bool = True):
    """Rigid yaw + (x, y) translation taking ``src`` onto ``dst`` (trimmed
    point-to-point ICP; ``rotate=False``: translation only). Returns (4x4
    world transform, median residual)."""
    T = np.eye(4)
    T[:2, 3] = init_t[:2]
    sub_s = src[:: max(1, len(src) // 1500)]
    sub_d = dst[:: max(1, len(dst) // 5000)]
    nearest = _NearestXY(sub_d)
    res = np.inf
    for _ in range(iters):
        p = ig.transform_points(sub_s, T)
        idx, d = nearest(p)
        keep = d <= np.quantile(d, trim)
        a, b = p[keep, :2], sub_d[idx[keep], :2]
        ca, cb = a.mean(0), b.mean(0)
        H = (a - ca).T @ (b - cb)
        U, _, Vt = np.linalg.svd(H)
        R = Vt.T @ U.T
        if np.linalg.det(R) < 0:
            Vt[1] *= -1
            R = Vt.T @ U.T
        if not rotate:
            R = np.eye(2)
        step = np.eye(4)
        step[:2, :2] = R
        step[:2, 3] = cb - R @ ca
        T = step @ T
        res = float(np.median(d))
    p = ig.transform_points(sub_s, T)
    res = float(np.median(nearest(p)[1]))
    return T, res


def _velocity(track: MotionTrack) -> np.ndarray:
    """World velocity (per sweep) of the first cluster's centroid over the
    last registered step."""
    c = track.clusters[0].centroid
    k = len(track.motions) - 1
    p1 = track.motions[k][:3, :3] @ c + track.motions[k][:3, 3]
    p0 = track.motions[k - 1][:3, :3] @ c + track.motions[k - 1][:3, 3]
    return (p1 - p0) / max(track.clusters[k].frame - track.clusters[k - 1].frame, 1)


def track_clusters(clusters_per_frame, opts: MotionOptions) -> list:
    """Greedy nearest-centroid association with constant-velocity prediction."""
    tracks, active = [], []
    for frame_clusters in clusters_per_frame:
        used = set()
        still = []
        for tr in active:
            last = tr.clusters[-1]
            if len(tr.clusters) >= 2:
                prev = tr.clusters[-2]
                vel = (last.centroid - prev.centroid) / max(last.frame - prev.frame, 1)
            else:
                vel = np.zeros(3)
            best, bd = None, opts.gate
            for k, c in enumerate(frame_clusters):
                if k in used:
                    continue
                pred = last.centroid + vel * (c.frame - last.frame)
                d = float(np.linalg.norm((c.centroid - pred)[:2]))
                if d < bd:
                    best, bd = k, d
            if best is not None:
                used.add(best)
                tr.clusters.append(frame_clusters[best])
                still.append(tr)
            elif frame_clusters and frame_clusters[0].frame - last.frame <= opts.max_gap:
                still.append(tr)
        for k, c in enumerate(frame_clusters):
            if k not in used:
                tr = MotionTrack([c])
                tracks.append(tr)
                still.append(tr)
        active = still
    for tr in tracks:
        tr.motions = [np.eye(4)]
        tr.residuals = [0.0]
        model = tr.clusters[0].points
        for a, b in zip(tr.clusters[:-1], tr.clusters[1:]):
            # Register against every earlier view brought to frame a (less
            # drift than frame to frame); a yaw step beyond max_yaw_step is
            # not a vehicle's turn in 0.1 s but a sparse cluster's ambiguity:
            # translation only then.
            # Start from the previous step's velocity: a partial view's
            # centroid is biased towards the side the LiDAR sees.
            if len(tr.motions) >= 2:
                init = -_velocity(tr) * (b.frame - a.frame)
            else:
                init = a.centroid - b.centroid
            T, res = icp_2d(b.points, model, init)
            if abs(np.degrees(np.arctan2(T[1, 0], T[0, 0]))) > opts.max_yaw_step_deg:
                T, res = icp_2d(b.points, model, init, rotate=False)
            # T maps frame b's points onto frame a's: the motion a -> b is its inverse.
            step = np.linalg.inv(T)
            tr.motions.append(step @ tr.motions[-1])
            tr.residuals.append(res)
            model = np.concatenate([ig.transform_points(model, step), b.points])
    return tracks


def _box(track: MotionTrack, n_frames: int, track_id: int) -> ObjectTrack:
    """A rigid node for a track: accumulated points in its first frame,
    heading along its travel, box from robust extents."""
    first = track.clusters[0]
    acc = np.concatenate([ig.transform_points(c.points, np.linalg.inv(M))
                          for c, M in zip(track.clusters, track.motions)])
    travel = track.motions[-1][:3, 3] + track.motions[-1][:3, :3] @ first.centroid - first.centroid
    yaw = float(np.arctan2(travel[1], travel[0]))
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    local = acc @ R                                    # world -> heading frame (rotation only)
    lo = np.percentile(local, 1, axis=0)
    hi = np.percentile(local, 99, axis=0)
    lo[2] = local[:, 2].min() - 0.3                    # down to the road (ground was removed)
    centre_h = (lo + hi) / 2
    size = hi - lo
    T0 = np.eye(4)
    T0[:3, :3] = R
    T0[:3, 3] = R @ centre_h
    frames = track.frames
    poses = np.stack([M @ T0 for M in track.motions])
    disp = float(np.linalg.norm(poses[:, :3, 3] - poses[0, :3, 3], axis=1).max())
    labelled = np.zeros(n_frames, bool)
    labelled[frames] = True
    return ObjectTrack(name=f"object_{track_id}", track_id=track_id, kind="moving",
                       size_hwl=np.array([size[2], size[1], size[0]]),
                       poses=fill_poses(frames, poses, n_frames, extrapolate=True), labelled=labelled,
                       displacement_m=disp, moving=True, dynamic=True)


def follow_node(track: MotionTrack, obj: ObjectTrack, sweeps, opts: MotionOptions,
                others=()) -> list:
    """Follow a node before and after the sweeps its track holds, by
    registering its accumulated points to each further sweep; updates
    ``obj`` (poses, labelled frames) and ``track`` (a :class:`Cluster` of
    the node's points per sweep, so that they are not masked) and returns
    the frames it registered.

    ``sweeps``: per frame, (world points above the ground, their index in
    the sweep). A vehicle stops (or starts) and its moving points stop
    with it, but the LiDAR still sees it. The track's ends are its least
    reliable part: as a vehicle slows, the free-space test sees only a
    fragment of it and the registration of those fragments drifts (a box
    that stopped dead drifted 1 m in two sweeps). So the following starts
    from the last (first) sweep whose cluster held :data:`FOLLOW_MIN_SHARE`
    of the track's median cluster size and registers the sweeps after
    (before) it again. Each step tries two predictions, the pose held and
    moved on at the velocity of the last two known poses, takes the points
    within :data:`FOLLOW_MARGIN` of the box there, registers the node's
    points to them (the tracks' 2-D ICP, started at the prediction) and
    keeps the registration whose box then holds the most points, provided
    its median residual is at most ``max_residual``, its correction at most
    half the ``gate`` and ``max_yaw_step_deg``, and its box holds
    :data:`FOLLOW_MIN_SHARE` of the median cluster. The first sweep that
    fails ends the following in that direction (a vehicle out of sight, or
    one the registration loses); the track's own poses stand there. So
    does a sweep where the registered box would overlap the box of one of
    ``others`` (nodes, :class:`ObjectTrack`) in a frame that node is
    labelled in: on the KITTI excerpt the truck ahead was two tracks, 17
    and 8 sweeps long, and each, followed through the other's, drew the
    truck twice."""
    n = len(sweeps)
    if not track.clusters:
        return []
    sizes = {c.frame: len(c.points) for c in track.clusters}
    need = max(opts.min_points, FOLLOW_MIN_SHARE * float(np.median(list(sizes.values()))))
    full = sorted(f for f, k in sizes.items() if k >= need)
    if not full:
        return []
    model = np.concatenate([ig.transform_points(c.points, np.linalg.inv(obj.poses[c.frame]))
                            for c in track.clusters if sizes[c.frame] >= need])
    half = obj.half_extent
    known = {f: obj.poses[f].copy() for f in full}
    registered = {}
    for step in (1, -1):
        f = full[-1] if step > 0 else full[0]
        while 0 <= f + step < n:
            g = f + step
            world, index = sweeps[g]
            found = _register_box(world, model, half, known, f, step, need, opts)
            if found is None:
                break
            if any(o.labelled[g] and boxes_overlap(found[0], half, o.poses[g], o.half_extent)
                   for o in others):
                break
            known[g], inside = found
            registered[g] = Cluster(g, world[inside], index[inside])
            f = g
    if not registered:
        return []
    # A sweep the track held keeps its cluster's points too (the box's
    # bottom 0.15 m, which the registered box leaves to the road, may hold
    # moving points).
    for c in track.clusters:
        r = registered.get(c.frame)
        if r is not None:
            index, at = np.unique(np.concatenate([r.point_index, c.point_index]), return_index=True)
            registered[c.frame] = Cluster(c.frame, np.concatenate([r.points, c.points])[at], index)
    track.clusters = sorted([c for c in track.clusters if c.frame not in registered]
                            + list(registered.values()), key=lambda c: c.frame)
    # The track's own poses stand where the following did not reach.
    for f in np.nonzero(obj.labelled)[0]:
        known.setdefault(int(f), obj.poses[f].copy())
    frames = sorted(known)
    obj.labelled[frames] = True
    obj.poses = fill_poses(frames, np.stack([known[f] for f in frames]), n, extrapolate=True)
    return sorted(registered)


def boxes_overlap(pose_a, half_a, pose_b, half_b) -> bool:
    """Whether two boxes (world_from_box poses, half extents x, y, z)
    overlap seen from above: the separating-axis test on their footprints
    (the boxes stand upright)."""
    def corners(pose, half):
        c = np.array([[sx * half[0], sy * half[1]] for sx in (-1, 1) for sy in (-1, 1)])
        return c @ pose[:2, :2].T + pose[:2, 3]
    a, b = corners(pose_a, half_a), corners(pose_b, half_b)
    for pose in (pose_a, pose_b):
        for axis in pose[:2, :2].T:
            pa, pb = a @ axis, b @ axis
            if pa.max() < pb.min() or pb.max() < pa.min():
                return False
    return True


def _register_box(world, model, half, known, f, step, need, opts):
    """One step of :func:`follow_node`: the node's pose in the sweep after
    (``step`` 1) or before (-1) frame ``f``, with the points its box holds
    there, or None."""
    if len(world) < need:
        return None
    preds = [known[f]]
    behind = [k for k in known if (k - f) * step < 0]
    if behind:
        # the velocity over the last gap between known poses (a track's
        # fragments may have left sweeps out)
        k = max(behind, key=lambda k: k * step)
        moved = known[f].copy()
        moved[:3, 3] += (known[f][:3, 3] - known[k][:3, 3]) / (f - k) * step
        preds.append(moved)
    best = None
    for pred in preds:
        near = in_box(ig.transform_points(world, np.linalg.inv(pred)), half, margin=FOLLOW_MARGIN)
        if near.sum() < need:
            continue
        T, res = icp_2d(world[near], ig.transform_points(model, pred), np.zeros(3))
        yaw = abs(np.degrees(np.arctan2(T[1, 0], T[0, 0])))
        if (res > opts.max_residual or yaw > opts.max_yaw_step_deg
                or np.linalg.norm(T[:2, 3]) > 0.5 * opts.gate):
            continue
        pose = np.linalg.inv(T) @ pred
        inside = in_box(ig.transform_points(world, np.linalg.inv(pose)), half, margin=0.1)
        if inside.sum() >= need and (best is None or inside.sum() > best[1].sum()):
            best = (pose, inside)
    return best


def standing_vehicles(candidates, tracks, modelled, n_frames, opts: MotionOptions) -> list:
    """Tracks of :func:`standing_candidates` that stayed put: seen in at
    least ``min_frames`` sweeps, registered within ``max_residual``, and
    moved less than ``min_travel``. Their few moving points were the
    free-space test's misses at their edges (the view of a vehicle's side
    changes as the ego vehicle passes it); masking them, and the hull the
    camera mask draws around them, hid the vehicle from the fit. On the
    KITTI excerpt a car beside the ego vehicle, registered whole 0.31 m
    apart over 19 sweeps, was masked whole in the held-out frames from
    1-2 % of its points. A candidate holding points of a node's cluster in that
    sweep is the node's, not standing."""
    claimed = [set() for _ in range(n_frames)]
    for tr, ok in zip(tracks, modelled):
        if ok:
            for c in tr.clusters:
                claimed[c.frame].update(c.point_index.tolist())
    free = [[c for c in frame if not claimed[c.frame].intersection(c.point_index.tolist())]
            for frame in candidates]
    out = []
    for tr in track_clusters(free, opts):
        if len(tr.clusters) < opts.min_frames or \
                max(tr.residuals[1:], default=np.inf) > opts.max_residual:
            continue
        if _box(tr, n_frames, 0).displacement_m < opts.min_travel:
            out.append(tr)
    return out


def detect_motion(scans, poses, opts: MotionOptions | None = None, log=None) -> MotionResult:
    """Moving objects of a drive: rigid nodes where they can be tracked,
    per-point masks where they cannot (see the module docstring)."""
    opts = opts or MotionOptions()
    n = len(scans)
    dyn = dynamic_points(scans, poses, opts)
    per_frame, candidates, sweeps = [], [], []
    for i in range(n):
        pts = np.asarray(scans[i], np.float64)
        idx = np.nonzero(above_ground(pts, opts))[0]
        world = ig.transform_points(pts[idx], poses[i])
        sweeps.append((world, idx))
        per_frame.append(clusters_of(i, world, idx, dyn[i][idx], opts))
        candidates.append(standing_candidates(i, world, idx, dyn[i][idx], opts))
    tracks = track_clusters(per_frame, opts)
    objects, modelled, node_tracks, followed_frames = [], [], [], {}
    masked = [d.copy() for d in dyn]
    for tr in tracks:
        for c in tr.clusters:
            masked[c.frame][c.point_index] = True
    for tr in tracks:
        ok = (len(tr.clusters) >= opts.min_frames
              and max(tr.residuals[1:], default=np.inf) <= opts.max_residual)
        obj = None
        if ok:
            obj = _box(tr, n, opts.track_id_base + len(objects))
            h, w, l = obj.size_hwl
            # A box grown past a vehicle's size by drifting registrations
            # would pull static background into the node: mask it instead.
            ok = (obj.displacement_m >= opts.min_travel and l <= MAX_LENGTH + 1.0
                  and w <= MAX_WIDTH + 1.0 and h <= opts.max_height + 0.5)
        modelled.append(bool(ok))
        if ok:
            objects.append(obj)
            node_tracks.append(tr)
    # Longest tracks first: where two tracks hold parts of one vehicle, the
    # one seen longer follows it, and the other's following stops at its box.
    order = sorted(range(len(objects)), key=lambda k: -len(node_tracks[k].clusters))
    for k in order if opts.follow else []:
        followed = follow_node(node_tracks[k], objects[k], sweeps, opts,
                               others=objects[:k] + objects[k + 1:])
        if followed:
            followed_frames[objects[k].name] = followed
    for tr in node_tracks:
        for c in tr.clusters:
            masked[c.frame][c.point_index] = False
    standing = standing_vehicles(candidates, tracks, modelled, n, opts)
    for tr in standing:
        for c in tr.clusters:
            masked[c.frame][c.point_index] = False
    res = MotionResult(objects, dyn, masked, tracks, modelled, standing)
    res.stats = {"dynamic_points": int(sum(d.sum() for d in dyn)),
                 "clusters": int(sum(len(c) for c in per_frame)),
                 "tracks": len(tracks), "nodes": len(objects), "standing": len(standing),
                 "followed_sweeps": int(sum(len(v) for v in followed_frames.values())),
                 "masked_points": int(sum(m.sum() for m in masked))}
    if log is not None:
        log("[motion] %(dynamic_points)d moving LiDAR points in %(clusters)d clusters, "
            "%(tracks)d tracks -> %(nodes)d rigid nodes (followed on %(followed_sweeps)d more "
            "sweeps), %(standing)d vehicles standing still, "
            "%(masked_points)d points masked"
            % res.stats)
    return res


# ----------------------------------------------------------------------------
# Masks and the import steps
# ----------------------------------------------------------------------------

def camera_mask(world_points, groups, w2c, K, size, dilate_px: int = 2) -> np.ndarray:
    """(H, W) uint8 mask: the convex hull of each group's projected points,
    grown by ``dilate_px``."""
    import cv2

    W, H = size
    mask = np.zeros((H, W), np.uint8)
    if len(world_points) == 0:
        return mask
    uv, z, _ = ig.project(world_points, w2c, K, (W, H))
    front = z > 0.5
    for g in np.unique(groups):
        sel = (groups == g) & front
        if sel.sum() < 3:
            continue
        hull = cv2.convexHull(np.round(uv[sel]).astype(np.int32))
        cv2.fillConvexPoly(mask, hull, 255)
    if dilate_px > 0:
        mask = cv2.dilate(mask, np.ones((2 * dilate_px + 1,) * 2, np.uint8))
    return mask


def import_step(src, state, opts, log, options: MotionOptions | None = None):
    """``mi-invrgbl import``'s motion step for drives without tracking
    labels: appends the rigid nodes to ``state.objects`` (the import then
    gives them Gaussians and per-frame poses) and keeps the masked points
    for :func:`write_masks`."""
    if src.labels is not None:
        return
    scans = [s[0] for s in state.scans]
    if options is None:
        options = MotionOptions(follow=bool(getattr(opts, "follow_nodes", False)))
    res = detect_motion(scans, state.poses, options, log=log)
    state.objects.extend(res.objects)
    for o in res.objects:
        state.object_report.append({"track_id": o.track_id, "kind": o.kind,
                                       "displacement_m": o.displacement_m, "moving": True,
                                       "dynamic": True, "labelled_frames": int(o.labelled.sum()),
                                       "from": FROM_LIDAR_MOTION})
        log("[import] moving object %d from the LiDAR: %d frames, %.2f m travelled, "
            "box %.1f x %.1f x %.1f m" % (o.track_id, int(o.labelled.sum()), o.displacement_m,
                                          *o.size_hwl[::-1]))
    state.motion = res
    state.counts["motion_nodes"] = len(res.objects)
    state.counts["motion_masked_points"] = res.stats["masked_points"]


def image_masks(state, which: str = "masked") -> list:
    """Per frame, the camera mask at the import's image size (or None) of
    the ``masked`` points (moving, in no node) or of all ``dynamic`` ones
    (moving, with the clusters grown around them)."""
    import cv2

    res = state.motion
    if res is None:
        return [None] * len(state.scans)
    out = []
    for i, (pts, _) in enumerate(state.scans):
        if which == "masked":
            chosen = res.masked[i]
        else:
            chosen = res.dynamic[i].copy()
            for tr in res.tracks:
                for c in tr.clusters:
                    if c.frame == i:
                        chosen[c.point_index] = True
        sel = np.nonzero(chosen)[0]
        world = ig.transform_points(np.asarray(pts, np.float64)[sel], state.poses[i])
        if len(sel):
            # One hull per connected group of masked points.
            groups = np.zeros(len(sel), np.int64)
            q = np.floor(world[:, :2] / 0.5).astype(np.int64)
            q -= q.min(axis=0) - 1
            grid = np.zeros((int(q[:, 1].max()) + 2, int(q[:, 0].max()) + 2), np.uint8)
            grid[q[:, 1], q[:, 0]] = 255
            _, lab = cv2.connectedComponents(cv2.dilate(grid, np.ones((3, 3), np.uint8)))
            groups = lab[q[:, 1], q[:, 0]]
        else:
            groups = np.zeros(0, np.int64)
        out.append(camera_mask(world, groups, np.linalg.inv(state.cam_poses[i]),
                               state.K, state.size))
    return out


def write_masks(state, out_dir) -> list:
    """Write the masks of the module docstring into ``out_dir/observations``;
    returns per frame the ``{"camera": path, "lidar": path}`` written (the
    frame records' ``masks``), empty dicts when motion was not run."""
    import cv2
    from pathlib import Path

    res = state.motion
    if res is None:
        return [{} for _ in state.range_images]
    obs = Path(out_dir) / "observations"
    cams = image_masks(state)
    n_any = 0
    written = []
    for i, ri in enumerate(state.range_images):
        lidar = np.zeros(ri.shape, np.uint8)
        idx = ri.index
        hit = idx >= 0
        lidar[hit] = np.where(res.masked[i][idx[hit]], 255, 0)
        paths = {"camera": obs / ("motion_%04d.png" % i),
                 "lidar": obs / ("motion_lidar_%04d.png" % i)}
        cv2.imwrite(str(paths["lidar"]), lidar)
        cv2.imwrite(str(paths["camera"]), cams[i])
        written.append(paths)
        n_any += bool(lidar.any() or cams[i].any())
    state.counts["motion_masked_frames"] = n_any
    return written
