"""Per-frame corrections of the sensor rig's pose, fitted in stage 1.

Without GPS/IMU poses the import takes the ego motion from LiDAR odometry
(:mod:`mi_invrgbl.io.odometry`). Along a street the sweeps slide along the
street axis, which their geometry hardly pins down, and their heading
drifts: on the KITTI excerpt a stage-1 render of each frame matched its
image best after a zoom of -0.5 % to +0.5 % and a shift of up to a pixel
at quarter resolution (``cv2.findTransformECC``), growing smoothly from
the first frame to the last. A camera that is a few centimetres off blurs
every view it shares with the others by that much.

So stage 1 fits, per training frame, a rigid correction of the whole rig
(camera and LiDAR move together) in the camera's own frame (Mitsuba's
axes: x left, y up, z forward), translation ``t`` in metres and rotation
vector ``w`` in radians, about the camera's centre::

    camera_to_world' = camera_to_world @ [R(w) | t]
    lidar_to_world'  = W @ lidar_to_world,  W = camera_to_world' @ camera_to_world^-1

A step traces its camera pixels and LiDAR beams along the corrected rays,
differentiable in the correction (the Gaussians' responses along a ray
depend smoothly on its origin and direction). Frames that take no gradient
steps -- validation and held-out frames -- get the correction interpolated
linearly in frame index between the nearest training frames (held at the
ends): their images are never read, and the drift the corrections follow
is smooth. :meth:`RigPoseFit.bake` moves every frame's sensors and rays to
the corrected poses; everything after stage 1 (freezing, stage 2, the
outputs, ``eval`` through the fit's own ``frames.json`` and ``scene.xml``)
uses them.
"""

from __future__ import annotations

import copy

import numpy as np
import drjit as dr
import mitsuba as mi

from ..physics.host_arrays import jit_array
from .object_poses import FrameView, RigidPose, correction_matrix, correction_table

#: Adam learning rates (metres, radians per step with a gradient). A frame
#: takes a step every ~32 iterations on the KITTI excerpt; a quarter-
#: resolution pixel there is 5.5 mrad, so 2e-4 rad a visit crosses it in
#: about 30 visits, and 2 mm a visit moves the camera the few centimetres
#: odometry is off in a stage's worth of visits. The rates follow the
#: positions' schedule down to 1 % as a budgeted stage 1 ends.
TRANSLATION_LR = 2e-3
ROTATION_LR = 2e-4
#: Largest correction: beyond it the odometry is wrong, not noisy.
MAX_TRANSLATION = 0.5      # metres, per axis
MAX_ROTATION = 0.03        # radians, per axis (1.7 degrees)
#: The two optimised parts of a correction.
PARTS = {"t": (TRANSLATION_LR, MAX_TRANSLATION), "w": (ROTATION_LR, MAX_ROTATION)}
#: The rig's name in the optimiser's keys and checkpoints.
NAME = "rig"
#: The search of :meth:`RigPoseFit.align_from_images`: first steps of the
#: pattern search (metres, radians; halved :data:`HALVINGS` times), training
#: neighbours on each side, sweeps over the frames, points per frame and
#: their distances from the camera, the share of a pair's colour
#: differences kept (the rest: occlusions, moving objects), least points a
#: pair must share, and the least relative gain to keep the result.
SEARCH_STEP = (0.02, 0.0005)
HALVINGS = 5
NEIGHBOURS = 2
SWEEPS = 2
MAX_POINTS = 6000
DEPTH = (2.0, 60.0)
TRIM = 0.8
MIN_POINTS = 200
MIN_GAIN = 0.02


def _to_world(sensor) -> np.ndarray:
    return np.array(sensor.world_transform().matrix, np.float64).reshape(4, 4)


def _set_to_world(sensor, matrix) -> None:
    params = mi.traverse(sensor)
    params["to_world"] = mi.Transform4f(np.asarray(matrix, np.float64))
    params.update()


