"""Differentiable renders the fit needs, built on the plugins' traversal.

Stage 1 (geometry moves): :func:`camera_unlit` and :func:`lidar_beams` trace
the rays every iteration and blend differentiably (the plugins' own
``trace`` / ``eval_gaussian_hits`` / ``blend_weights``).

Stage 2 (geometry frozen): :func:`freeze` traces a frame once and keeps, per
hit, the Gaussian, its blend weight and its distance; :func:`camera_shaded`
and :func:`lidar_shaded` are then pure gathers and sums over those cached
arrays plus the cached per-Gaussian visibility — no ray is traced.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import drjit as dr
import mitsuba as mi

from ..physics import brdf, hits as hitlib
from ..physics.lighting import environment_radiance
from ..physics.lidar_response import LidarResponse as Response  # noqa: F401 (the fit's name)
from ..physics.host_arrays import jit_array
from .config import MAX_PIXEL_GRID


# ---------------------------------------------------------------- stage 1
def batch_order(index: np.ndarray) -> np.ndarray:
    """A random batch of pixel or beam indices in the order to trace them.

    The LLVM backend traces rays in SIMD packets, and a packet runs until
    its last ray has walked all of its Gaussians. Sorted indices put rays
    of neighbouring pixels (and beams) into one packet: they cross the same
    Gaussians, so the packet's BVH traversals are coherent and its rays end
    at about the same step. On a fitted KITTI scene a 4 096-ray stage-1
    render took 0.173 s sorted against 0.300 s in draw order (2 cores,
    135 391 Gaussians). The loss is a mean over the batch; what a ray
    renders changes only by rounding in Embree's packet traversal, which
    now and then finds a flat Gaussian's entry a hair nearer or farther
    (on a fitted KITTI scene 0.36 % of a batch's rays moved by more than
    1e-3, one by 0.24; ``tests/bench/batch_order.py``)."""
    return np.sort(index)


def gather_rays(rays, idx):
    """The rays ``idx`` (``mi.UInt32``) of a ray bundle, ``maxt`` included."""
    out = mi.Ray3f(dr.gather(mi.Point3f, rays.o, idx), dr.gather(mi.Vector3f, rays.d, idx))
    out.maxt = dr.gather(mi.Float, rays.maxt, idx)
    return out


def camera_unlit(scene, rays, max_hits=32, min_transmittance=1e-2):
    """View-independent colour (the ``albedo`` field blended), alpha, depth."""
    nodes = hitlib.gaussian_nodes(scene)
    hl = hitlib.trace(scene, rays, max_hits, min_transmittance, nodes)
    g = hitlib.eval_gaussian_hits(nodes, rays, hl)
    w, t_after = hitlib.blend_weights(g)
    colour = hitlib.gather_attribute(nodes, "albedo", g.node_ids, g.prims, g.active)
    c = hitlib.composite_front_to_back(
        g, w, t_after, {"rgb": mi.Color3f(colour), "alpha": 1.0, "depth": g.t},
        {"rgb": mi.Color3f(environment_radiance(scene, rays.d))})
    return c["rgb"], c["alpha"], c["depth"]


def lidar_beams(integrator, scene, rays, row, near):
    """``lidar_return`` channels (intensity, range, hit, lidar_albedo, alpha)."""
    return integrator.render_beams(scene, rays, row, near=near)


# ---------------------------------------------------------------- stage 2
@dataclass
class FrozenHits:
    """One frame's traversal with frozen geometry (flat per-hit arrays)."""
    n_rays: int
    max_hits: int
    ray: mi.UInt32
    slot: mi.UInt32
    node_ids: mi.UInt32
    prims: mi.UInt32
    weight: mi.Float
    t: mi.Float
    t_after: mi.Float         # per ray: transmittance left behind the Gaussians
    surface: mi.Bool          # per ray: an opaque (mesh) surface ends the ray

    def ray_index(self):
        return self.ray

    @property
    def hit_count(self):
        return dr.width(self.ray)

    def nbytes(self):
        return 24 * self.hit_count + 5 * self.n_rays


