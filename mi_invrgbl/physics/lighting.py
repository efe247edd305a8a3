"""Per-Gaussian incident light for the ``invrgbl`` integrator.

Lighting a Gaussian does not depend on the camera, so it is computed once
per Gaussian (at its centre, as in the paper) and shared by every ray that
hits it:

* the sky, through ``M`` cosine-weighted Fibonacci directions around the
  Gaussian's normal, each with its traced visibility
  (``v_i L_sky(w_i)``; the diffuse part is their mean);
* every light that is a point or a direction (a ``shsun`` sun, stock
  ``directional``, ``point`` and ``spot`` lights: the paper's sun, headlights
  and street lights), with its traced visibility and irradiance at the centre;
* with ``bounces`` >= 1, light reflected by other Gaussians: a sky direction
  that a Gaussian blocks brings that Gaussian's diffusely reflected light
  instead of nothing. The same traced sky rays give, per Gaussian, the blend
  weights of the Gaussians its sky directions meet (a sparse matrix ``W``);
  the bounce is ``W (albedo * E / pi)``, repeated per extra bounce. Without
  it, light that arrives after a bounce (7-9 % of the synthetic street's,
  ``tests/bench/direct_light_bound.py``) can only be explained as brighter
  albedo. Meshes block sky directions but reflect nothing, and the bounce is
  diffuse only (its specular part is left out).

Visibility is traced without derivatives through Gaussians (transmittance)
and meshes (blocked) and cached while geometry and lights stay put; the
radiance and irradiance terms stay differentiable w.r.t. the sky's SH
coefficients, the sun, and the Gaussians' normals.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import drjit as dr
import mitsuba as mi

from . import brdf, coat
from . import hits as hitlib
from .host_arrays import jit_array

GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0
#: Gaussians traversed by a visibility (shadow) ray before giving up.
SHADOW_MAX_HITS = 16
#: Sun (and other light) shadow rays start this far above the Gaussian's
#: centre, along its normal turned towards the light (scene units, metres
#: for imported scenes). From the centre, rays at a low sun graze through the
#: neighbouring Gaussians of the same surface and it looks self-shadowed: a
#: bumpy Gaussian ground under a 15-degree sun kept three quarters of its sun
#: (tests/test_invrgbl.py), and relit under a 25-degree sun a fitted street's
#: sunlit facade came out at 0.64 of the truth's luminance, 0.86 from here
#: (docs/measurements.md, "Where the relighting error sits"). The fit's sun search and
#: stage 2's start trace from here too.
SHADOW_OFFSET = 0.1
#: Most diffuse bounces an integrator or a fit may ask for.
MAX_BOUNCES = 8
#: Shadow-ray hits blended with less weight pass on no bounce light (the
#: sparse bounce matrix stays small; they carry < 0.1 % of a ray's light).
BOUNCE_MIN_WEIGHT = 1e-3


def fibonacci_hemisphere(count, rotation):
    """Local cosine-weighted Fibonacci directions.

    ``count`` directions per element, flat index ``j = g * count + i``;
    ``rotation`` (per element, in [0, 1)) turns the spiral about the normal so
    neighbouring Gaussians do not share the same sample pattern.
    """
    j = dr.arange(mi.UInt32, dr.width(rotation) * count)
    return fibonacci_direction(mi.Float(j % count), count, dr.gather(mi.Float, rotation, j // count))


def fibonacci_direction(i, count, rot):
    """Local direction ``i`` (a Float) of the spiral turned by ``rot``."""
    u = (i + 0.5) / count
    frac = i * GOLDEN + rot
    phi = dr.two_pi * (frac - dr.floor(frac))
    r = dr.sqrt(u)
    s, c = dr.sincos(phi)
    return mi.Vector3f(r * c, r * s, dr.safe_sqrt(1.0 - u))


def _hash_rotation(n, pattern=0):
    """Deterministic per-element offsets in [0, 1) (a low-discrepancy sequence)."""
    return hash_rotation_of(dr.arange(mi.UInt32, n), pattern)


def hash_rotation_of(index, pattern=0):
    """:func:`_hash_rotation`'s offset of element ``index`` (UInt32).

    ``pattern`` p turns every element's spiral further (the second axis of
    the R2 sequence): the fit cycles through a few patterns so that the
    albedo it finds fits the sky integral, not one set of M directions."""
    turn = float(pattern) * 0.5698402909980532
    # Opaque: the turn is data, not a constant traced into the kernel, so
    # every pattern runs the same compiled kernels (a literal made each of
    # the fit's patterns compile its own, seconds each on the LLVM backend).
    x = mi.Float(index) * 0.7548776662466927 + dr.opaque(mi.Float, turn - math.floor(turn))
    return x - dr.floor(x)


@dataclass
class GaussianTable:
    """All Gaussians of a scene in one index space (node offset + primitive)."""
    nodes: list
    offsets: list
    total: int
    center: mi.Point3f = None
    normal: mi.Vector3f = None

    @staticmethod
    def build(nodes):
        offsets, total = [], 0
        for node in nodes:
            offsets.append(total)
            total += node.count
        return GaussianTable(nodes, offsets, total)

    def global_index(self, node_ids, prims):
        g = mi.UInt32(0)
        for node, off in zip(self.nodes, self.offsets):
            g = dr.select(node_ids == node.id, prims + off, g)
        return g

    def node_and_prim(self):
        """Per global Gaussian: its node's registry id and primitive index."""
        ids = np.zeros(self.total, np.uint32)
        prims = np.zeros(self.total, np.uint32)
        for node, off in zip(self.nodes, self.offsets):
            ids[off:off + node.count] = node.id
            prims[off:off + node.count] = np.arange(node.count, dtype=np.uint32)
        return jit_array(mi.UInt32, ids), jit_array(mi.UInt32, prims)

    def load_geometry(self):
        """Differentiable centres and unit normals of every Gaussian."""
        ids, prims = self.node_and_prim()
        active = mi.Bool(True)
        center, scale, quat, _ = hitlib.gather_geometry(self.nodes, ids, prims, active)
        _, _, axis = hitlib.gaussian_response(center, scale, quat, mi.Float(0),
                                              center + mi.Vector3f(0, 0, 1), mi.Vector3f(0, 0, 1))
        has_normal = mi.Bool(False)
        for node in self.nodes:
            if "normal" in node.attributes:
                has_normal |= ids == node.id
        stored = hitlib.gather_attribute(self.nodes, "normal", ids, prims, has_normal)
        n = dr.select(has_normal, stored, axis)
        self.center = center
        self.normal = n * dr.rsqrt(dr.maximum(dr.squared_norm(n), 1e-20))
        self.ids, self.prims = ids, prims
        return self


