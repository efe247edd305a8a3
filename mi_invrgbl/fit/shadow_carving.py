"""Gaussians that cast the sun's shadow where the images show sunlight.

Stage 2 learns each Gaussian's sun visibility from the images; the fitted
scene's own sun reads it. A relit scene (``relight``, ``night``, ``insert``,
``eval``'s time B) traces the sun's shadows through the Gaussians instead,
and there geometry no camera saw casts shadows that no image could check:
the import continues facades above the LiDAR's top beam, and above a roof
lower than the continuation it stands for nothing. Traced from the fitted
street's sunlit Gaussians towards the fitted sun, one in ten came out
shadowed, most of them by such Gaussians.

The images do say where the sun reached: a Gaussian the cameras see,
facing the sun, that stage 2 learned as sunlit (visibility at least
:data:`LIT`) had a clear path to the sun. A Gaussian on that path that no camera and no LiDAR beam
sees contradicts it, and nothing speaks for it. *Shadow carving* traces a
shadow ray from every such receiver (from :data:`~mi_invrgbl.physics.lighting.SHADOW_OFFSET`
above it, as relighting does) and drops the unseen static Gaussians whose
blend weight, summed over the receivers' rays, reaches :data:`MIN_WEIGHT`.
It repeats with them gone (a ray's later blockers then carry the weight),
at most :data:`ROUNDS` times.

What it cannot reach: a wrong wall that shadows nothing the images show lit
at the fitted time of day, but does at another. The training images are
untouched by construction (only Gaussians no training camera sees go), and
so is the LiDAR's view. Measured on the synthetic street ("Shadow carving",
docs/measurements.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import drjit as dr
import mitsuba as mi

from ..physics import hits as hitlib
from ..physics.lighting import GaussianTable, point_lights, shadow_blockers, shadow_origins
from ..physics.host_arrays import jit_array
from .shading_init import seen_weight

#: Learned sun visibility from which a seen Gaussian counts as sunlit.
LIT = 0.5
#: Least cosine between a receiver's normal and the sun: a Gaussian turned
#: away from the sun gets no gradient on its learned visibility (its sun term
#: is zero), which then says nothing of the path to the sun; its shadow ray
#: would also start behind its own surface and cross the unseen back layers.
COS_MIN = 0.1
#: Summed blend weight on sunlit receivers' shadow rays that drops an unseen
#: Gaussian (one receiver whose ray it blocks by a tenth of the light).
MIN_WEIGHT = 0.1
#: Summed camera (or LiDAR) blend weight above which a Gaussian counts as seen
#: (the value stage 2's start uses for its seen Gaussians).
SEEN = 0.05
#: Most passes of tracing and dropping.
ROUNDS = 4


@dataclass
class CarvingReport:
    """What :func:`carve_unseen_blockers` did: receivers traced, Gaussians
    dropped per round, and the share of the receivers' shadow rays that the
    traced Gaussians left below half the sun before and after."""
    receivers: int
    dropped: list
    shadowed_before: float
    shadowed_after: float

    def as_dict(self):
        return {"receivers": self.receivers, "dropped_per_round": self.dropped,
                "receivers_shadowed_before": round(self.shadowed_before, 4),
                "receivers_shadowed_after": round(self.shadowed_after, 4)}


def _set_dropped(params, nodes, table, opacity0, dropped):
    """The scene's opacities with ``dropped`` (global mask) at 0."""
    for node, off in zip(table.nodes, table.offsets):
        key = "%s.opacities" % node.shape.id()
        values = np.where(dropped[off:off + node.count], 0.0, opacity0[key])
        params[key] = jit_array(mi.Float, values.astype(np.float32))
    params.update()