def freeze(scene, rays, max_hits=32, min_transmittance=1e-2, min_weight=1e-4, nodes=None):
    """Trace ``rays`` once and keep the hits that matter (weight >= ``min_weight``)."""
    with dr.suspend_grad():
        nodes = hitlib.gaussian_nodes(scene) if nodes is None else nodes
        hl = hitlib.trace(scene, rays, max_hits, min_transmittance, nodes)
        g = hitlib.eval_gaussian_hits(nodes, rays, hl)
        w, t_after = hitlib.blend_weights(g)
        keep = dr.compress(g.active & (w >= min_weight))
        if dr.width(keep) == 0:
            keep = dr.zeros(mi.UInt32, 1)
        take = lambda a, T: dr.gather(T, a, keep)  # noqa: E731
        fh = FrozenHits(hl.n_rays, hl.max_hits, take(g.ray, mi.UInt32), take(g.slot, mi.UInt32),
                        take(g.node_ids, mi.UInt32), take(g.prims, mi.UInt32),
                        take(dr.select(g.active, w, 0.0), mi.Float), take(g.t, mi.Float),
                        mi.Float(t_after), hl.surface_valid & hl.surface_interaction(rays).is_valid())
        dr.eval(fh.ray, fh.slot, fh.node_ids, fh.prims, fh.weight, fh.t, fh.t_after, fh.surface)
        return fh


def freeze_pixels(scene, camera, grid=1, max_hits=32, min_transmittance=1e-2, min_weight=1e-4,
                  nodes=None):
    """A camera frame's frozen hits integrated over each pixel's area.

    The camera (and ``eval``, which renders with a box filter) averages the
    light over a pixel; one ray through its centre samples it at a point. A
    stage 2 fitted to centre rays fits the albedo to a point sample of a
    pixel's average and then renders blurred once more where ``eval``
    integrates the pixel. With ``grid`` > 1 the frame is traced at a
    ``grid`` x ``grid`` stratified set of positions in every pixel and the
    hits are merged per pixel: each Gaussian's weight is its mean over the
    sub-rays (0 where a sub-ray misses it), its distance the weighted mean,
    and the transmittance left to the sky the mean over the sub-rays (0
    behind an opaque surface). Rendering the merged list is then the pixel's
    box-filtered average, with the shading evaluated along the centre ray's
    direction (``camera.rays``; the directions within a pixel differ by a
    fraction of a degree). Neighbouring sub-rays mostly meet the same
    Gaussians, so the merged list is far shorter than the ``grid``² lists
    together (1.26x the centre ray's hits on a KITTI frame at 2 x 2).

    ``camera``: a :class:`~.observations.CameraObservation` (sensor, size,
    centre rays). ``grid`` 1 is :func:`freeze` of the centre rays.
    """
    grid = int(grid)
    if not 1 <= grid <= MAX_PIXEL_GRID:
        raise ValueError("pixel grid must be in 1..%d (got %r)" % (MAX_PIXEL_GRID, grid))
    if grid == 1:
        return freeze(scene, camera.rays, max_hits, min_transmittance, min_weight, nodes)
    from .observations import pixel_rays   # (observations imports this module)
    n = camera.width * camera.height
    index = dr.arange(mi.UInt32, n)
    share = 1.0 / grid ** 2
    parts, sky_t, opaque = [], np.zeros(n, np.float64), np.ones(n, bool)
    with dr.suspend_grad():
        nodes = hitlib.gaussian_nodes(scene) if nodes is None else nodes
        for v in (np.arange(grid) + 0.5) / grid:
            for u in (np.arange(grid) + 0.5) / grid:
                rays = pixel_rays(camera.sensor, camera.width, camera.height, index,
                                  (dr.full(mi.Float, float(u), n), dr.full(mi.Float, float(v), n)))
                fh = freeze(scene, rays, max_hits, min_transmittance, min_weight, nodes)
                keep = np.array(fh.node_ids) != 0       # freeze keeps one empty slot when nothing is hit
                parts.append([np.array(a)[keep] for a in (fh.ray, fh.node_ids, fh.prims,
                                                           fh.weight, fh.t)])
                surface = np.array(fh.surface, bool)
                sky_t += np.where(surface, 0.0, np.array(fh.t_after, np.float64)) * share
                opaque &= surface
    ray, node, prim, weight, t = (np.concatenate([p[i] for p in parts]) for i in range(5))
    if ray.size == 0:
        # No sub-ray met a Gaussian: one inactive entry (node id 0), as freeze keeps.
        ray_m = node_m = prim_m = slot = np.zeros(1, np.uint32)
        weight_m = t_m = np.zeros(1, np.float32)
    else:
        node_ids, node_rank = np.unique(node, return_inverse=True)
        key = ((ray.astype(np.int64) * len(node_ids) + node_rank) * (int(prim.max()) + 1)
               + prim.astype(np.int64))
        _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
        w = weight.astype(np.float64) * share
        weight_m = np.bincount(inverse, w)
        t_m = np.bincount(inverse, w * t) / np.maximum(weight_m, 1e-30)
        ray_m, node_m, prim_m = ray[first], node[first], prim[first]
        # Keys sort by ray first: a hit's rank within its ray is its position
        # less the ray's first position.
        rank = np.arange(ray_m.size) - np.searchsorted(ray_m, ray_m, side="left")
        slot = ray_m.astype(np.int64) * grid ** 2 * max_hits + rank
        weight_m, t_m = weight_m.astype(np.float32), t_m.astype(np.float32)
    fh = FrozenHits(n, grid ** 2 * int(max_hits), jit_array(mi.UInt32, ray_m),
                    jit_array(mi.UInt32, slot), jit_array(mi.UInt32, node_m),
                    jit_array(mi.UInt32, prim_m), jit_array(mi.Float, weight_m),
                    jit_array(mi.Float, t_m), jit_array(mi.Float, sky_t), jit_array(mi.Bool, opaque))
    dr.eval(fh.ray, fh.slot, fh.node_ids, fh.prims, fh.weight, fh.t, fh.t_after, fh.surface)
    return fh