def point_lights(scene):
    """Emitters the Gaussians see as a single direction: delta lights and suns."""
    out = []
    for emitter in scene.emitters():
        flags = emitter.flags()
        if hasattr(emitter, "sun_direction_world"):
            if emitter.has_sun():
                out.append(("sun", emitter))
        elif flags & (mi.EmitterFlags.DeltaPosition | mi.EmitterFlags.DeltaDirection):
            if not hasattr(emitter, "power"):  # the LiDAR's own laser is not light
                out.append(("delta", emitter))
    return out


def light_at(kind, emitter, points):
    """Unit direction to the light, irradiance on a facing surface, distance."""
    if kind == "sun":
        d = emitter.sun_direction_world()
        n = dr.width(points)
        return (dr.zeros(mi.Vector3f, n) + d, dr.zeros(mi.Color3f, n) + emitter.sun_irradiance_value(),
                dr.full(mi.Float, dr.inf, n))
    it = dr.zeros(mi.Interaction3f, dr.width(points))
    it.p = points
    ds, weight = emitter.sample_direction(it, mi.Point2f(0.5), True)
    # For delta lights the weight is exactly the irradiance on a surface
    # facing the light (intensity / d^2, spot falloff included).
    return ds.d, mi.Color3f(weight), ds.dist


