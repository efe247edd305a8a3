"""Gaussians that only stand in for the sky.

Stage 1 fits a view-independent colour per Gaussian and the SH sky behind
them. A Gaussian seen in front of the sky can take the sky's colour; the
image then cannot tell it from empty space, its opacity gets no gradient
and it stays. The import's wall extensions (facades continued above the
LiDAR's top beam, whose height the LiDAR cannot see) end this way above
every roof lower than the extension: walls made of sky. They would cast
shadows and hide sky that is not there, pull the sun search towards
directions that shorten those shadows and darken the albedo under them.

A Gaussian is a *sky look-alike* when it has the sky's colour (within
``tolerance`` of the sky radiance along the rays that see it) and, with
every sky-coloured Gaussian removed from those rays, the camera would see
the sky there (within ``tolerance``), averaged over the training pixels it
contributes to with its blend weight. Removing such Gaussians leaves the
images as they are. The second test keeps a real sky-blue wall in front of
a darker building: removing it would reveal the building. Rays are traced
deep (transmittance down to 1e-4) so that what such a wall hides is found;
a Gaussian seen by any ray cut off before that, or ending on a mesh, is kept.

Above a look-alike, its vertical column (an xy cell of ``COLUMN_CELL``
metres in the node's frame, z up) goes too where no training camera sees it
(summed blend weight at most ``min_weight``): where a camera saw the sky
through the column, what the import extended above that height stands for a
wall no image shows, and it would cast the sun's shadows that the images
never saw. Gaussians above a look-alike that some camera does see keep their
own verdict. On the synthetic street this took the Gaussians above the true
roofs from 13 610 to 8 526 (``tests/bench/walls_above_roofs.py``) with the
real facades untouched; the relit sun's wrong shadows come mostly from
columns no camera saw at all (``tests/bench/shadow_blockers.py``), which it
cannot reach.
"""

from __future__ import annotations

import numpy as np
import drjit as dr
import mitsuba as mi

from ..physics import hits as hitlib
from .render import environment_radiance


def _segment_exclusive_cumsum(values, ray):
    """Per hit, the sum of ``values`` over the earlier hits of its ray (hits grouped by ray)."""
    if values.shape[0] == 0:
        return values.copy()
    incl = np.cumsum(values, axis=0)
    segment = np.cumsum(np.r_[True, ray[1:] != ray[:-1]]) - 1
    starts = np.r_[0, np.nonzero(ray[1:] != ray[:-1])[0] + 1]
    before = np.concatenate([np.zeros((1,) + values.shape[1:]), incl[starts[1:] - 1]])
    return incl - before[segment] - values


def frame_statistics(scene, rays, max_hits=64, min_transmittance=1e-4, tolerance=0.15,
                     valid=None):
    """Per Gaussian hit of one camera frame: ``(node ids, prims, blend weight,
    colour mismatch, background mismatch)``. ``valid`` (a bool per ray, or
    None for all) leaves the hits of the other rays out (weight 0).

    The colour mismatch is ``|c - sky| / |sky|`` with the sky radiance along
    the ray. The background mismatch is the ray's: how far what the camera
    would see with every hit within ``tolerance`` of the sky's colour removed
    (the rest re-blended) is from the sky, relative to ``|sky|``. Trace deep (small
    ``min_transmittance``) so that what a sky-coloured layer hides is found.
    """
    nodes = hitlib.gaussian_nodes(scene)
    hl = hitlib.trace(scene, rays, max_hits, min_transmittance, nodes)
    g = hitlib.eval_gaussian_hits(nodes, rays, hl)
    w, t_end = hitlib.blend_weights(g)
    colour = hitlib.gather_attribute(nodes, "albedo", g.node_ids, g.prims, g.active)
    sky_ray = mi.Color3f(environment_radiance(scene, rays.d))
    n_rays = g.n_rays
    active = np.broadcast_to(np.array(g.active, bool), (dr.width(g.slot),)) \
        & (np.array(g.slot) < n_rays * g.max_hits)
    order = np.argsort(np.array(g.slot)[active], kind="stable")   # by ray, front to back

    def per_hit(values, dtype=np.float64):
        return np.asarray(values, dtype)[active][order]

    def per_ray(values):
        return np.broadcast_to(np.array(values, np.float64), (n_rays,))

    ray = per_hit(g.ray, np.int64)
    alpha = np.clip(per_hit(g.alpha), 0.0, 1.0 - 1e-7)
    w = per_hit(w)
    c = np.stack([per_hit(colour[k]) for k in range(3)], 1)
    sky_rays = np.stack([per_ray(sky_ray[k]) for k in range(3)], 1)
    sky = sky_rays[ray]
    scale = np.maximum(np.linalg.norm(sky, axis=1), 1e-3)
    colour_off = np.linalg.norm(c - sky, axis=1) / scale
    # What the camera would see with the sky-coloured hits removed.
    keep = colour_off >= tolerance
    log_t = np.where(keep, np.log1p(-alpha), 0.0)
    w_kept = keep * alpha * np.exp(_segment_exclusive_cumsum(log_t, ray))
    t_kept = np.bincount(ray, log_t, minlength=n_rays)
    revealed = np.exp(t_kept)[:, None] * sky_rays
    for k in range(3):
        revealed[:, k] += np.bincount(ray, w_kept * c[:, k], minlength=n_rays)
    behind = np.linalg.norm(revealed - sky_rays, axis=1) / np.maximum(np.linalg.norm(sky_rays, axis=1), 1e-3)
    # A ray cut off at max_hits or min_transmittance never showed what is
    # behind its last hits, and one ending on a mesh shows the mesh: no
    # evidence that removal is harmless.
    cut = (per_ray(hl.count) >= max_hits) | (per_ray(t_end) < min_transmittance) \
        | np.broadcast_to(np.array(hl.surface_valid, bool), (n_rays,))
    behind[cut] = np.inf
    if valid is not None:
        w = np.where(np.asarray(valid, bool)[ray], w, 0.0)
    return per_hit(g.node_ids, np.uint32), per_hit(g.prims, np.int64), w, colour_off, behind[ray]


