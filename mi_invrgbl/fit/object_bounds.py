"""Moving objects' Gaussians kept inside the box their label gives them.

A moving object is a rigid node: whatever its Gaussians draw moves with it.
Stage 1 fits colour without light, so a car's shadow on the road, which
moves with the car, is drawn best by the car's own Gaussians: on the
synthetic street the lowest ones grew flat and 0.6-1.2 m wide, reached up to
1.9 m past the car's box and painted the shadow dark onto the road, with
normals of the car's, not the road's. In the held-out frames the pixels of
other meshes within 15 pixels of the car came out 24.7 deg off the truth's
normal on average, 2.85 deg of the street's 15.1 deg mean normal error
(``tests/bench/albedo_breakdown.py``). A shadow belongs to the light
(``fit --per-frame-visibility`` traces it per frame), not to the object's
shape.

So after every stage-1 step each Gaussian of a moving object whose whole
extent the import knew (a labelled object, :func:`boxed_objects`) is held
inside the box (object frame) spanned by the import's Gaussian centres for
it (the LiDAR points in the label's box grown by the import's margin, and
samples on the box's sides and top where they were few): its centre is clipped into that box grown by
:data:`CENTRE_MARGIN`, and where its support (:data:`SUPPORT` standard
deviations along the box's axes, through its rotation) reaches more than
:data:`MARGIN` past a face, all three of its scales shrink by the same
factor until it fits. Tracks the import found by LiDAR motion are left
free: their box is only what the LiDAR saw of them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import drjit as dr
import mitsuba as mi

from ..io.motion import FROM_LIDAR_MOTION
from ..physics.fields import BY_NAME

#: Metres a Gaussian's support may reach beyond the import's outermost
#: centres: room for the surface Gaussians' own extent.
MARGIN = 0.1
#: Metres a centre may move beyond them; less than :data:`MARGIN`, so that a
#: clipped centre keeps room for a Gaussian of about 2 cm.
CENTRE_MARGIN = 0.05
#: Standard deviations of a Gaussian's support (the ``gaussians`` shape's
#: ``extent``, 3: the traversal ignores it beyond).
SUPPORT = 3.0
#: Smallest factor one step may shrink a Gaussian by (the log-scale's own
#: floor applies after this).
MIN_FACTOR = 1e-3


@dataclass
class ObjectBox:
    """Axis-aligned box of one moving node's imported centres, in the node's own frame."""
    node: str
    lo: np.ndarray
    hi: np.ndarray

    @classmethod
    def around(cls, node: str, centers: np.ndarray) -> "ObjectBox | None":
        """The box of ``centers`` (N x 3, object frame); None without finite centres."""
        c = np.asarray(centers, np.float64).reshape(-1, 3)
        c = c[np.all(np.isfinite(c), axis=1)]
        if not len(c):
            return None
        return cls(node, c.min(0), c.max(0))

    def keys(self):
        return tuple("%s.%s" % (self.node, BY_NAME[f].variable) for f in ("center", "scale", "rotation"))

    def apply(self, adam) -> None:
        """Clip the node's centres into the box and shrink the Gaussians
        whose support leaves it (in place in ``adam``, Adam's state kept)."""
        kc, ks, kq = self.keys()
        if not all(k in adam for k in (kc, ks, kq)):
            return
        n = dr.width(adam[kc]) // 3
        if n == 0:
            return
        idx3, idx4 = dr.arange(mi.UInt32, n) * 3, dr.arange(mi.UInt32, n) * 4
        with dr.suspend_grad():
            c_flat, s_flat, q_flat = (dr.detach(adam[k]) for k in (kc, ks, kq))
            c = [dr.gather(mi.Float, c_flat, idx3 + k) for k in range(3)]
            log_s = [dr.gather(mi.Float, s_flat, idx3 + k) for k in range(3)]
            q = mi.Quaternion4f(*[dr.gather(mi.Float, q_flat, idx4 + k) for k in range(4)])
            # As the renderer reads it (physics.hits.gather_geometry): normalised.
            q = q * dr.rsqrt(dr.maximum(dr.squared_norm(q), 1e-20))
            # Row a: the box's axis a in the Gaussian's own axes.
            rows = dr.quat_to_matrix(mi.Matrix3f, q)
            s2 = [dr.square(dr.exp(v)) for v in log_s]
            factor = mi.Float(1.0)
            for a in range(3):
                lo, hi = float(self.lo[a]) - MARGIN, float(self.hi[a]) + MARGIN
                c[a] = dr.clip(c[a], lo + (MARGIN - CENTRE_MARGIN), hi - (MARGIN - CENTRE_MARGIN))
                reach = SUPPORT * dr.sqrt(sum(dr.square(rows[a][j]) * s2[j] for j in range(3)))
                room = dr.minimum(c[a] - lo, hi - c[a])
                factor = dr.minimum(factor, room / dr.maximum(reach, 1e-12))
            shrink = dr.log(dr.clip(factor, MIN_FACTOR, 1.0))
            c_new, s_new = dr.zeros(mi.Float, 3 * n), dr.zeros(mi.Float, 3 * n)
            for k in range(3):
                dr.scatter(c_new, c[k], idx3 + k)
                dr.scatter(s_new, log_s[k] + shrink, idx3 + k)
        adam[kc] = c_new
        adam[ks] = s_new


def boxed_objects(frames) -> set:
    """Names of the objects whose extent the import knew: every object of
    ``frames`` except those its ``tracks`` report found by LiDAR motion. A
    label (or a box written by hand) spans the whole object; a track found
    in the sweeps has the box of the points the LiDAR saw of it, often one
    side or the lower half (the top beam cuts a truck; a car seen from
    behind has no front), and the cameras see more of it than that. On the
    KITTI excerpt, whose seven tracks are all found by motion, holding
    their Gaussians in those boxes cost 0.85 dB held-out at 30 minutes
    (21.48 against 22.33 dB, one run each)."""
    found = {int(t["track_id"]) for t in frames.extra.get("tracks") or []
             if isinstance(t, dict) and "track_id" in t and t.get("from") == FROM_LIDAR_MOTION}
    return {name for name, o in frames.objects.items() if o.track_id not in found}


def object_boxes(model, names) -> list:
    """One :class:`ObjectBox` per moving node of ``model`` named in
    ``names``, from its current (the import's) centres; nodes without
    Gaussians get none."""
    out = []
    for name, node in model.nodes.items():
        if node.dynamic and node.count and name in names:
            box = ObjectBox.around(name, node.numpy(BY_NAME["center"].variable))
            if box is not None:
                out.append(box)
    return out