def environment_radiance(scene, directions):
    """Sky radiance towards ``directions`` (world), without any sun disk."""
    env = scene.environment()
    if env is None:
        return dr.zeros(mi.Color3f, dr.width(directions))
    if hasattr(env, "sky_radiance"):
        return env.sky_radiance(directions)
    si = dr.zeros(mi.SurfaceInteraction3f, dr.width(directions))
    si.wi = -directions
    return mi.Color3f(env.eval(si))


def shadow_origins(table, directions, offset=SHADOW_OFFSET):
    """Where shadow rays towards ``directions`` leave each Gaussian of the
    loaded ``table``: ``offset`` above its centre along its normal, turned
    to the light's side (normals are two-sided)."""
    n = dr.detach(table.normal)
    side = dr.select(dr.dot(n, directions) < 0, -1.0, 1.0)
    return dr.detach(table.center) + n * (offset * side)


def _shadow_trace(scene, origins, directions, maxt, nodes):
    rays = mi.Ray3f(origins, directions)
    rays.maxt = maxt
    h = hitlib.trace(scene, rays, SHADOW_MAX_HITS, 1e-3, nodes)
    g = hitlib.eval_gaussian_hits(nodes, rays, h)
    w, t_after = hitlib.blend_weights(g)
    return dr.select(h.surface_valid, 0.0, t_after), g, w


def transmittance(scene, origins, directions, maxt, nodes):
    """Visibility in [0, 1] along shadow rays: Gaussian transmittance, 0 behind meshes."""
    return _shadow_trace(scene, origins, directions, maxt, nodes)[0]


def split_transmittance(scene, origins, directions, maxt, nodes, moving_ids):
    """Visibility along shadow rays, split by what blocks them: ``(static,
    moving)`` per ray. ``moving`` is the transmittance through the Gaussians
    of the nodes whose shape ids are in ``moving_ids``; ``static`` through
    every other Gaussian, and 0 behind a mesh. Their product is
    :func:`transmittance`'s value (one trace, the same hits).

    A ray stops where the product falls below the trace's threshold, so the
    split is exact only where the static part leaves light through; where
    it does not, the sun is blocked either way."""
    rays = mi.Ray3f(origins, directions)
    rays.maxt = maxt
    h = hitlib.trace(scene, rays, SHADOW_MAX_HITS, 1e-3, nodes)
    g = hitlib.eval_gaussian_hits(nodes, rays, h)
    moving = mi.Bool(False)
    for i in moving_ids:
        moving |= g.node_ids == i
    log_t = dr.log(1.0 - g.alpha)
    parts = []
    for keep in (~moving, moving):
        total = dr.zeros(mi.Float, h.n_rays)
        dr.scatter_reduce(dr.ReduceOp.Add, total, dr.select(g.active & keep, log_t, 0.0), g.ray)
        parts.append(dr.exp(total))
    return dr.select(h.surface_valid, 0.0, parts[0]), parts[1]


#: A moving node's Gaussians reach this many of their largest scale past
#: their centres when :func:`moving_shadows` decides which shadow rays can
#: meet the node (the response is below 1.2e-2 of its peak beyond 3 sigma).
MOVING_SUPPORT = 3.0


def _moving_boxes(table, moving_ids):
    """World-space bounds (lo, hi) of each moving node's Gaussians' support
    (centre +- :data:`MOVING_SUPPORT` times its largest scale)."""
    boxes = []
    for node in table.nodes:
        if node.id not in moving_ids or node.count == 0:
            continue
        data = np.array(dr.detach(node.data), np.float64).reshape(-1, 10)
        reach = MOVING_SUPPORT * np.max(np.abs(data[:, 3:6]), axis=1, keepdims=True)
        boxes.append((np.min(data[:, :3] - reach, axis=0), np.max(data[:, :3] + reach, axis=0)))
    return boxes


