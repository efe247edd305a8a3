"""Per-frame corrections of the moving objects' poses, fitted in stage 1.

The import gives every moving object a pose per frame: KITTI tracklets, or
rigid registration of its LiDAR points (:mod:`mi_invrgbl.io.motion`).
Registration slides along shapes that do not pin it down -- a tanker's
cylinder along its axis -- and an object was held where it was last seen.
On the KITTI excerpt the tanker beside the car is 0.22-0.34 m off between
frames two apart in the first ten frames (the colour of its LiDAR points,
projected into both images, agrees best that far along its axis), and
the truck cab beside it 0.34-0.50 m a frame pair once its track ended
(``tests/bench/object_pose_check.py``). The images then
see the object in other places than its Gaussians are, and stage 1 smears
it.

So stage 1 starts, per moving object and training frame, from the offset
along the object's heading that makes its colours agree between
neighbouring training images (:meth:`ObjectPoseFit.align_from_images`), and
fits a rigid correction in the object's own frame (translation ``t`` in metres and a
rotation vector ``w`` in radians)::

    world_from_object' = world_from_object @ [R(w) | t]

from the same losses as the Gaussians (colour and LiDAR range: both see
the object where it is). Frames that take no gradient steps -- validation
and held-out frames -- are given the correction interpolated linearly in
frame index between the nearest training frames (held at the ends): the
images of those frames are never read. :meth:`ObjectPoseFit.bake` writes
the corrected poses into every frame's ``poses``; everything after stage 1
(freezing, stage 2, the outputs, ``eval`` through the fit's own
``frames.json``) uses them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import drjit as dr
import mitsuba as mi

from ..scene.posing import rotation_to_quat_xyzw
from ..physics.host_arrays import jit_array

#: Adam learning rates of the correction: metres and radians per step.
#: Adam moves a value by about its rate per step that has a gradient, and a
#: frame takes a step every ~24 iterations on the KITTI excerpt (frames out
#: of view take none): the steps refine what the heading search
#: (:meth:`ObjectPoseFit.align_from_images`) found, a few millimetres a
#: visit, and follow the positions' schedule down to 1 % as a budgeted stage
#: 1 ends (``fit.runner``).
TRANSLATION_LR = 3e-3
ROTATION_LR = 1e-3
#: Largest correction: beyond it the object's track is wrong, not noisy.
MAX_TRANSLATION = 2.0      # metres, per axis
MAX_ROTATION = 0.2         # radians, per axis (11 degrees)
#: Values per frame in a correction table: tx, ty, tz, wx, wy, wz.
WIDTH = 6
#: The two optimised parts of a correction: translation and rotation vector.
PARTS = {"t": (TRANSLATION_LR, MAX_TRANSLATION), "w": (ROTATION_LR, MAX_ROTATION)}


@dataclass
class RigidPose:
    """A node -> world rigid transform in Dr.Jit form (differentiable when
    built from the fitted corrections)."""
    rotation: mi.Matrix3f
    translation: mi.Vector3f
    quaternion: mi.Quaternion4f        # the same rotation, x y z w

    @classmethod
    def from_matrix(cls, m) -> "RigidPose":
        """The pose of a 4x4 matrix. Its numbers enter the kernels as
        parameters (``dr.opaque``), not as constants: a pose that changes
        between renders (every frame, every step of the corrections) would
        otherwise compile new kernels each time."""
        m = np.asarray(m, np.float64)
        q = rotation_to_quat_xyzw(m[:3, :3])
        value = lambda x: dr.opaque(mi.Float, float(x))  # noqa: E731
        return cls(mi.Matrix3f(*[value(x) for x in m[:3, :3].ravel()]),
                   mi.Vector3f(*[value(x) for x in m[:3, 3]]),
                   mi.Quaternion4f(*[value(x) for x in q]))

    def corrected(self, t: mi.Vector3f, w: mi.Vector3f) -> "RigidPose":
        """``self @ [R(w) | t]`` (the correction in the node's own frame).

        ``R(w)`` is the unit quaternion ``(w / 2, 1)`` normalised: exact to
        first order and smooth through ``w = 0``, where the corrections start."""
        qd = mi.Quaternion4f(0.5 * w.x, 0.5 * w.y, 0.5 * w.z, 1.0)
        qd = qd * dr.rsqrt(dr.squared_norm(qd))
        q = self.quaternion * qd
        return RigidPose(dr.quat_to_matrix(mi.Matrix3f, q),
                         self.rotation @ t + self.translation, q)


def correction_matrix(c) -> np.ndarray:
    """The 4x4 ``[R(w) | t]`` of one correction ``(tx, ty, tz, wx, wy, wz)``
    (numpy; the same rotation as :meth:`RigidPose.corrected`)."""
    from ..physics.gaussian_ply import quaternion_to_matrix
    c = np.asarray(c, np.float64)
    q = np.concatenate([[1.0], 0.5 * c[3:]])          # w x y z, normalised below
    out = np.eye(4)
    out[:3, :3] = quaternion_to_matrix((q / np.linalg.norm(q))[None])[0]
    out[:3, 3] = c[:3]
    return out


def interpolate(known_index, known_values, index):
    """Linear interpolation of per-frame rows ``known_values`` (K x WIDTH) at
    frame ``index``, held beyond the first and last known frame."""
    known_index = np.asarray(known_index)
    return np.stack([np.interp(index, known_index, known_values[:, j])
                     for j in range(known_values.shape[1])], axis=-1)


class ObjectPoseFit:
    """The corrections of every moving object at every frame and the
    import's poses they correct. Per object and part (``t``, ``w``: see
    :data:`PARTS`) one flat ``mi.Float`` of 3 values per frame, in frame
    order."""

    def __init__(self, observations, train_frames, objects):
        self.frames = list(observations)
        self.position = {f.index: k for k, f in enumerate(self.frames)}
        self.train = sorted({self.position[f.index] for f in train_frames})
        self.objects = [n for n in objects
                        if any(n in f.poses for f in self.frames)]
        # The import's poses, kept: corrections always apply to these.
        self.base = [{n: np.array(p, np.float64) for n, p in f.poses.items()} for f in self.frames]
        self.values = {(n, part): dr.zeros(mi.Float, 3 * len(self.frames))
                       for n in self.objects for part in PARTS}

    def __bool__(self):
        return bool(self.objects) and bool(self.train)

    # ------------------------------------------------------------ stage 1
    def poses(self, frame) -> dict:
        """Node -> world poses at a training frame, differentiable in the
        corrections (other nodes of the frame keep their matrices)."""
        k = self.position[frame.index]
        out = dict(self.base[k])
        for name in self.objects:
            if name not in out:
                continue
            # (opaque indices: one compiled kernel serves every frame)
            t, w = (mi.Vector3f(*[dr.gather(mi.Float, self.values[name, part],
                                            dr.opaque(mi.UInt32, 3 * k + j)) for j in range(3)])
                    for part in PARTS)
            out[name] = RigidPose.from_matrix(out[name]).corrected(t, w)
        return out

    # ------------------------------------------------------------ host side
    def table(self, name) -> np.ndarray:
        """(frames, WIDTH) corrections of ``name``: fitted at training frames,
        interpolated elsewhere."""
        fitted = np.concatenate([np.array(dr.detach(self.values[name, part]), np.float64).reshape(-1, 3)
                                 for part in PARTS], axis=1)
        out = fitted.copy()
        trained = set(self.train)
        others = [k for k in range(len(self.frames)) if k not in trained]
        if others:
            out[others] = interpolate(self.train, fitted[self.train], np.asarray(others))
        return out

    def bake(self) -> None:
        """Write the corrected poses (numpy) into every frame's ``poses``."""
        tables = {n: self.table(n) for n in self.objects}
        for k, f in enumerate(self.frames):
            poses = dict(self.base[k])
            for n, tab in tables.items():
                if n in poses:
                    poses[n] = poses[n] @ correction_matrix(tab[k])
            f.poses = poses

    # ------------------------------------------------------------ start
    def align_from_images(self, model, log=None) -> dict:
        """Start the corrections from a search along each object's heading.

        The gradient steps move a correction about its learning rate per
        visit of a frame and see only a few pixels' width around the current
        pose; the tracks' errors are tens of centimetres along the heading
        (:mod:`.object_poses`). So first, per object, each training frame's
        offset along the object's x axis is searched on a grid (+-
        :data:`SEARCH` m): the object's Gaussian centres, projected into two
        training frames at their corrected poses, should sample the same
        colours (coordinate descent over the frames against their
        :data:`NEIGHBOURS` nearest training frames on each side, with a cost
        per metre of jump between them (:data:`SMOOTHNESS`), :data:`SWEEPS`
        sweeps, the median offset taken out: the object's own frame is
        free). Frames where fewer than :data:`MIN_POINTS` centres
        are seen in both images of every pair keep no offset of their own
        (interpolated like frames without steps). An object whose colours
        agree less than :data:`MIN_GAIN` better than at the import's poses
        keeps them. Only training images are read. Returns, per object, the
        offsets and the mean colour differences before and after.
        """
        report = {}
        views = [_FrameView(self.frames[k]) for k in self.train]
        for name in self.objects:
            pts = model.cloud(name).centers.astype(np.float64)
            if len(pts) > MAX_POINTS:
                pts = pts[np.random.default_rng(0).choice(len(pts), MAX_POINTS, replace=False)]
            offsets, before, after = _align(views, [self.base[k].get(name) for k in self.train], pts)
            ok = np.isfinite(offsets)
            used = bool(ok.sum() >= 2 and after < (1.0 - MIN_GAIN) * before)
            report[name] = {"mean_colour_difference": [round(before, 5), round(after, 5)],
                            "frames_aligned": int(ok.sum()), "used": used}
            if not used:
                continue
            known = np.asarray(self.train)[ok]
            full = np.interp(np.asarray(self.train), known, offsets[ok])
            t = np.array(dr.detach(self.values[name, "t"]), np.float64).reshape(-1, 3)
            t[self.train, 0] = full
            self.values[name, "t"] = jit_array(mi.Float, t)
            report[name]["offset_m"] = [round(float(v), 3) for v in full]
            if log is not None:
                log("[fit] %s: poses moved along its heading by up to %.2f m (median %.2f m) at "
                    "the training frames; colour difference between frames %.4f -> %.4f"
                    % (name, np.abs(full).max(), np.median(np.abs(full)), before, after))
        return report

    def corrected_frames(self, frames):
        """A copy of ``frames`` (:class:`~mi_invrgbl.scene.frames.Frames`)
        whose object poses are the corrected ones: the fit writes it as its
        own ``frames.json``, which ``eval`` then reads."""
        import copy
        out = copy.deepcopy(frames)
        tables = {n: self.table(n) for n in self.objects}
        for record in out.frames:
            k = self.position.get(record.index)
            if k is None:
                continue
            for n, tab in tables.items():
                if n in record.objects and n in self.base[k]:
                    record.objects[n] = self.base[k][n] @ correction_matrix(tab[k])
        return out

    def summary(self) -> dict:
        """Per object: the largest and the median correction over the training
        frames (metres; degrees), for metrics.json and the log."""
        out = {}
        for n in self.objects:
            tab = self.table(n)[self.train]
            t = np.linalg.norm(tab[:, :3], axis=1)
            r = np.degrees(np.linalg.norm(tab[:, 3:], axis=1))
            out[n] = {"translation_m_median": round(float(np.median(t)), 4),
                      "translation_m_max": round(float(t.max()), 4),
                      "rotation_deg_median": round(float(np.median(r)), 3),
                      "rotation_deg_max": round(float(r.max()), 3)}
        return out

    @staticmethod
    def key(name, part) -> str:
        """The correction's name in Adam and in checkpoints."""
        return "pose.%s.%s" % (name, part)

    def state_dict(self) -> dict:
        return {self.key(*k): np.array(dr.detach(v), np.float32) for k, v in self.values.items()}

    def load_state_dict(self, state) -> None:
        for k in self.values:
            v = state.get(self.key(*k))
            if v is not None and v.size == 3 * len(self.frames):
                self.values[k] = jit_array(mi.Float, v)


