"""Gaussians no training sensor saw.

The import adds Gaussians no sensor measured: facades continued upward
above the LiDAR's top beam (``import --extend-walls``, 10 m by default), whose
true height the LiDAR cannot see. Stage 1 keeps what the cameras confirm
and removes what they see through (the sky term, :mod:`.sky_lookalikes`);
the part that no training camera looks at and no training LiDAR beam
reaches gets no gradient at all and stays as imported. The cameras on a
street look along it, a few degrees above the horizon: they see the upper
floors of the buildings far ahead and none of those beside the car. So a
wall extension above a roof lower than it stays wherever no camera looked
past that roof. The camera images do not care, but light does: on the
synthetic street 72 % of the Gaussians that shadowed surfaces the truth
leaves sunlit under a low sun (relighting) stood more than a metre above
the true roof below them, 78 % of those were seen by no training camera,
and the extended walls also hide sky from the street (stage 2's sky
visibility) that is there.

A Gaussian is *unseen* when its blend weight summed over every training
camera pixel (the fit's own rays, masked pixels left out) and over every
training LiDAR beam the fit uses stays below ``min_weight``: no
observation depends on it, so removing it leaves every training image and
scan as it renders. What it would have added (shadows, occluded sky) is a
guess the data never confirmed; a building whose upper floors no camera saw
loses them. A node none of whose Gaussians is seen (an object outside every
training view) is left whole: there is nothing to tell its conjecture from
its measurement.
"""

from __future__ import annotations

import numpy as np
import drjit as dr

from ..physics import hits as hitlib


def frame_weights(scene, rays, max_hits, valid=None):
    """Per Gaussian hit of ``rays``: ``(node ids, prims, blend weight)``;
    ``valid`` (a bool per ray or None) leaves the other rays' hits out."""
    nodes = hitlib.gaussian_nodes(scene)
    hl = hitlib.trace(scene, rays, max_hits, 1e-3, nodes)
    g = hitlib.eval_gaussian_hits(nodes, rays, hl)
    w, _ = hitlib.blend_weights(g)
    n = dr.width(g.slot)
    active = np.broadcast_to(np.array(g.active, bool), (n,)) \
        & (np.array(g.slot) < g.n_rays * g.max_hits)
    w = np.broadcast_to(np.array(w, np.float64), (n,))
    if valid is not None:
        ray = np.broadcast_to(np.array(g.ray, np.int64), (n,))
        w = np.where(np.asarray(valid, bool)[np.minimum(ray, len(valid) - 1)], w, 0.0)
    ids = np.broadcast_to(np.array(g.node_ids, np.uint32), (n,))
    prims = np.broadcast_to(np.array(g.prims, np.int64), (n,))
    return ids[active], prims[active], w[active]


def accumulate(acc, shape_ids, stats):
    """Add one pass's :func:`frame_weights` into ``acc`` ({node: (count,) summed weight})."""
    ids, prims, w = stats
    for name, sid in shape_ids.items():
        m = ids == sid
        acc[name] += np.bincount(prims[m], w[m], minlength=acc[name].shape[0])[:acc[name].shape[0]]


def unseen_masks(acc, min_weight=0.05):
    """Per node: summed weight below ``min_weight``; a node with no seen
    Gaussian at all is kept whole (all False)."""
    return {name: (a < min_weight) if np.any(a >= min_weight) else np.zeros(a.shape, bool)
            for name, a in acc.items()}


def find_unseen(ctx, frames, min_weight=0.05, stage=1):
    """Boolean mask per node name: Gaussians whose blend weight, summed over
    every camera pixel and LiDAR beam of ``frames``, stays below ``min_weight``."""
    acc = {name: np.zeros(node.count) for name, node in ctx.model.nodes.items()}
    max_hits = max(ctx.config.max_hits, 64)
    with dr.suspend_grad():
        for f in frames:
            ctx.model.push(f.poses, stage=stage)
            for obs in (f.camera, f.lidar):
                if obs is None or obs.rays is None:
                    continue
                accumulate(acc, ctx.model.shape_ids,
                           frame_weights(ctx.scene, obs.rays, max_hits, obs.valid()))
    return unseen_masks(acc, min_weight)