def moving_shadows(nodes, table, direction, moving_ids, return_rays=False):
    """Per Gaussian of the loaded ``table`` (G,): the transmittance of its
    shadow ray towards ``direction`` (a unit world vector, towards the light)
    through the Gaussians of the moving nodes, as they are placed now.
    The moving nodes' own Gaussians get 1 (their shading is the learned
    field's), as does every ray that cannot meet a moving node's bounds:
    only rays whose slab test meets a node's box are traced.

    The rays are traced through a scene of the moving nodes' shapes alone
    (``nodes`` must be the scene's own, :func:`~.hits.gaussian_nodes`), so
    a ray walks past no static Gaussian on its way (KITTI excerpt, 54 000
    rays: 0.15-0.23 s with the scene built, against 0.92-0.98 s through the
    whole scene), and no static hit ends it before it reaches the objects.

    This is the factor that lets a learned, static ``sun_visibility`` field
    carry the shadows of objects that move: the field holds what the static
    scene casts, this what the objects cast where the frame has them.
    With ``return_rays``, also how many shadow rays were traced."""
    G = table.total
    ids = set(int(i) for i in moving_ids)
    out = np.ones(G, np.float32)
    boxes = _moving_boxes(table, ids)
    if G == 0 or not boxes:
        return (jit_array(mi.Float, out), 0) if return_rays else jit_array(mi.Float, out)
    d = np.asarray(direction, np.float64).ravel()
    d = d / np.linalg.norm(d)
    node_id = np.array(table.ids, np.uint32)
    origin = np.array(shadow_origins(table, dr.zeros(mi.Vector3f, G) + mi.Vector3f(
        *[float(x) for x in d])), np.float64).T
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(np.abs(d) > 1e-12, 1.0 / d, np.inf)
    candidate = np.zeros(G, bool)
    for lo, hi in boxes:
        # Slab test of the ray origin + t d, t >= 0, against the box.
        t0, t1 = (lo - origin) * inv, (hi - origin) * inv
        near = np.nanmax(np.minimum(t0, t1), axis=1)
        far = np.nanmin(np.maximum(t0, t1), axis=1)
        candidate |= (far >= np.maximum(near, 0.0))
    candidate &= ~np.isin(node_id, list(ids))
    rows = np.flatnonzero(candidate)
    if rows.size:
        o = mi.Point3f(*origin[rows].T.astype(np.float32))
        dv = mi.Vector3f(*np.tile(d.astype(np.float32), (rows.size, 1)).T)
        shapes = [n.shape for n in nodes if n.id in ids]
        # Keyed by their own ids: a scene's dictionary names its objects.
        movers = mi.load_dict(dict({"type": "scene"}, **{
            (s.id() or "moving_%d" % i): s for i, s in enumerate(shapes)}))
        with dr.suspend_grad():
            moving = transmittance(movers, o, dv, mi.Float(dr.inf), hitlib.gaussian_nodes(movers))
        out[rows] = np.clip(np.array(moving, np.float32), 0.0, 1.0)
    return (jit_array(mi.Float, out), int(rows.size)) if return_rays else jit_array(mi.Float, out)


def shadow_blockers(scene, origins, directions, maxt, nodes, table):
    """Visibility along shadow rays and the Gaussians that block them.

    Returns ``(visibility, ray, source, weight)``: per ray as in
    :func:`transmittance`, then one entry per blocking hit with weight >=
    :data:`BOUNCE_MIN_WEIGHT`: the ray it lies on, the blocking Gaussian's
    index in ``table`` and its front-to-back blend weight (``None`` for the
    three when nothing blocks).
    """
    vis, g, w = _shadow_trace(scene, origins, directions, maxt, nodes)
    keep = dr.compress(g.active & (w >= BOUNCE_MIN_WEIGHT))
    if dr.width(keep) == 0:
        return vis, None, None, None
    take = lambda a, T: dr.gather(T, a, keep)  # noqa: E731
    source = table.global_index(take(g.node_ids, mi.UInt32), take(g.prims, mi.UInt32))
    return vis, take(g.ray, mi.UInt32), source, take(w, mi.Float)