class VirtualNode:
    """A Gaussian node as the plugins' gathers see it, built from fit variables.

    Same fields as :class:`~mi_invrgbl.physics.hits.GaussianNode`; ``id`` is the
    scene shape's registry id so traced hit lists address it.
    """

    def __init__(self, shape_id, data, opacities, attributes, count):
        self.id = shape_id
        self.data = data
        self.opacities = opacities
        self.attributes = attributes
        self.count = count
        self.shape = None


def frozen_gaussian_hits(nodes, rays, fh: FrozenHits):
    """A :class:`~mi_invrgbl.physics.hits.GaussianHits` over cached hits; the
    normal (and what depends on it) stays differentiable."""
    active = fh.node_ids != 0
    d = dr.gather(mi.Vector3f, rays.d, fh.ray)
    n = hitlib.gather_attribute(nodes, "normal", fh.node_ids, fh.prims, active)
    n = n * dr.rsqrt(dr.maximum(dr.squared_norm(n), 1e-20))
    cos_d = dr.dot(n, d)
    n = dr.select(cos_d > 0, -n, n)
    return hitlib.GaussianHits(mi.Float(0.0), fh.t, n, dr.abs(cos_d), active, fh.node_ids,
                               fh.prims, fh.ray, fh.slot, fh.n_rays, fh.max_hits)


def camera_shaded(integrator, scene, lighting, nodes, rays, fh: FrozenHits):
    """Physically based colour + AOVs of a frozen frame (``invrgbl``'s shading)."""
    g = frozen_gaussian_hits(nodes, rays, fh)
    colour, albedo, n, tau, rho = integrator.shade_gaussian_hits(lighting, nodes, rays, fh, g)
    sky = dr.select(fh.surface, 0.0, mi.Color3f(environment_radiance(scene, rays.d)))
    return hitlib.composite_front_to_back(
        g, fh.weight, fh.t_after, {"rgb": colour, "albedo": albedo, "normal": n, "roughness": tau,
                                   "lidar_albedo": rho, "alpha": 1.0}, {"rgb": sky})


def lidar_shaded(nodes, rays, row, near, fh: FrozenHits, response: Response,
                 model="pbr", f0=brdf.F0_DEFAULT):
    """Per-beam intensity, LiDAR albedo and alpha of a frozen scan."""
    g = frozen_gaussian_hits(nodes, rays, fh)
    rho = hitlib.gather_attribute(nodes, "lidar_albedo", g.node_ids, g.prims, g.active)
    tau = hitlib.gather_attribute(nodes, "roughness", g.node_ids, g.prims, g.active)
    factor = brdf.lidar_return_factor(rho, tau, g.cos_theta, model, f0)
    dist = fh.t + dr.gather(mi.Float, near, fh.ray)
    intensity_k = response(factor, g.cos_theta, dist, dr.gather(mi.UInt32, row, fh.ray))
    return hitlib.composite_front_to_back(
        g, fh.weight, fh.t_after, {"intensity": intensity_k, "lidar_albedo": rho, "alpha": 1.0,
                                   "range": dist})


def dominant_hit(fh: FrozenHits):
    """Per ray, the index (global over nodes: node id, prim) of the hit with the
    largest weight, as numpy arrays (ray, node_id, prim, weight, t)."""
    ray = np.array(fh.ray)
    w = np.array(fh.weight)
    order = np.lexsort((-w, ray))
    ray_s = ray[order]
    first = np.ones(len(ray_s), bool)
    first[1:] = ray_s[1:] != ray_s[:-1]
    sel = order[first]
    return (ray[sel], np.array(fh.node_ids)[sel], np.array(fh.prims)[sel], w[sel],
            np.array(fh.t)[sel])