def _transform_rays(rays, matrix):
    """``rays`` moved by the rigid 4x4 ``matrix`` (numpy, no derivatives)."""
    m = np.asarray(matrix, np.float64)
    R = mi.Matrix3f(*[float(x) for x in m[:3, :3].ravel()])
    t = mi.Vector3f(*[float(x) for x in m[:3, 3]])
    out = mi.Ray3f(mi.Point3f(R @ mi.Vector3f(rays.o) + t), mi.Vector3f(R @ rays.d))
    out.maxt = mi.Float(rays.maxt)
    dr.eval(out.o, out.d, out.maxt)
    return out


class RigPoseFit:
    """The rig corrections of every frame. One flat ``mi.Float`` of 3 values
    per frame (in frame order) for each part of :data:`PARTS`; the
    import's sensor poses and rays are kept, corrections always apply to them."""

    objects = (NAME,)   # (the handle :class:`.variables.PoseVariable` iterates)

    def __init__(self, observations, train_frames):
        self.frames = list(observations)
        self.position = {f.index: k for k, f in enumerate(self.frames)}
        self.train = sorted({self.position[f.index] for f in train_frames
                             if f.camera is not None})
        self.pivot, self.base_camera, self.base_lidar = [], [], []
        for f in self.frames:
            cam = None if f.camera is None else (_to_world(f.camera.sensor), f.camera.rays)
            lid = None if f.lidar is None else (_to_world(f.lidar.sensor), f.lidar.rays)
            self.base_camera.append(cam)
            self.base_lidar.append(lid)
            self.pivot.append(cam[0] if cam else (lid[0] if lid else np.eye(4)))
        self.values = {(NAME, part): dr.zeros(mi.Float, 3 * len(self.frames)) for part in PARTS}

    def __bool__(self):
        # Corrections need images: the LiDAR alone is what odometry aligned.
        return len(self.train) > 1

    @staticmethod
    def key(name, part) -> str:
        return "%s.%s" % (name, part)

    # ------------------------------------------------------------ stage 1
    def rays(self, frame, idx, lidar=False):
        """The base rays ``idx`` (``mi.UInt32``) of ``frame``'s camera (or
        LiDAR), moved by the frame's correction: differentiable in it."""
        k = self.position[frame.index]
        base = self.base_lidar[k] if lidar else self.base_camera[k]
        o = dr.gather(mi.Point3f, base[1].o, idx)
        d = dr.gather(mi.Vector3f, base[1].d, idx)
        # (opaque indices and matrices: one compiled kernel serves every frame)
        t, w = (mi.Vector3f(*[dr.gather(mi.Float, self.values[NAME, part],
                                        dr.opaque(mi.UInt32, 3 * k + j)) for j in range(3)])
                for part in PARTS)
        pivot = RigidPose.from_matrix(self.pivot[k])
        moved = pivot.corrected(t, w)
        # World -> camera (the pivot's inverse), then the corrected camera -> world.
        back = pivot.rotation.T
        local_o = back @ (mi.Vector3f(o) - pivot.translation)
        out = mi.Ray3f(mi.Point3f(moved.rotation @ local_o + moved.translation),
                       mi.Vector3f(moved.rotation @ (back @ d)))
        out.maxt = dr.gather(mi.Float, base[1].maxt, idx)
        return out

    # ------------------------------------------------------------ start
    def align_from_images(self, points, log=None) -> dict:
        """Start the corrections from the poses under which the static
        scene's colours agree between neighbouring training images.

        The gradient steps move a correction by its learning rate per visit
        of a frame, and the Gaussians they see have been fitted to the
        odometry's poses, blurred by their errors. So first, per training
        frame, a pattern search (coordinate steps from :data:`SEARCH_STEP`,
        halved :data:`HALVINGS` times) over the six values moves the frame's
        camera so that ``points`` (the static scene: the background
        Gaussians' centres, world frame) it sees, in front at their pixels
        and within :data:`DEPTH`, sample the colours the
        :data:`NEIGHBOURS` training frames on each side see at their current
        poses (the mean of the :data:`TRIM` smallest absolute differences:
        occlusions and moving objects fall in the rest); :data:`SWEEPS`
        sweeps over the frames. The points stay put, so the images decide
        where the cameras are relative to the LiDAR's scene. The result is
        kept only if it lowers the mean difference by :data:`MIN_GAIN`.
        Only training images are read. Returns the differences before and
        after and the corrections' sizes."""
        views = {k: _RigView(self.frames[k], points) for k in self.train}
        K = len(self.frames)
        c = np.zeros((K, 6))
        pairs = {k: [j for j in self.train if j != k and
                     abs(self.train.index(j) - self.train.index(k)) <= NEIGHBOURS]
                 for k in self.train}
        moves = lambda k, ck: self.pivot[k] @ np.linalg.inv(correction_matrix(ck)) \
            @ np.linalg.inv(self.pivot[k])  # noqa: E731  (world points into frame k's import pose)

        def seen_by_neighbours(k):
            """What frame k's points look like in its neighbours' images, at
            their current corrections (fixed while frame k is searched)."""
            return [views[j].sample(views[k].points, moves(j, c[j])) for j in pairs[k]]

        def cost(k, ck, refs):
            mine, vals = views[k].sample(views[k].points, moves(k, ck)), []
            for theirs in refs:
                ok = mine[1] & theirs[1]
                if ok.sum() >= MIN_POINTS:
                    d = np.sort(np.abs(mine[0][ok] - theirs[0][ok]).sum(1))
                    vals.append(d[: max(1, int(TRIM * d.size))].mean())
            return float(np.mean(vals)) if vals else np.nan

        def total():
            v = [cost(k, c[k], seen_by_neighbours(k)) for k in self.train]
            v = [x for x in v if np.isfinite(x)]
            return float(np.mean(v)) if v else np.nan

        before = total()
        if not np.isfinite(before):
            return {"used": False, "reason": "no two training views share %d points" % MIN_POINTS}
        for _ in range(SWEEPS):
            for k in self.train:
                refs = seen_by_neighbours(k)
                best = cost(k, c[k], refs)
                if not np.isfinite(best):
                    continue
                step = np.array([SEARCH_STEP[0]] * 3 + [SEARCH_STEP[1]] * 3)
                for _ in range(HALVINGS + 1):
                    improved = True
                    while improved:
                        improved = False
                        for j in range(6):
                            for sign in (1.0, -1.0):
                                trial = c[k].copy()
                                trial[j] += sign * step[j]
                                if np.any(np.abs(trial[:3]) > MAX_TRANSLATION) or \
                                        np.any(np.abs(trial[3:]) > MAX_ROTATION):
                                    continue
                                v = cost(k, trial, refs)
                                if v < best:
                                    c[k], best, improved = trial, v, True
                    step = step / 2
        after = total()
        used = bool(after < (1.0 - MIN_GAIN) * before)
        t = np.linalg.norm(c[self.train, :3], axis=1)
        r = np.degrees(np.linalg.norm(c[self.train, 3:], axis=1))
        report = {"mean_colour_difference": [round(before, 5), round(after, 5)], "used": used,
                  "translation_m_max": round(float(t.max()), 4),
                  "translation_m_median": round(float(np.median(t)), 4),
                  "rotation_deg_max": round(float(r.max()), 4),
                  "rotation_deg_median": round(float(np.median(r)), 4)}
        if used:
            for part, cols in (("t", slice(0, 3)), ("w", slice(3, 6))):
                self.values[NAME, part] = jit_array(mi.Float, c[:, cols].ravel())
        if log is not None:
            log("[fit] camera poses %s: colour difference between neighbouring training images "
                "%.4f -> %.4f; corrections up to %.3f m (median %.3f) and %.3f deg"
                % ("moved" if used else "kept (too little gain)", before, after, t.max(),
                   np.median(t), r.max()))
        return report

    # ------------------------------------------------------------ host side
    def table(self) -> np.ndarray:
        """(frames, 6) corrections (tx, ty, tz, wx, wy, wz): fitted at the
        training frames, interpolated elsewhere."""
        return correction_table([self.values[NAME, part] for part in PARTS], self.train,
                                len(self.frames))

    def world_corrections(self):
        """Per frame, the 4x4 world-space move ``W`` of its sensors."""
        tab = self.table()
        return [P @ correction_matrix(c) @ np.linalg.inv(P) for P, c in zip(self.pivot, tab)]

    def bake(self) -> None:
        """Move every frame's sensors and traced rays to the corrected poses."""
        with dr.suspend_grad():
            for f, W, cam, lid in zip(self.frames, self.world_corrections(), self.base_camera,
                                      self.base_lidar):
                if cam is not None:
                    _set_to_world(f.camera.sensor, W @ cam[0])
                    f.camera.rays = _transform_rays(cam[1], W)
                if lid is not None:
                    _set_to_world(f.lidar.sensor, W @ lid[0])
                    f.lidar.rays = _transform_rays(lid[1], W)

    def corrected_frames(self, frames):
        """A copy of ``frames`` (:class:`~mi_invrgbl.scene.frames.Frames`)
        whose camera and LiDAR poses are the corrected ones."""
        out = copy.deepcopy(frames)
        moves = self.world_corrections()
        for record in out.frames:
            k = self.position.get(record.index)
            if k is None:
                continue
            record.camera_to_world = moves[k] @ record.camera_to_world
            record.lidar_to_world = moves[k] @ record.lidar_to_world
        return out

    def summary(self) -> dict:
        """The largest and median correction over the training frames
        (metres; degrees), for metrics.json and the log."""
        tab = self.table()[self.train]
        t = np.linalg.norm(tab[:, :3], axis=1)
        r = np.degrees(np.linalg.norm(tab[:, 3:], axis=1))
        return {"translation_m_median": round(float(np.median(t)), 4),
                "translation_m_max": round(float(t.max()), 4),
                "rotation_deg_median": round(float(np.median(r)), 4),
                "rotation_deg_max": round(float(r.max()), 4)}

    def state_dict(self) -> dict:
        return {self.key(*k): np.array(dr.detach(v), np.float32) for k, v in self.values.items()}

    def load_state_dict(self, state) -> None:
        for k in self.values:
            v = state.get(self.key(*k))
            if v is not None and v.size == 3 * len(self.frames):
                self.values[k] = jit_array(mi.Float, v)