def accumulate(acc, shape_ids, stats):
    """Add one frame's :func:`frame_statistics` into ``acc`` ({node: (count, 3) array}
    of weight, weight x colour mismatch, weight x background mismatch)."""
    ids, prims, w, c_off, b_off = stats
    for name, sid in shape_ids.items():
        m = ids == sid
        a = acc[name]
        n = a.shape[0]
        a[:, 0] += np.bincount(prims[m], w[m], minlength=n)
        a[:, 1] += np.bincount(prims[m], w[m] * c_off[m], minlength=n)
        # One ray without evidence (infinite mismatch) keeps the Gaussian;
        # a zero-weight hit adds nothing (not 0 x inf).
        a[:, 2] += np.bincount(prims[m], w[m] * np.where(w[m] > 0, b_off[m], 0.0), minlength=n)


def lookalike_masks(acc, tolerance=0.15, min_weight=0.05):
    """Per node: seen (summed weight above ``min_weight``), with mean colour
    and background mismatches below ``tolerance``."""
    out = {}
    for name, a in acc.items():
        wsum = np.maximum(a[:, 0], 1e-12)
        out[name] = (a[:, 0] > min_weight) & (a[:, 1] / wsum < tolerance) & (a[:, 2] / wsum < tolerance)
    return out


#: Metres: the xy cell of a vertical column. The import extends a facade in
#: columns of one xy each, one per 0.25 m cell
#: (``mi_invrgbl.io.importer._extend_walls``); stage 1 moves the centres by
#: centimetres, so a column on a cell's edge may come to straddle two cells.
COLUMN_CELL = 0.25


def unseen_above(centres, lookalike, weight, min_weight=0.05, cell=COLUMN_CELL):
    """Boolean mask: Gaussians no camera sees (``weight`` at most
    ``min_weight``) whose centre stands above a look-alike's in the same xy
    cell of ``cell`` metres (z up). ``centres`` (N, 3), ``lookalike`` and
    ``weight`` (N,)."""
    centres = np.asarray(centres, np.float64).reshape(-1, 3)
    lookalike = np.asarray(lookalike, bool)
    out = np.zeros(centres.shape[0], bool)
    if not lookalike.any():
        return out
    _, inv = np.unique(np.floor(centres[:, :2] / cell).astype(np.int64), axis=0, return_inverse=True)
    inv = inv.ravel()
    lowest = np.full(int(inv.max()) + 1, np.inf)
    np.minimum.at(lowest, inv[lookalike], centres[lookalike, 2])
    return ~lookalike & (np.asarray(weight) <= min_weight) & (centres[:, 2] > lowest[inv])


def find_sky_lookalikes(ctx, frames, tolerance=0.15, min_weight=0.05, stage=1):
    """Per node name, two boolean masks: ``(lookalike, above)``; look-alikes
    are Gaussians whose colour and background both match the sky wherever the
    training cameras see them, ``above`` the unseen ones above them in their
    columns (:func:`unseen_above`)."""
    acc = {name: np.zeros((node.count, 3)) for name, node in ctx.model.nodes.items()}
    with dr.suspend_grad():
        for f in frames:
            if f.camera is None:
                continue
            ctx.model.push(f.poses, stage=stage)
            accumulate(acc, ctx.model.shape_ids,
                       frame_statistics(ctx.scene, f.camera.rays, max(ctx.config.max_hits, 64), 1e-4,
                                        tolerance, f.camera.valid()))
    masks = lookalike_masks(acc, tolerance, min_weight)
    return {name: (m, unseen_above(ctx.model.nodes[name].numpy("center"), m, acc[name][:, 0], min_weight))
            for name, m in masks.items()}
