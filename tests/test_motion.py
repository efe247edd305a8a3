"""Moving objects from the LiDAR alone: a box driving between two static
walls, scanned by a simulated spinning LiDAR on a moving ego vehicle."""

import numpy as np
import pytest

from mi_invrgbl.io import motion

N_FRAMES = 14
EGO_STEP = 0.5           # metres per sweep, along x
BOX_START = np.array([8.0, 3.0, 0.8])
BOX_STEP = 1.0           # metres per sweep, along x
BOX_HALF = np.array([2.0, 1.0, 0.8])
WALL_Y = 8.0
SENSOR_Z = 1.7


def _rays(beams=32, steps=720):
    el = np.radians(np.linspace(2.0, -24.0, beams))
    az = np.arange(steps) * 2 * np.pi / steps
    e, a = np.meshgrid(el, az, indexing="ij")
    return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)


def _slab(o, d, lo, hi):
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - o) / d
        t2 = (hi - o) / d
    tn = np.nanmax(np.minimum(t1, t2), axis=1)
    tf = np.nanmin(np.maximum(t1, t2), axis=1)
    return np.where((tf >= tn) & (tn > 0), tn, np.inf)


def _sweep(frame, with_box=True, centre=None):
    """Sensor-frame points of one sweep (the sensor is axis-aligned); the
    box at ``centre`` (default: where it drives to by ``frame``)."""
    origin = np.array([EGO_STEP * frame, 0.0, SENSOR_Z])
    d = _rays()
    o = np.broadcast_to(origin, d.shape)
    t = np.full(len(d), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        tg = -origin[2] / d[:, 2]                          # road z = 0
        t = np.where(tg > 0, np.minimum(t, tg), t)
        for y in (WALL_Y, -WALL_Y):                        # facades, 6 m tall
            tw = (y - origin[1]) / d[:, 1]
            z = origin[2] + tw * d[:, 2]
            t = np.where((tw > 0) & (z < 6.0), np.minimum(t, tw), t)
    # two static pillars for structure
    for cx in (15.0, 30.0):
        t = np.minimum(t, _slab(o, d, np.array([cx - 0.3, -5.3, 0]), np.array([cx + 0.3, -4.7, 3])))
    if with_box:
        c = BOX_START + np.array([BOX_STEP * frame, 0, 0]) if centre is None else centre
        t = np.minimum(t, _slab(o, d, c - BOX_HALF, c + BOX_HALF))
    ok = np.isfinite(t) & (t < 80)
    return d[ok] * t[ok, None]


def _poses():
    P = np.tile(np.eye(4), (N_FRAMES, 1, 1))
    P[:, 0, 3] = EGO_STEP * np.arange(N_FRAMES)
    P[:, 2, 3] = SENSOR_Z
    return P


def _on_box(points_world, frame):
    c = BOX_START + np.array([BOX_STEP * frame, 0, 0])
    return np.all(np.abs(points_world - c) <= BOX_HALF + 0.05, axis=1)


@pytest.fixture(scope="module")
def drive():
    return [_sweep(i) for i in range(N_FRAMES)], _poses()


def test_moving_box_becomes_a_rigid_node(drive):
    scans, poses = drive
    res = motion.detect_motion(scans, poses)
    assert len(res.objects) == 1
    obj = res.objects[0]
    # Static walls, pillars and road are not dynamic.
    for i, s in enumerate(scans):
        world = s + poses[i, :3, 3]
        box = _on_box(world, i)
        assert res.dynamic[i][~box].mean() < 0.005
    # The node moves with the box: BOX_STEP per sweep along x, no sideways drift.
    lab = np.nonzero(obj.labelled)[0]
    assert len(lab) >= motion.MotionOptions().min_frames
    t = obj.poses[lab, :3, 3]
    steps = np.diff(t, axis=0) / np.diff(lab)[:, None]
    assert abs(np.median(steps[:, 0]) - BOX_STEP) < 0.05
    assert np.allclose(steps[:, 0], BOX_STEP, atol=0.2)
    assert np.abs(steps[:, 1]).max() < 0.1
    # Heading along the travel; the box's footprint near the truth.
    assert abs(obj.poses[lab[0], 0, 0]) > 0.99
    h, w, l = obj.size_hwl
    assert abs(l - 2 * BOX_HALF[0]) < 0.6 and abs(w - 2 * BOX_HALF[1]) < 0.6
    # Its centre at a labelled frame (x, y) within 0.5 m of the box's.
    c = BOX_START[:2] + np.array([BOX_STEP * lab[0], 0])
    assert np.linalg.norm(obj.poses[lab[0], :2, 3] - c) < 0.5
    assert res.stats["masked_points"] < 0.05 * res.stats["dynamic_points"]


def test_untrackable_motion_is_masked_not_modelled(drive):
    scans, poses = drive
    res = motion.detect_motion(scans, poses, motion.MotionOptions(min_frames=N_FRAMES + 1))
    assert res.objects == []
    box_pts = masked_on_box = wall_masked = 0
    for i, s in enumerate(scans):
        box = _on_box(s + poses[i, :3, 3], i)
        box_pts += box.sum()
        masked_on_box += res.masked[i][box].sum()
        wall_masked += res.masked[i][~box].sum()
    assert masked_on_box > 0.6 * box_pts
    assert wall_masked < 0.01 * masked_on_box


def test_camera_mask_covers_the_box():
    K = np.array([[200.0, 0, 159.5], [0, 200.0, 59.5], [0, 0, 1]])
    # camera at the ego's first pose, looking along +x (OpenCV axes)
    cam = np.eye(4)
    cam[:3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)
    cam[:3, 3] = [0, 0, SENSOR_Z]
    s = _sweep(0)
    box = _on_box(s + [0, 0, SENSOR_Z], 0)
    world = s[box] + [0, 0, SENSOR_Z]
    mask = motion.camera_mask(world, np.zeros(len(world), int), np.linalg.inv(cam), K, (320, 120))
    from mi_invrgbl.io.init_gaussians import project
    uv, _, ok = project(world, np.linalg.inv(cam), K, (320, 120))
    px = np.round(uv[ok]).astype(int)
    assert (mask[px[:, 1], px[:, 0]] == 255).all()
    # a wall point on the other side stays unmasked
    wall = np.array([[12.0, -WALL_Y, 2.0]])
    uv, _, ok = project(wall, np.linalg.inv(cam), K, (320, 120))
    assert ok[0] and mask[int(round(uv[0, 1])), int(round(uv[0, 0]))] == 0


# ---------------------------------------------------------------- vehicles standing still
PARKED_CENTRE = np.array([10.0, -3.0, 0.8])
PARKED_HALF = np.array([2.0, 0.9, 0.8])


def _sweep_with_parked(frame, gap=None):
    """A sweep of the drive plus a parked box beside the road; with ``gap``
    a second parked box stands that far beside it (a queue in the next lane)."""
    origin = np.array([EGO_STEP * frame, 0.0, SENSOR_Z])
    pts = _sweep(frame)
    d = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    t = np.linalg.norm(pts, axis=1)
    o = np.broadcast_to(origin, d.shape)
    boxes = [(PARKED_CENTRE, PARKED_HALF)]
    if gap is not None:
        other = PARKED_CENTRE - np.array([0.0, 2 * PARKED_HALF[1] + gap, 0.0])
        boxes.append((other, PARKED_HALF))
    for c, h in boxes:
        t = np.minimum(t, _slab(o, d, c - h, c + h))
    return d * t[:, None]


def _on_parked(points_world):
    return np.all(np.abs(points_world - PARKED_CENTRE) <= PARKED_HALF + 0.05, axis=1)


@pytest.fixture(scope="module")
def parked_drive():
    return [_sweep_with_parked(i) for i in range(N_FRAMES)], _poses()


def _with_edge_misses(monkeypatch, share):
    """The free-space test, plus false 'moved' votes on ``share`` of the
    parked box's points in every sweep (its edges, seen from a new angle)."""
    real = motion.dynamic_points

    def dynamic_points(scans, poses, opts=None):
        out = real(scans, poses, opts)
        rng = np.random.default_rng(1)
        for i, s in enumerate(scans):
            # (the test votes on points above the road only)
            on = np.nonzero(_on_parked(s + poses[i, :3, 3])
                            & motion.above_ground(s, opts or motion.MotionOptions()))[0]
            out[i][rng.choice(on, max(int(share * len(on)), 25), replace=False)] = True
        return out

    monkeypatch.setattr(motion, "dynamic_points", dynamic_points)


def test_a_parked_vehicle_with_a_few_false_moving_points_is_not_masked(parked_drive, monkeypatch):
    scans, poses = parked_drive
    before = motion.detect_motion(scans, poses)
    assert before.standing == []
    _with_edge_misses(monkeypatch, 0.03)
    res = motion.detect_motion(scans, poses)
    # The moving box is still the one node, the parked one stands still...
    assert len(res.objects) == 1 and len(res.standing) == 1
    assert res.stats["standing"] == 1
    track = res.standing[0]
    assert len(track.clusters) >= motion.MotionOptions().min_frames
    # ...and none of its points is masked (its false seeds included), while
    # the moving box's are covered by its node as before.
    for i, s in enumerate(scans):
        world = s + poses[i, :3, 3]
        assert not res.masked[i][_on_parked(world)].any()
        assert res.dynamic[i][_on_parked(world)].any()
    # Without the standing test those seeds would be masked.
    opts = motion.MotionOptions(min_frames=N_FRAMES + 1)
    res_short = motion.detect_motion(scans, poses, opts)
    assert res_short.standing == []
    assert sum(res_short.masked[i][_on_parked(s + poses[i, :3, 3])].sum()
               for i, s in enumerate(scans)) > 0


def test_a_box_moving_with_few_moving_points_is_not_standing():
    """Candidates that travel (1 m a sweep) are never taken for standing."""
    drive = [_sweep(i) for i in range(N_FRAMES)]
    poses = _poses()
    opts = motion.MotionOptions()
    candidates = []
    for i, s in enumerate(drive):
        world = s + poses[i, :3, 3]
        on = np.nonzero(_on_box(world, i))[0]
        candidates.append([motion.Cluster(i, world[on], on)])
    assert motion.standing_vehicles(candidates, [], [], N_FRAMES, opts) == []
    # The same clusters held in place stand still.
    held = [[motion.Cluster(i, c[0].points - [BOX_STEP * i, 0, 0], c[0].point_index)]
            for i, c in enumerate(candidates)]
    assert len(motion.standing_vehicles(held, [], [], N_FRAMES, opts)) == 1
    # A candidate holding points of a node's cluster belongs to the node.
    node = motion.MotionTrack([c[0] for c in held])
    assert motion.standing_vehicles(held, [node], [True], N_FRAMES, opts) == []


def test_a_queue_of_vehicles_is_split_into_vehicle_sized_candidates():
    """Two parked boxes 0.8 m apart are one component on the 0.4 m grid;
    the candidates are found on a finer one, each a single box."""
    s = _sweep_with_parked(0, gap=0.8)
    world = s + _poses()[0, :3, 3]
    opts = motion.MotionOptions()
    keep = motion.above_ground(s, opts)
    idx = np.nonzero(keep)[0]
    w = world[idx]
    n, lab = motion._components(w[:, :2], opts.cell)
    on = _on_parked(w)
    assert not motion.vehicle_sized(w[lab == lab[np.nonzero(on)[0][0]]])
    seeds = np.zeros(len(w), bool)
    seeds[np.nonzero(on)[0][:: 12]] = True            # 8 % of the box's points
    assert seeds.sum() >= opts.min_points
    found = motion.standing_candidates(0, w, idx, seeds, opts)
    assert len(found) == 1
    got = found[0]
    assert motion.vehicle_sized(got.points)
    assert _on_parked(got.points).mean() > 0.95 and _on_parked(got.points).sum() >= 0.9 * on.sum()
    # Too many moving points for a standing vehicle: a moving one's cluster.
    seeds[np.nonzero(on)[0][:: 2]] = True
    assert motion.standing_candidates(0, w, idx, seeds, opts) == []


# ---------------------------------------------------------------- vehicles that stop
STOP_FRAME = 6           # the box drives BOX_STEP a sweep up to here, then stands
FOLLOW = motion.MotionOptions(follow=True)      # import --follow-nodes


def _stop_centre(frame):
    return BOX_START + np.array([BOX_STEP * min(frame, STOP_FRAME), 0, 0])


def test_a_vehicle_that_stops_stays_its_node(monkeypatch):
    """The free-space test sees the box only while it drives; the node
    follows it by registration over the sweeps where it stands."""
    scans = [_sweep(i, centre=_stop_centre(i)) for i in range(N_FRAMES)]
    poses = _poses()
    res = motion.detect_motion(scans, poses, FOLLOW)
    assert len(res.objects) == 1
    obj = res.objects[0]
    lab = np.nonzero(obj.labelled)[0]
    assert lab[-1] == N_FRAMES - 1 and res.stats["followed_sweeps"] > 0
    # Standing: the node's centre keeps still (the truth does) within 0.1 m
    # over every sweep after the stop, and is where the moving part put it.
    after = np.arange(STOP_FRAME + 1, N_FRAMES)
    t = obj.poses[after, :3, 3]
    assert np.linalg.norm(t[:, :2] - t[0, :2], axis=1).max() < 0.1
    c0 = obj.poses[lab[0], :2, 3] - _stop_centre(lab[0])[:2]      # the node's offset in its box
    assert np.linalg.norm(t[:, :2] - (_stop_centre(N_FRAMES - 1)[:2] + c0), axis=1).max() < 0.15
    # The node's box holds the standing box's points in every sweep after
    # the stop (the import gives the node the points its box holds), and
    # none of them is masked.
    from mi_invrgbl.io.objects import in_box
    for i in after:
        world = scans[i] + poses[i, :3, 3]
        on = _on_stopped(world, i) & (world[:, 2] > 0.2)
        local = world[on] @ obj.poses[i, :3, :3] - obj.poses[i, :3, 3] @ obj.poses[i, :3, :3]
        assert in_box(local, obj.half_extent).mean() > 0.95
        assert not res.masked[i][on].any()
    # Without following, the track ends where its moving points do, and the
    # extrapolated pose drives on through the standing box.
    # (Following is off by default: import --follow-nodes.)
    assert motion.detect_motion(scans, poses).stats["followed_sweeps"] == 0
    monkeypatch.setattr(motion, "follow_node", lambda *a, **k: [])
    plain = motion.detect_motion(scans, poses).objects[0]
    last = np.nonzero(plain.labelled)[0][-1]
    assert last < N_FRAMES - 1
    assert plain.poses[N_FRAMES - 1, 0, 3] - plain.poses[last, 0, 3] > 0.5 * (N_FRAMES - 1 - last)


def _on_stopped(points_world, frame):
    return np.all(np.abs(points_world - _stop_centre(frame)) <= BOX_HALF + 0.05, axis=1)


def test_a_vehicle_that_leaves_is_not_followed_into_the_background():
    """The box drives, then is gone (out of the scene): following stops at
    the first sweep without it, and claims no wall, pillar or road."""
    gone = STOP_FRAME + 2
    scans = [_sweep(i, with_box=i < gone)
             for i in range(N_FRAMES)]
    poses = _poses()
    res = motion.detect_motion(scans, poses, FOLLOW)
    assert len(res.objects) == 1
    lab = np.nonzero(res.objects[0].labelled)[0]
    assert lab[-1] < gone


def test_boxes_overlap_is_the_separating_axis_test_on_the_footprints():
    def pose(x, y, yaw_deg):
        T = np.eye(4)
        c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
        T[:2, :2] = [[c, -s], [s, c]]
        T[:2, 3] = x, y
        return T
    half = np.array([2.0, 1.0, 0.8])
    assert motion.boxes_overlap(pose(0, 0, 0), half, pose(3.9, 0, 0), half)
    assert not motion.boxes_overlap(pose(0, 0, 0), half, pose(4.1, 0, 0), half)
    assert not motion.boxes_overlap(pose(0, 0, 0), half, pose(0, 2.1, 0), half)
    # Turned 45 degrees, the corner reaches 2.12 m along the other's y: the
    # centres' distance on the axes alone would call 2.5 m apart separate.
    assert motion.boxes_overlap(pose(0, 0, 0), half, pose(0, 2.9, 45), half)
    assert not motion.boxes_overlap(pose(0, 0, 0), half, pose(0, 3.2, 45), half)
    # Height plays no part; the test is symmetric.
    a, b = pose(0, 0, 30), pose(2.5, 1.5, -60)
    assert motion.boxes_overlap(a, half, b, half) == motion.boxes_overlap(b, half, a, half)


def test_following_stops_at_another_nodes_box(monkeypatch):
    """Where another node holds the standing box (two tracks of one vehicle),
    the following stops at the first sweep in which their boxes overlap."""
    scans = [_sweep(i, centre=_stop_centre(i)) for i in range(N_FRAMES)]
    poses = _poses()
    monkeypatch.setattr(motion, "follow_node", lambda *a, **k: [])
    res = motion.detect_motion(scans, poses)
    monkeypatch.undo()
    track = next(t for t, ok in zip(res.tracks, res.modelled) if ok)
    opts = FOLLOW
    sweeps = []
    for s, P in zip(scans, poses):
        idx = np.nonzero(motion.above_ground(s, opts))[0]
        sweeps.append((s[idx] + P[:3, 3], idx))
    blocker_from = STOP_FRAME + 4
    blocker = motion.ObjectTrack(
        name="object_9", track_id=9, kind="moving", size_hwl=res.objects[0].size_hwl,
        poses=np.tile(np.eye(4), (N_FRAMES, 1, 1)),
        labelled=np.arange(N_FRAMES) >= blocker_from, displacement_m=0.0, moving=True, dynamic=True)
    blocker.poses[:, :3, 3] = _stop_centre(N_FRAMES)
    import copy
    alone = copy.deepcopy(res.objects[0])
    assert motion.follow_node(copy.deepcopy(track), alone, sweeps, opts)[-1] == N_FRAMES - 1
    obj = copy.deepcopy(res.objects[0])
    got = motion.follow_node(copy.deepcopy(track), obj, sweeps, opts, others=[blocker])
    assert got and got[-1] == blocker_from - 1
    assert not obj.labelled[blocker_from:].any()


def test_following_runs_backwards_at_the_tracks_velocity(monkeypatch):
    """The free-space test misses the driving box in its first sweeps: the
    node is followed back to the first sweep, BOX_STEP a sweep, as the
    track moved."""
    late = 5
    real = motion.dynamic_points

    def blind_at_first(scans, poses, opts=None):
        out = real(scans, poses, opts)
        return [np.zeros_like(d) if i < late else d for i, d in enumerate(out)]

    monkeypatch.setattr(motion, "dynamic_points", blind_at_first)
    scans = [_sweep(i) for i in range(N_FRAMES)]
    poses = _poses()
    res = motion.detect_motion(scans, poses, FOLLOW)
    assert len(res.objects) == 1
    obj = res.objects[0]
    lab = np.nonzero(obj.labelled)[0]
    assert lab[0] == 0
    steps = np.diff(obj.poses[: late + 2, 0, 3])
    assert np.allclose(steps, BOX_STEP, atol=0.1), steps
    assert np.abs(np.diff(obj.poses[: late + 2, 1, 3])).max() < 0.1
    # Without following the track starts at the first sweep it saw moving.
    monkeypatch.setattr(motion, "follow_node", lambda *a, **k: [])
    assert np.nonzero(motion.detect_motion(scans, poses).objects[0].labelled)[0][0] >= late


def test_following_stops_at_an_empty_sweep(monkeypatch):
    """A sweep with no points above the ground (a dropped sweep) ends the
    following there: no pose is made up for it or past it."""
    scans = [_sweep(i, centre=_stop_centre(i)) for i in range(N_FRAMES)]
    poses = _poses()
    monkeypatch.setattr(motion, "follow_node", lambda *a, **k: [])
    res = motion.detect_motion(scans, poses)
    monkeypatch.undo()
    track = next(t for t, ok in zip(res.tracks, res.modelled) if ok)
    sweeps = []
    for s, P in zip(scans, poses):
        idx = np.nonzero(motion.above_ground(s, FOLLOW))[0]
        sweeps.append((s[idx] + P[:3, 3], idx))
    gap = STOP_FRAME + 4
    sweeps[gap] = (np.zeros((0, 3)), np.zeros(0, np.int64))
    obj = res.objects[0]
    got = motion.follow_node(track, obj, sweeps, FOLLOW)
    assert got and max(got) == gap - 1
    assert not obj.labelled[gap:].any() and np.all(np.isfinite(obj.poses))