@dataclass
class LightingCache:
    """Detached visibility, reused while geometry and lights do not move.

    The sky's visibility and the lights' are keyed apart: moving or
    switching the sun (the lighting selection's candidates, the sun trial)
    re-traces the lights' G shadow rays, not the sky's G x M (on the
    street's 8-minute fit a sky trace took 17 s, and the sun trial made
    three, 52 s of its 77)."""
    #: What the sky visibility (and bounce matrix) was traced for: geometry,
    #: M, bounces, pattern. Empty until traced.
    key: tuple = ()
    #: What ``light_visibility`` was traced for: geometry and the lights.
    light_key: tuple = ()
    sky_visibility: mi.Float = None      # (G * M,)
    light_visibility: list = field(default_factory=list)  # per light, (G,)
    #: The bounce matrix W (with ``bounces`` >= 1), one entry per blocking hit:
    #: receiving Gaussian, blocking Gaussian, blend weight / M.
    bounce_target: mi.UInt32 = None
    bounce_source: mi.UInt32 = None
    bounce_weight: mi.Float = None
    #: (G, 3) unit normals the sky directions were traced about. A Gaussian's
    #: M directions turn with its normal; visibility traced for the old ones
    #: is not the new ones' (:func:`retrace_turned`).
    normals: np.ndarray = None
    #: What ``moving_visibility`` was traced for: geometry and sun directions.
    moving_key: tuple = ()
    #: Per light, the moving shapes' shadow factor on a learned sun
    #: visibility (:func:`moving_shadows`; None for other lights).
    moving_visibility: list = field(default_factory=list)


def geometry_key(nodes):
    """What traced visibility depends on of the nodes: their arrays' identities
    (a placement or an edit through ``mi.traverse`` makes new ones)."""
    return tuple((n.id, n.data.index, n.count) for n in nodes)


def _light_key(scene, lights, trace_sun=True):
    key = []
    for kind, emitter in lights:
        if kind == "sun" and not trace_sun:
            key.append("sun: stored visibility")   # its direction moves nothing cached
        elif kind == "sun":
            key.append(tuple(np.array(dr.detach(emitter.sun_direction_world())).ravel().round(7)))
        else:
            key.append(tuple(np.array(emitter.world_transform().matrix, np.float64).ravel().round(7)))
    return tuple(key)


def unit_normals(table) -> np.ndarray:
    """(G, 3) float32 copy of a loaded table's unit normals."""
    return np.array(dr.detach(table.normal), np.float32).T.copy()