#: The heading search of :meth:`ObjectPoseFit.align_from_images`: range and
#: step (metres), neighbours on each side, sweeps, least centres seen in both
#: images of a pair, least relative gain to keep the result, and the most
#: centres an object is searched with.
SEARCH = 0.6
SEARCH_STEP = 0.03
NEIGHBOURS = 2
SWEEPS = 4
MIN_POINTS = 100
MIN_GAIN = 0.05
MAX_POINTS = 4000
#: Cost of a jump between neighbouring frames' offsets, per metre, in units
#: of the mean colour difference (linear RGB): aligning the KITTI excerpt's
#: tanker lowers that difference by about 0.005, which buys a 0.3 m jump.
SMOOTHNESS = 0.015


class _FrameView:
    """A training frame's image and pinhole projection (numpy)."""

    def __init__(self, frame):
        from .sky_mask import PinholeProjection
        cam = frame.camera
        self.image = None if cam is None else \
            np.ascontiguousarray(cam.image.reshape(cam.height, cam.width, 3), np.float32)
        if cam is not None:
            T = np.array(cam.sensor.world_transform().matrix, np.float64).reshape(4, 4)
            d = np.stack([np.array(cam.rays.d[k]) for k in range(3)], 1)
            self.proj = PinholeProjection(T, d, cam.width, cam.height)

    def sample(self, world):
        """Colours (N, 3) at the projections of ``world`` (N, 3), and which
        of them land in the image in front of the camera."""
        import cv2
        n = len(world)
        if self.image is None:
            return np.zeros((n, 3), np.float32), np.zeros(n, bool)
        P = self.proj
        p = (world - P.o) @ P.R
        z = np.maximum(p[:, 2], 1e-6)
        col = P.cx[0] * p[:, 0] / z + P.cx[1] - 0.5
        row = P.cy[0] * p[:, 1] / z + P.cy[1] - 0.5
        h, w = self.image.shape[:2]
        ok = (p[:, 2] > 0.5) & (col >= -0.5) & (col <= w - 0.5) & (row >= -0.5) & (row <= h - 0.5)
        c = cv2.remap(self.image, col.astype(np.float32)[None], row.astype(np.float32)[None],
                      cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)[0]
        return c, ok