def carve_unseen_blockers(scene, receivers, droppable, direction, min_weight=MIN_WEIGHT,
                          rounds=ROUNDS):
    """Gaussians of ``scene`` that block the sun from the ``receivers``.

    ``receivers`` and ``droppable`` are boolean masks over the scene's
    Gaussians in :class:`~mi_invrgbl.physics.lighting.GaussianTable` order
    (:func:`~mi_invrgbl.physics.hits.gaussian_nodes`); ``direction`` points
    towards the sun. Returns ``(dropped mask, CarvingReport)``: the
    ``droppable`` Gaussians whose blend weight on the receivers' shadow rays
    sums to ``min_weight`` or more, over up to ``rounds`` passes. The scene's
    opacities are as they were on return.
    """
    nodes = hitlib.gaussian_nodes(scene)
    table = GaussianTable.build(nodes)
    receivers = np.asarray(receivers, bool).ravel()
    droppable = np.asarray(droppable, bool).ravel()
    if receivers.size != table.total or droppable.size != table.total:
        raise ValueError("carve_unseen_blockers: masks of %d and %d for %d Gaussians"
                         % (receivers.size, droppable.size, table.total))
    d = np.asarray(direction, np.float64).ravel()
    if d.size != 3 or not np.all(np.isfinite(d)) or np.linalg.norm(d) == 0:
        raise ValueError("carve_unseen_blockers: the sun's direction %s is not a direction" % (d,))
    d = d / np.linalg.norm(d)
    dropped = np.zeros(table.total, bool)
    rows = np.flatnonzero(receivers)
    report = CarvingReport(int(rows.size), [], 0.0, 0.0)
    if rows.size == 0 or not droppable.any():
        return dropped, report
    params = mi.traverse(scene)
    opacity0 = {"%s.opacities" % n.shape.id(): np.array(params["%s.opacities" % n.shape.id()],
                                                        np.float64).ravel() for n in nodes}
    towards = [float(x) for x in d]
    try:
        with dr.suspend_grad():
            for rnd in range(rounds + 1):
                geometry = GaussianTable.build(nodes).load_geometry()
                dirs = dr.zeros(mi.Vector3f, table.total) + mi.Vector3f(*towards)
                origins = np.array(shadow_origins(geometry, dirs), np.float32).T[rows]
                o = mi.Point3f(*[jit_array(mi.Float, origins[:, k]) for k in range(3)])
                dv = dr.zeros(mi.Vector3f, rows.size) + mi.Vector3f(*towards)
                vis, _, source, weight = shadow_blockers(scene, o, dv, mi.Float(dr.inf), nodes, geometry)
                shadowed = float(np.mean(np.array(vis) < 0.5))
                if rnd == 0:
                    report.shadowed_before = shadowed
                report.shadowed_after = shadowed
                if rnd == rounds or source is None:
                    break
                blame = np.bincount(np.array(source, np.int64), np.array(weight, np.float64),
                                    minlength=table.total)
                new = droppable & ~dropped & (blame >= min_weight)
                if not new.any():
                    break
                report.dropped.append(int(new.sum()))
                dropped |= new
                _set_dropped(params, nodes, table, opacity0, dropped)
    finally:
        _set_dropped(params, nodes, table, opacity0, np.zeros(table.total, bool))
    return dropped, report


def sunlit(visibility, normals, direction):
    """Receivers' sunlit test: learned visibility at least :data:`LIT` on a
    Gaussian whose (oriented) normal faces the sun by :data:`COS_MIN`."""
    n = np.asarray(normals, np.float64).reshape(-1, 3)
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    d = np.asarray(direction, np.float64).ravel()
    cos = n @ (d / max(np.linalg.norm(d), 1e-12))
    return (np.asarray(visibility, np.float64).ravel() >= LIT) & (cos >= COS_MIN)


def carve_fit(ctx, frozen):
    """Shadow carving for a fit after stage 2: per node name, the boolean mask
    of its Gaussians to leave out of the fitted scene, and the report (or
    ``({}, None)`` without a sun whose visibility stage 2 learned).

    Receivers are the static Gaussians the training and validation cameras
    see (:data:`SEEN`) that face the sun and whose learned sun visibility is
    at least :data:`LIT` (:func:`sunlit`);
    droppable are the static Gaussians no such camera and no LiDAR beam sees."""
    suns = [e for kind, e in point_lights(ctx.scene) if kind == "sun"]
    if not suns or not ctx.sun_visibility_learned:
        return {}, None
    direction = np.array(dr.detach(suns[0].sun_direction_world()), np.float64).ravel()
    nodes = hitlib.gaussian_nodes(ctx.scene)
    table = GaussianTable.build(nodes)
    frames = [f for f in list(ctx.train_frames) + list(ctx.validation_frames)]
    camera = seen_weight(table, [(frozen.camera[f.index], f.camera.valid()) for f in frames
                                 if f.index in frozen.camera])
    lidar = seen_weight(table, [frozen.lidar[f.index] for f in frames if f.index in frozen.lidar])
    name_of = {sid: name for name, sid in ctx.model.shape_ids.items()}
    static = np.zeros(table.total, bool)
    lit = np.zeros(table.total, bool)
    for node, off in zip(table.nodes, table.offsets):
        name = name_of.get(node.id)
        if name is None or ctx.model.nodes[name].dynamic:
            continue
        static[off:off + node.count] = True
        cloud = ctx.model.cloud(name)
        lit[off:off + node.count] = sunlit(cloud.sun_visibility, cloud.normals, direction)
    seen = camera > SEEN
    dropped, report = carve_unseen_blockers(ctx.scene, static & seen & lit,
                                            static & ~seen & (lidar <= SEEN), direction)
    out = {}
    for node, off in zip(table.nodes, table.offsets):
        name = name_of.get(node.id)
        if name is not None and dropped[off:off + node.count].any():
            out[name] = dropped[off:off + node.count].copy()
    return out, report