def trace_sky(scene, nodes, table, samples, pattern=0, bounces=0, gaussians=None):
    """Trace the M sky directions of ``gaussians`` (global indices, numpy;
    default every Gaussian of the loaded ``table``), cosine-weighted about
    each one's normal and turned by its :func:`hash_rotation_of`.

    Returns ``(visibility, target, source, weight)``: visibility per ray
    (``len(gaussians) * M``, Gaussian-major), then with ``bounces`` the
    entries of the bounce matrix these rays add (receiving and blocking
    Gaussian, blend weight / M; ``None`` for the three when nothing blocks
    or ``bounces`` is 0). The one place sky directions are traced: the first
    trace of a cache and :func:`retrace_turned` share it."""
    M = int(samples)
    with dr.suspend_grad():
        idx = dr.arange(mi.UInt32, table.total) if gaussians is None else jit_array(mi.UInt32, gaussians)
        j = dr.arange(mi.UInt32, dr.width(idx) * M)
        g = dr.gather(mi.UInt32, idx, j // M)
        local = fibonacci_direction(mi.Float(j % M), M, hash_rotation_of(g, pattern))
        dirs = mi.Frame3f(dr.gather(mi.Vector3f, dr.detach(table.normal), g)).to_world(local)
        origins = dr.gather(mi.Point3f, dr.detach(table.center), g)
        if bounces <= 0:
            return transmittance(scene, origins, dirs, mi.Float(dr.inf), nodes), None, None, None
        vis, ray, source, w = shadow_blockers(scene, origins, dirs, mi.Float(dr.inf), nodes, table)
        if ray is None:
            return vis, None, None, None
        return vis, dr.gather(mi.UInt32, g, ray), source, w / M


def retrace_turned(scene, nodes, cache: LightingCache, samples, pattern=0, bounces=0,
                   max_turn_deg=1.0, table=None) -> int:
    """Re-trace the sky visibility (and bounce entries) of the Gaussians whose
    normal turned by more than ``max_turn_deg`` since ``cache`` traced them;
    returns how many.

    A Gaussian's M sky directions are cosine-weighted about its normal, so
    they turn with it. Visibility traced for the old directions is not the
    new ones': a KITTI 30-minute fit's scene, rendered with visibility traced
    for its final normals, was -18 % .. +15 % (5th-95th percentile of the
    pixels) off the fit's own render of a training frame, whose cache was
    traced for the normals at stage 2's start, and 0.1 dB further from the
    image; turning every normal of that scene by 5 degrees moved its pixels
    by a like spread. Only the turned Gaussians are traced again
    (:func:`trace_sky`): their entries of ``sky_visibility`` are overwritten
    and their rows of the bounce matrix replaced."""
    if cache.sky_visibility is None or cache.normals is None:
        return 0
    if table is None:
        table = GaussianTable.build(nodes).load_geometry()
    M = int(samples)
    now = unit_normals(table)
    if now.shape != cache.normals.shape:
        raise ValueError("retrace_turned: the cache holds %d Gaussians, the scene %d"
                         % (cache.normals.shape[0], now.shape[0]))
    cos = np.sum(now * cache.normals, axis=1)
    limit = math.cos(math.radians(max_turn_deg)) if max_turn_deg > 0 else 1.0 - 1e-7
    turned = np.flatnonzero(cos < limit).astype(np.uint32)
    if turned.size == 0:
        return 0
    new_vis, target, source, weight = trace_sky(scene, nodes, table, M, pattern, bounces, turned)
    if bounces > 0:
        # Keep the other Gaussians' rows of W; the turned ones get their new rows.
        parts = []
        if cache.bounce_target is not None:
            old = [np.array(a) for a in (cache.bounce_target, cache.bounce_source,
                                         cache.bounce_weight)]
            keep = ~np.isin(old[0], turned)
            parts.append([a[keep] for a in old])
        if target is not None:
            parts.append([np.array(a) for a in (target, source, weight)])
        if parts:
            t, src, w = (np.concatenate(col) for col in zip(*parts))
            cache.bounce_target = jit_array(mi.UInt32, t)
            cache.bounce_source = jit_array(mi.UInt32, src)
            cache.bounce_weight = jit_array(mi.Float, w)
            dr.eval(cache.bounce_target, cache.bounce_source, cache.bounce_weight)
    # A new array rather than a scatter into the cached one: lighting built
    # before this call may still read the old one. It is handed over padded
    # (:mod:`.host_arrays`): a NumPy buffer that ends at an unmapped page
    # crashes the next kernel that reads it, the likelier cause of the
    # SIGSEGVs once blamed on the scatter.
    slots = (turned.astype(np.int64)[:, None] * M + np.arange(M)).ravel()
    vis = np.array(cache.sky_visibility, np.float32)
    vis[slots] = np.array(new_vis, np.float32)
    cache.sky_visibility = jit_array(mi.Float, vis)
    dr.eval(cache.sky_visibility)
    cache.normals[turned] = now[turned]
    # The lights' shadow rays leave along the normals too (shadow_origins):
    # trace them again on the next build (one ray per Gaussian and light).
    cache.light_key = None
    return int(turned.size)


class GaussianLighting:
    """Incident light per Gaussian for one render (see module docstring)."""

    def __init__(self, scene, nodes, samples, cache: LightingCache, trace_sun=True, bounces=0,
                 pattern=0, follow_normals=False, before_trace=None, diffuse_fresnel=False,
                 f0=brdf.F0_DEFAULT, light_transmittance=None):
        """``follow_normals``: when the cache is reused, first re-trace the sky
        directions of every Gaussian whose normal changed since they were
        traced (:func:`retrace_turned`); the integrator does, so normals
        edited through ``mi.traverse`` are lit as a fresh load lights them.
        The fit re-traces at its own times instead (every step would cost a
        read-back of the normals).

        ``before_trace``: called (no arguments) just before the cache is
        traced afresh (it is empty or its key no longer matches). The fit
        puts the scene's moving objects where the cache's frame has them:
        a trace goes through the scene as it was last pushed.

        ``diffuse_fresnel``: the diffuse term takes each light through a
        rough dielectric coat of reflectance ``f0`` and the Gaussian's
        roughness on the way in (:func:`~mi_invrgbl.physics.coat.transmission`
        of its angle to the normal); the way out depends on the viewer and is
        the integrator's (:func:`~mi_invrgbl.physics.coat.way_out`). The
        bounce light a Gaussian receives is not weighted on its way in.

        ``light_transmittance``: per light of :func:`point_lights` (same
        order), ``None`` or a (G,) factor on that light's visibility: the
        shadows of moving objects where the frame has them
        (:func:`moving_shadows`), for a sun whose visibility is the learned
        field of the static scene."""
        self.table = GaussianTable.build(nodes)
        self.diffuse_fresnel, self.f0 = bool(diffuse_fresnel), f0
        self.samples = int(samples)
        self.bounces = int(bounces)
        self.pattern = int(pattern)
        self.lights = point_lights(scene)
        if self.table.total == 0:
            return
        with dr.suspend_grad():
            geometry = geometry_key(nodes)
            sky_key = (geometry, self.samples, self.bounces > 0, self.pattern)
            light_key = (geometry, _light_key(scene, self.lights, trace_sun), trace_sun)
        table = self.table.load_geometry()
        M, G = self.samples, self.table.total
        frames = mi.Frame3f(dr.gather(mi.Vector3f, table.normal,
                                      dr.arange(mi.UInt32, G * M) // M))
        local = fibonacci_hemisphere(M, _hash_rotation(G, self.pattern))
        self.sky_dirs = frames.to_world(local)           # (G*M,) differentiable in n
        if cache.key != sky_key or cache.light_key != light_key:
            if before_trace is not None:
                before_trace()
        if cache.key != sky_key:
            with dr.suspend_grad():
                cache.bounce_target = cache.bounce_source = cache.bounce_weight = None
                if M:
                    (cache.sky_visibility, cache.bounce_target, cache.bounce_source,
                     cache.bounce_weight) = trace_sky(scene, nodes, table, M, self.pattern,
                                                      self.bounces)
                    if cache.bounce_target is not None:
                        dr.eval(cache.bounce_target, cache.bounce_source, cache.bounce_weight)
                else:
                    cache.sky_visibility = mi.Float()
                dr.eval(cache.sky_visibility)
                cache.normals = unit_normals(table)
                cache.key = sky_key
        elif follow_normals and M:
            retrace_turned(scene, nodes, cache, M, pattern, self.bounces, max_turn_deg=0.0, table=table)
        if cache.light_key != light_key:
            with dr.suspend_grad():
                cache.light_visibility = []
                for kind, emitter in self.lights:
                    d, _, dist = light_at(kind, emitter, dr.detach(table.center))
                    if kind == "sun" and not trace_sun:
                        # Read the field on every render (below), not cached: it
                        # may be edited or optimised through mi.traverse, which
                        # the cache key does not see.
                        cache.light_visibility.append(None)
                        continue
                    # (A light at a finite distance: the ray stops short of
                    # it by the offset too, not past it.)
                    vis = transmittance(scene, shadow_origins(table, d), d,
                                        dr.select(dr.isfinite(dist), dr.maximum(
                                            dist - SHADOW_OFFSET, 0.0) * (1 - 1e-4), dr.inf),
                                        nodes)
                    cache.light_visibility.append(dr.detach(vis))
                dr.eval([v for v in cache.light_visibility if v is not None])
                cache.light_key = light_key
        self.cache = cache
        # v_i L_sky(w_i): differentiable in the sky's coefficients and normals.
        self.sky_radiance = environment_radiance(scene, self.sky_dirs) * cache.sky_visibility
        sky_in = self.sky_radiance
        coat_roughness = None
        if diffuse_fresnel:
            coat_roughness = hitlib.gather_attribute(nodes, "roughness", table.ids, table.prims,
                                                     mi.Bool(True))
        if diffuse_fresnel and M:
            # The samples' local z is their cosine to the normal.
            sky_in = sky_in * coat.transmission(
                local.z, dr.gather(mi.Float, coat_roughness, dr.arange(mi.UInt32, G * M) // M), f0)
        self.diffuse_sky = mi.Color3f(*[dr.block_sum(sky_in[c], M) / M for c in range(3)]) \
            if M else dr.zeros(mi.Color3f, G)
        self.light_dir, self.light_irr = [], []
        extra = light_transmittance or [None] * len(self.lights)
        for (kind, emitter), vis, t in zip(self.lights, cache.light_visibility, extra):
            d, irr, _ = light_at(kind, emitter, table.center)
            if vis is None:  # sun_visibility = attribute: the stored field
                vis = hitlib.gather_attribute(nodes, "sun_visibility", table.ids,
                                              table.prims, mi.Bool(True))
            if t is not None:
                vis = vis * t
            self.light_dir.append(d)
            self.light_irr.append(irr * vis)
        # E / pi of the diffuse term per Gaussian (its normal is the shading
        # normal of every hit on it): sky, lights, and the bounce.
        self.direct = mi.Color3f(self.diffuse_sky)
        for d_l, e_l in zip(self.light_dir, self.light_irr):
            cos_l = dr.maximum(dr.dot(table.normal, d_l), 0.0)
            if diffuse_fresnel:
                cos_l = cos_l * coat.transmission(cos_l, coat_roughness, f0)
            self.direct += e_l * cos_l * dr.inv_pi
        self.indirect = self.bounce_light(nodes) if self.bounces > 0 else dr.zeros(mi.Color3f, G)
        self.diffuse = self.direct + self.indirect

    def bounce_light(self, nodes):
        """E / pi that reaches each Gaussian after 1..``bounces`` diffuse bounces."""
        table, G = self.table, self.table.total
        if self.cache.bounce_target is None:
            return dr.zeros(mi.Color3f, G)
        albedo = mi.Color3f(hitlib.gather_attribute(nodes, "albedo", table.ids, table.prims,
                                                    mi.Bool(True)))
        indirect = dr.zeros(mi.Color3f, G)
        for _ in range(self.bounces):
            # Radiance leaving each Gaussian (Lambertian), passed along W.
            indirect = self.pass_on(albedo * (self.direct + indirect))
        return indirect

    def pass_on(self, leaving):
        """``W leaving``: E / pi at each Gaussian from the radiance ``leaving``
        every Gaussian (Color3f, one per Gaussian) towards its sky directions."""
        cache, G = self.cache, self.table.total
        out = [dr.zeros(mi.Float, G) for _ in range(3)]
        if cache.bounce_target is None:
            return mi.Color3f(*out)
        passed = dr.gather(mi.Color3f, leaving, cache.bounce_source) * cache.bounce_weight
        for c in range(3):
            dr.scatter_reduce(dr.ReduceOp.Add, out[c], passed[c], cache.bounce_target)
        return mi.Color3f(*out)