class _RigView(FrameView):
    """A training frame's image, projection, and the static points it sees
    from its import pose (in front at their pixel, within :data:`DEPTH`;
    at most :data:`MAX_POINTS`, chosen at random with a fixed seed)."""

    def __init__(self, frame, points):
        super().__init__(frame)
        P = self.proj
        h, w = self.image.shape[:2]
        p = (np.asarray(points, np.float64) - P.o) @ P.R
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            col = np.floor(P.cx[0] * p[:, 0] / z + P.cx[1]).astype(np.int64)
            row = np.floor(P.cy[0] * p[:, 1] / z + P.cy[1]).astype(np.int64)
        ok = (z > DEPTH[0]) & (z < DEPTH[1]) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
        pix = row[ok] * w + col[ok]
        nearest = np.full(h * w, np.inf)
        np.minimum.at(nearest, pix, z[ok])
        # In front at its pixel: within 5 % of the nearest point there.
        front = z[ok] <= nearest[pix] * 1.05
        valid = frame.camera.valid() if hasattr(frame.camera, "valid") else np.ones(h * w, bool)
        keep = np.nonzero(ok)[0][front & valid[pix]]
        if keep.size > MAX_POINTS:
            keep = np.random.default_rng(0).choice(keep, MAX_POINTS, replace=False)
        self.points = np.asarray(points, np.float64)[keep]

    def sample(self, world, move=None):
        """Colours of ``world`` points moved by the 4x4 ``move`` first (the
        inverse of a correction's world move: sampling the moved points from
        the import pose is sampling the points from the corrected pose)."""
        if move is not None:
            world = world @ move[:3, :3].T + move[:3, 3]
        return super().sample(world)