def _align(views, poses, points):
    """Per-frame offsets along the object's x axis (NaN: not aligned) and the
    mean colour difference between neighbouring frames at zero offsets and
    at the offsets found (see :meth:`ObjectPoseFit.align_from_images`)."""
    grid = np.arange(-SEARCH, SEARCH + 1e-9, SEARCH_STEP)
    K = len(views)
    samples = [[None] * len(grid) for _ in range(K)]
    for k, (view, T) in enumerate(zip(views, poses)):
        if T is None or view.image is None:
            continue
        for j, dx in enumerate(grid):
            q = points + [dx, 0.0, 0.0]
            samples[k][j] = view.sample(q @ T[:3, :3].T + T[:3, 3])
    zero = int(np.argmin(np.abs(grid)))
    pairs = [(a, b) for a in range(K) for b in range(a + 1, min(K, a + NEIGHBOURS + 1))
             if samples[a][0] is not None and samples[b][0] is not None]

    def diff(a, ja, b, jb):
        (ca, oa), (cb, ob) = samples[a][ja], samples[b][jb]
        m = oa & ob
        return (float(np.abs(ca[m] - cb[m]).mean()), int(m.sum())) if m.sum() else (np.nan, 0)

    # Pairs seen well enough at the import's poses take part.
    pairs = [(a, b) for a, b in pairs if diff(a, zero, b, zero)[1] >= MIN_POINTS]
    if not pairs:
        return np.full(K, np.nan), float("nan"), float("nan")
    choice = np.full(K, zero)

    def total():
        return float(np.nanmean([diff(a, choice[a], b, choice[b])[0] for a, b in pairs]))
    before = total()
    members = sorted({k for p in pairs for k in p})
    for _ in range(SWEEPS):
        for k in members:
            mine = [(a, b) for a, b in pairs if k in (a, b)]
            cost = []
            for j in range(len(grid)):
                others = [b if a == k else a for a, b in mine]
                vals = [diff(k, j, o, choice[o]) for o in others]
                good = [v for v, n in vals if n >= MIN_POINTS]
                # A rigid object's track errs smoothly: jumps between
                # neighbouring frames cost SMOOTHNESS per metre.
                jump = np.mean([abs(grid[j] - grid[choice[o]]) for o in others])
                cost.append(np.mean(good) + SMOOTHNESS * jump if len(good) == len(vals) else np.inf)
            choice[k] = int(np.argmin(cost)) if np.isfinite(np.min(cost)) else choice[k]
    after = total()
    offsets = np.full(K, np.nan)
    offsets[members] = grid[choice[members]]
    offsets -= np.nanmedian(offsets)
    return offsets, before, after
