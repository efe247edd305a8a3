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
  albedo. Meshes block sky directions but reflect nothing, and the light
  passed on is the blockers' diffuse light (their specular part is left
  out). Under a coat (``diffuse_fresnel``) each entry of ``W`` takes the
  light out through the blocker's coat and in through the receiver's. The
  receiver's specular lobe reflects it too, sample by sample
  (:meth:`GaussianLighting.blocked_radiance`; the lobe's sum is
  :func:`~.specular_albedo.sky_specular`).

Visibility is traced without derivatives through Gaussians (transmittance)
and meshes (blocked) and cached while geometry and lights stay put; the
radiance and irradiance terms stay differentiable w.r.t. the sky's SH
coefficients, the sun, and the Gaussians' normals.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

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


def rays_meeting(origins, directions, boxes) -> np.ndarray:
    """Per ray (Dr.Jit ``origins``, ``directions``), whether it meets one of
    ``boxes`` (world ``(lo, hi)``, numpy) ahead of its origin: the rays a
    moved shape can have changed. Each box is padded a little, so that a ray
    grazing it in float32 counts (a ray along an axis, level with a face,
    included)."""
    hit = mi.Bool(False)
    with dr.suspend_grad():
        rays = mi.Ray3f(origins, directions)
        for lo, hi in boxes:
            pad = 1e-4 * (1.0 + np.abs(lo) + np.abs(hi)) + 1e-4 * (hi - lo)
            box = mi.BoundingBox3f(mi.Point3f(*[float(v) for v in lo - pad]),
                                   mi.Point3f(*[float(v) for v in hi + pad]))
            ok, _, far = box.ray_intersect(rays)
            hit |= ok & (far >= 0.0)
    return np.array(hit, bool).reshape(-1) if boxes else np.zeros(dr.width(origins), bool)


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
    boxes = [box for node, box in zip(table.nodes, node_boxes(table.nodes))
             if node.id in ids and box is not None]
    if G == 0 or not boxes:
        return (jit_array(mi.Float, out), 0) if return_rays else jit_array(mi.Float, out)
    d = np.asarray(direction, np.float64).ravel()
    d = d / np.linalg.norm(d)
    node_id = np.array(table.ids, np.uint32)
    towards = dr.zeros(mi.Vector3f, G) + mi.Vector3f(*[float(x) for x in d])
    origins = shadow_origins(table, towards)
    origin = np.array(origins, np.float64).T
    candidate = rays_meeting(origins, towards, boxes) & ~np.isin(node_id, list(ids))
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

    Returns ``(visibility, ray, source, weight, cos)``: per ray as in
    :func:`transmittance`, then one entry per blocking hit with weight >=
    :data:`BOUNCE_MIN_WEIGHT`: the ray it lies on, the blocking Gaussian's
    index in ``table``, its front-to-back blend weight and the cosine between
    the ray and the blocker's normal (``None`` for the four when nothing blocks).
    """
    vis, g, w = _shadow_trace(scene, origins, directions, maxt, nodes)
    keep = dr.compress(g.active & (w >= BOUNCE_MIN_WEIGHT))
    if dr.width(keep) == 0:
        return vis, None, None, None, None
    take = lambda a, T: dr.gather(T, a, keep)  # noqa: E731
    source = table.global_index(take(g.node_ids, mi.UInt32), take(g.prims, mi.UInt32))
    return vis, take(g.ray, mi.UInt32), source, take(w, mi.Float), take(g.cos_theta, mi.Float)


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
    #: Per entry, the cosine of the light's path to the blocking Gaussian's
    #: normal (where it leaves) and to the receiving one's (where it
    #: arrives): a coated surface (``diffuse_fresnel``) passes its diffuse
    #: light out and in through its coat at those angles.
    bounce_cos_source: mi.Float = None
    bounce_cos_target: mi.Float = None
    #: Per entry, which of the receiver's M sky samples it lies on: the
    #: specular lobe reads the light each sample brings.
    bounce_slot: mi.UInt32 = None
    #: (G, 3) unit normals the sky directions were traced about. A Gaussian's
    #: M directions turn with its normal; visibility traced for the old ones
    #: is not the new ones' (:func:`retrace_turned`).
    normals: np.ndarray = None
    #: Per node (the order of ``key``'s geometry), the world bounds (lo, hi)
    #: its Gaussians had when the sky was traced: what :func:`retrace_moved`
    #: tests the old rays against once the node has moved.
    boxes: list = None
    #: The same for the shapes that are not Gaussians (:func:`surfaces`).
    surface_boxes: list = None
    #: What ``moving_visibility`` was traced for: geometry and sun directions.
    moving_key: tuple = ()
    #: Per light, the moving shapes' shadow factor on a learned sun
    #: visibility (:func:`moving_shadows`; None for other lights).
    moving_visibility: list = field(default_factory=list)

    def sky_copy(self) -> "LightingCache":
        """A cache holding this one's sky visibility and bounce matrix (and
        what they were traced for), not its lights': another integrator
        with the same M, bounces and pattern, under other lights or another
        sun-visibility mode, starts from it instead of tracing the sky
        afresh (``eval``'s relighting after its scoring pass). The arrays
        are shared, never written in place, but the normals, which a
        re-trace updates in place, are copied."""
        return LightingCache(key=self.key, sky_visibility=self.sky_visibility,
                             bounce_target=self.bounce_target, bounce_source=self.bounce_source,
                             bounce_weight=self.bounce_weight,
                             bounce_cos_source=self.bounce_cos_source,
                             bounce_cos_target=self.bounce_cos_target,
                             bounce_slot=self.bounce_slot,
                             normals=None if self.normals is None else self.normals.copy(),
                             boxes=None if self.boxes is None else list(self.boxes),
                             surface_boxes=None if self.surface_boxes is None
                             else list(self.surface_boxes))


def geometry_key(nodes):
    """What traced visibility depends on of the nodes: their arrays' identities
    (a placement or an edit through ``mi.traverse`` makes new ones)."""
    return tuple((n.id, n.data.index, n.count) for n in nodes)


def surfaces(scene) -> list:
    """The scene's shapes that are not Gaussians (meshes, analytic shapes):
    they block the Gaussians' sky and shadow rays too."""
    return [shape for shape in scene.shapes() if not shape.is_ellipsoids()]


def surface_key(scene):
    """What traced visibility depends on of the shapes that are not
    Gaussians: per shape its id and the identity of its vertex array (a
    mesh) or its ``to_world`` (an analytic shape). Moving a mesh with
    :func:`~mi_invrgbl.scene.posing.place` writes new vertices: an inserted
    car driving along its track must shade the Gaussians under it anew on
    every frame, and without this key the cache kept the shadows of the
    first frame's placement (a roof moved 1.6 m over Gaussians left pixels
    up to 0.48 off a fresh load's)."""
    out = []
    for shape in surfaces(scene):
        params = mi.traverse(shape)
        if "vertex_positions" in params:
            ident = ("vertices", params["vertex_positions"].index)
        elif "to_world" in params:
            ident = tuple(np.array(params["to_world"].matrix, np.float64).ravel().round(7))
        else:
            box = shape.bbox()
            ident = tuple(np.concatenate([np.array(box.min, np.float64).ravel(),
                                          np.array(box.max, np.float64).ravel()]).round(7))
        out.append((shape.id(), ident))
    return tuple(out)


class SkyKey(NamedTuple):
    """What a cache's sky visibility (and bounce matrix) was traced for."""
    geometry: tuple     #: :func:`geometry_key` of the Gaussian nodes
    surfaces: tuple     #: :func:`surface_key` of the other shapes
    samples: int        #: M
    bounces: bool       #: whether the bounce matrix was recorded
    pattern: int        #: the directions' turn (:func:`hash_rotation_of`)


def cache_keys(scene, nodes, lights, samples, bounces=0, pattern=0, trace_sun=True):
    """``(sky key, light key)``: what a :class:`LightingCache` must have been
    traced for to be reused for these nodes, lights and settings (the one
    place both keys are made)."""
    with dr.suspend_grad():
        geometry, others = geometry_key(nodes), surface_key(scene)
        sky = SkyKey(geometry, others, int(samples), bool(bounces > 0), int(pattern))
        light = (geometry, others, _light_key(scene, lights, trace_sun), trace_sun)
    return sky, light


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


def sky_rays(table, samples, pattern=0, gaussians=None, normals=None):
    """The M sky rays of ``gaussians`` (global indices, numpy; default every
    Gaussian of the loaded ``table``), Gaussian-major: ``(Gaussian of each
    ray, origins, directions)``. Cosine-weighted about each one's normal
    (``normals``, a (G, 3) numpy array, or the table's) and turned by its
    :func:`hash_rotation_of`, from its centre. The one definition of the
    rays the sky's visibility is traced along."""
    M = int(samples)
    with dr.suspend_grad():
        idx = dr.arange(mi.UInt32, table.total) if gaussians is None else jit_array(mi.UInt32, gaussians)
        j = dr.arange(mi.UInt32, dr.width(idx) * M)
        g = dr.gather(mi.UInt32, idx, j // M)
        local = fibonacci_direction(mi.Float(j % M), M, hash_rotation_of(g, pattern))
        if normals is None:
            n = dr.gather(mi.Vector3f, dr.detach(table.normal), g)
        else:
            flat = jit_array(mi.Float, np.ascontiguousarray(normals, np.float32).ravel())
            n = mi.Vector3f(*[dr.gather(mi.Float, flat, g * 3 + c) for c in range(3)])
        return g, dr.gather(mi.Point3f, dr.detach(table.center), g), mi.Frame3f(n).to_world(local)


def trace_sky(scene, nodes, table, samples, pattern=0, bounces=0, gaussians=None):
    """Trace the M sky directions of ``gaussians`` (global indices, numpy;
    default every Gaussian of the loaded ``table``), cosine-weighted about
    each one's normal and turned by its :func:`hash_rotation_of`.

    Returns ``(visibility, bounce)``: visibility per ray (``len(gaussians) *
    M``, Gaussian-major), then with ``bounces`` the entries of the bounce
    matrix these rays add (:class:`BounceEntries`; ``None`` when nothing
    blocks or ``bounces`` is 0). The one place sky directions are traced: the first
    trace of a cache and :func:`retrace_turned` share it."""
    M = int(samples)
    with dr.suspend_grad():
        g, origins, dirs = sky_rays(table, M, pattern, gaussians)
        if bounces <= 0:
            return transmittance(scene, origins, dirs, mi.Float(dr.inf), nodes), None
        vis, ray, source, w, cos_source = shadow_blockers(scene, origins, dirs, mi.Float(dr.inf),
                                                          nodes, table)
        if ray is None:
            return vis, None
        target = dr.gather(mi.UInt32, g, ray)
        # The sample's cosine to the receiver's normal (its local z).
        cos_target = dr.dot(dr.gather(mi.Vector3f, dirs, ray),
                            dr.normalize(dr.gather(mi.Vector3f, dr.detach(table.normal), target)))
        return vis, BounceEntries(target, source, w / M, cos_source, cos_target, ray % M)


class BounceEntries(NamedTuple):
    """Entries of the bounce matrix W that one trace adds: receiving and
    blocking Gaussian, blend weight / M, and the cosines where the light
    leaves the blocker and arrives at the receiver, and the receiver's sky
    sample it lies on (:class:`LightingCache`)."""
    target: mi.UInt32
    source: mi.UInt32
    weight: mi.Float
    cos_source: mi.Float
    cos_target: mi.Float
    slot: mi.UInt32


#: The cache's fields that hold W, in :class:`BounceEntries`' order.
BOUNCE_FIELDS = ("bounce_target", "bounce_source", "bounce_weight", "bounce_cos_source",
                 "bounce_cos_target", "bounce_slot")
#: Their Dr.Jit types.
BOUNCE_TYPES = (mi.UInt32, mi.UInt32, mi.Float, mi.Float, mi.Float, mi.UInt32)


def set_bounce(cache, entries):
    """Hold ``entries`` (a :class:`BounceEntries` or None) as ``cache``'s W."""
    for name, value in zip(BOUNCE_FIELDS, entries if entries is not None else [None] * 6):
        setattr(cache, name, value)
    if entries is not None:
        dr.eval(*entries)


def _replace_rows(cache: LightingCache, gaussians, M, new_vis, bounce, normals):
    """Put the sky rays of ``gaussians`` (global indices, numpy uint32), just
    traced by :func:`trace_sky`, into ``cache``: their ``M`` entries of
    ``sky_visibility``, their rows of the bounce matrix (the other rows are
    kept) and their unit ``normals`` (the (G, 3) array they were traced
    about). The lights' shadow rays are traced again on the next build."""
    if cache.bounce_target is not None or bounce is not None:
        # Keep the other Gaussians' rows of W; these get their new rows.
        parts = []
        if cache.bounce_target is not None:
            old = [np.array(getattr(cache, name)) for name in BOUNCE_FIELDS]
            keep = ~np.isin(old[0], gaussians)
            parts.append([a[keep] for a in old])
        if bounce is not None:
            parts.append([np.array(a) for a in bounce])
        columns = [np.concatenate(col) for col in zip(*parts)]
        set_bounce(cache, BounceEntries(*[jit_array(T, c) for T, c in zip(BOUNCE_TYPES, columns)]))
    # A new array rather than a scatter into the cached one: lighting built
    # before this call may still read the old one. It is handed over padded
    # (:mod:`.host_arrays`): a NumPy buffer that ends at an unmapped page
    # crashes the next kernel that reads it, the likelier cause of the
    # SIGSEGVs once blamed on the scatter.
    slots = (gaussians.astype(np.int64)[:, None] * M + np.arange(M)).ravel()
    vis = np.array(cache.sky_visibility, np.float32)
    vis[slots] = np.array(new_vis, np.float32)
    cache.sky_visibility = jit_array(mi.Float, vis)
    dr.eval(cache.sky_visibility)
    cache.normals[gaussians] = normals[gaussians]
    # The lights' shadow rays leave along the normals too (shadow_origins):
    # trace them again on the next build (one ray per Gaussian and light).
    cache.light_key = None


#: A sky cache whose nodes moved is patched (:func:`retrace_moved`) while
#: the moved nodes hold at most this share of the Gaussians; past it the
#: static rays that meet them cost about what a fresh trace does.
PATCH_LIMIT = 0.5


def shape_boxes(shapes) -> list:
    """Per shape, its world bounds ``(lo, hi)`` (float64 numpy): the shape's
    own bounding box, the one the ray tracer's hierarchy is built from (for
    Gaussians, their traversal support); ``None`` for an empty shape."""
    out = []
    for shape in shapes:
        box = shape.bbox()
        lo = np.array(box.min, np.float64).ravel()
        hi = np.array(box.max, np.float64).ravel()
        ok = np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(hi >= lo)
        out.append((lo, hi) if ok else None)
    return out


def node_boxes(nodes) -> list:
    """:func:`shape_boxes` of the nodes' shapes; ``None`` for an empty node
    and for one whose arrays are not its shape's (the fit's virtual nodes,
    ``shape`` None: their bounds are unknown)."""
    return [None if node.count == 0 or node.shape is None else shape_boxes([node.shape])[0]
            for node in nodes]


class Moved(NamedTuple):
    """What moved since a cache traced the sky (:func:`moved_since`)."""
    nodes: list         #: positions in the Gaussian nodes
    surfaces: list      #: positions in :func:`surfaces`


def moved_since(cache: LightingCache, sky_key: SkyKey, nodes):
    """What changed since ``cache`` traced the sky, where
    :func:`retrace_moved` gives what a fresh trace would: the same settings
    (M, bounces, pattern), the same nodes with the same counts and the same
    other shapes, a few of them placed anew or edited (new arrays,
    :func:`geometry_key`, :func:`surface_key`), the moved nodes holding at
    most :data:`PATCH_LIMIT` of the Gaussians. ``None`` where the sky must
    be traced afresh (or nothing changed)."""
    old = cache.key
    if not isinstance(old, SkyKey) or cache.sky_visibility is None or cache.normals is None \
            or cache.boxes is None or cache.surface_boxes is None \
            or len(cache.boxes) != len(nodes) or old == sky_key:
        return None
    if (old.samples, old.bounces, old.pattern) != (sky_key.samples, sky_key.bounces,
                                                   sky_key.pattern) \
            or len(old.geometry) != len(sky_key.geometry) \
            or len(old.surfaces) != len(sky_key.surfaces) \
            or len(cache.surface_boxes) != len(sky_key.surfaces):
        return None
    moved = Moved([], [])
    for k, (a, b) in enumerate(zip(old.geometry, sky_key.geometry)):
        if a[0] != b[0] or a[2] != b[2]:
            return None     # another node, or Gaussians added or removed
        if a[1] != b[1]:
            if nodes[k].count and (nodes[k].shape is None or cache.boxes[k] is None):
                return None     # bounds unknown (a virtual node): nothing to test rays against
            moved.nodes.append(k)
    for k, (a, b) in enumerate(zip(old.surfaces, sky_key.surfaces)):
        if a[0] != b[0]:
            return None     # another shape
        if a[1] != b[1]:
            moved.surfaces.append(k)
    total = sum(n.count for n in nodes)
    if sum(nodes[k].count for k in moved.nodes) > PATCH_LIMIT * total:
        return None
    return moved


def retrace_moved(scene, nodes, cache: LightingCache, table, samples, pattern, bounces,
                  moved: Moved) -> int:
    """Re-trace the sky rays that what ``moved`` (from :func:`moved_since`)
    can have changed, into ``cache``; returns how many Gaussians were traced.

    Those are every ray of the moved nodes' own Gaussians (they moved, and
    their directions with them), and every other Gaussian's rays that meet
    a moved node's or shape's bounds as they were when the cache traced
    them or as they are now. Any other ray meets the same Gaussians and
    meshes as before, so its visibility and its bounce entries are what a
    fresh trace gives. ``eval`` and every frame of a rendered sequence place
    the moving objects anew; on the main job's street (one car) this traces
    a sixth of the Gaussians and takes a third of a fresh trace's time, on
    the KITTI excerpt (seven vehicles, 42 % of the Gaussians) three quarters
    of them (``tests/bench/bench_moving_frames.py``). ``table``: loaded
    (:meth:`GaussianTable.load_geometry`)."""
    M = int(samples)
    now = unit_normals(table)
    mine = np.zeros(table.total, bool)
    boxes = []
    new_boxes = node_boxes(nodes)
    new_surface_boxes = shape_boxes(surfaces(scene))
    for k in moved.nodes:
        off = table.offsets[k]
        mine[off:off + nodes[k].count] = True
        boxes += [b for b in (cache.boxes[k], new_boxes[k]) if b is not None]
    for k in moved.surfaces:
        boxes += [b for b in (cache.surface_boxes[k], new_surface_boxes[k]) if b is not None]
    others = np.flatnonzero(~mine).astype(np.uint32)
    meet = np.zeros(others.size, bool)
    if others.size and boxes:
        # The rays as the cache traced them: from the centres (unmoved),
        # about the normals it holds.
        _, origins, dirs = sky_rays(table, M, pattern, others, cache.normals)
        meet = rays_meeting(origins, dirs, boxes).reshape(-1, M).any(axis=1)
    gaussians = np.union1d(np.flatnonzero(mine), others[meet]).astype(np.uint32)
    if gaussians.size:
        new_vis, bounce = trace_sky(scene, nodes, table, M, pattern, bounces, gaussians)
        _replace_rows(cache, gaussians, M, new_vis, bounce, now)
    cache.boxes, cache.surface_boxes = new_boxes, new_surface_boxes
    return int(gaussians.size)


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
    new_vis, bounce = trace_sky(scene, nodes, table, M, pattern, bounces, turned)
    _replace_rows(cache, turned, M, new_vis, bounce, now)
    return int(turned.size)


def _add_into(values, index, size):
    """A Color3f of ``size`` zeros with ``values`` (Color3f) added at ``index``."""
    out = [dr.zeros(mi.Float, size) for _ in range(3)]
    for c in range(3):
        dr.scatter_reduce(dr.ReduceOp.Add, out[c], values[c], index)
    return mi.Color3f(*out)


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
        bounce light leaves its source through the source's coat and enters
        through the receiver's (:meth:`pass_on`).

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
        #: Gaussians whose sky rays this build traced (0: the cache's were reused).
        self.retraced = 0
        self.lights = point_lights(scene)
        if self.table.total == 0:
            return
        sky_key, light_key = cache_keys(scene, nodes, self.lights, self.samples, self.bounces,
                                        self.pattern, trace_sun)
        table = self.table.load_geometry()
        M, G = self.samples, self.table.total
        frames = mi.Frame3f(dr.gather(mi.Vector3f, table.normal,
                                      dr.arange(mi.UInt32, G * M) // M))
        local = fibonacci_hemisphere(M, _hash_rotation(G, self.pattern))
        self.sky_dirs = frames.to_world(local)           # (G*M,) differentiable in n
        if cache.key != sky_key or cache.light_key != light_key:
            if before_trace is not None:
                before_trace()
        # Only where nothing places the scene before a trace (the fit keys
        # its cache to one frame's placement; eval and rendered sequences
        # place the objects themselves, frame by frame).
        moved = moved_since(cache, sky_key, nodes) if before_trace is None and M else None
        if moved is not None:
            self.retraced = retrace_moved(scene, nodes, cache, table, M, self.pattern,
                                          self.bounces, moved)
            cache.key = sky_key
            if follow_normals:
                retrace_turned(scene, nodes, cache, M, pattern, self.bounces, max_turn_deg=0.0,
                               table=table)
        elif cache.key != sky_key:
            with dr.suspend_grad():
                set_bounce(cache, None)
                if M:
                    cache.sky_visibility, bounce = trace_sky(scene, nodes, table, M, self.pattern,
                                                             self.bounces)
                    set_bounce(cache, bounce)
                else:
                    cache.sky_visibility = mi.Float()
                dr.eval(cache.sky_visibility)
                cache.normals = unit_normals(table)
                cache.boxes = node_boxes(nodes)
                cache.surface_boxes = shape_boxes(surfaces(scene))
                cache.key = sky_key
                self.retraced = G
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
        #: Per Gaussian, the roughness of its coat (``diffuse_fresnel``), else None.
        self.coat_roughness = coat_roughness = None
        # Per entry of W, the blocker's coat transmission on the way out
        # (:meth:`_from_blockers`; computed once, used by the bounce and
        # by the specular lobe's blocked radiance).
        self._way_out = None
        if diffuse_fresnel:
            self.coat_roughness = coat_roughness = hitlib.gather_attribute(
                nodes, "roughness", table.ids, table.prims, mi.Bool(True))
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
        #: Radiance arriving along each sky sample (G * M, Gaussian-major):
        #: the sky where it is open, with ``bounces`` also the light the
        #: blocking Gaussians reflect towards it. The specular lobe reflects
        #: it (a window mirrors the facade across the street, not black).
        self.reflected_radiance = self.sky_radiance
        if self.bounces > 0:
            self.indirect, leaving = self.bounce_light(nodes)
            if M and self.cache.bounce_target is not None:
                self.reflected_radiance = self.sky_radiance + self.blocked_radiance(leaving)
        else:
            self.indirect = dr.zeros(mi.Color3f, G)
        self.diffuse = self.direct + self.indirect

    def bounce_light(self, nodes):
        """``(indirect, leaving)``: E / pi that reaches each Gaussian after
        1..``bounces`` diffuse bounces, and the diffuse radiance each one then
        sends out, ``albedo * (direct + indirect)`` (under its coat)."""
        table, G = self.table, self.table.total
        albedo = mi.Color3f(hitlib.gather_attribute(nodes, "albedo", table.ids, table.prims,
                                                    mi.Bool(True)))
        indirect = dr.zeros(mi.Color3f, G)
        if self.cache.bounce_target is not None:
            for _ in range(self.bounces):
                # Radiance leaving each Gaussian (Lambertian), passed along W.
                indirect = self.pass_on(albedo * (self.direct + indirect))
        return indirect, albedo * (self.direct + indirect)

    def blocked_radiance(self, leaving, through_coat=True):
        """Per sky sample (G * M), the radiance the Gaussians blocking it send
        along it: ``leaving`` (each Gaussian's diffuse radiance under its
        coat) taken out through the blocker's coat at the sample's angle,
        times its blend weight on the sample's ray. Its receiver's coat does
        not dim it: the specular lobe reflects it off the coat's surface.
        ``through_coat=False`` takes ``leaving`` as radiance already out of
        its coat (as :meth:`pass_on`)."""
        cache, M = self.cache, self.samples
        if cache.bounce_target is None or not M:
            return dr.zeros(mi.Color3f, self.table.total * M)
        # W holds the blend weight / M.
        return _add_into(self._from_blockers(leaving, through_coat) * M,
                         cache.bounce_target * M + cache.bounce_slot, self.table.total * M)

    def reflect_blockers(self, leaving, through_coat=True):
        """Let the specular lobe see ``leaving`` (one Color3f per Gaussian, as
        :meth:`blocked_radiance`) in the sky samples other Gaussians block,
        in place of the light the lighting found for them. Stage 2's start
        passes stage 1's colours: the albedos that would give the blockers'
        light are what the start is solving for."""
        self.reflected_radiance = self.sky_radiance + self.blocked_radiance(leaving, through_coat)

    def pass_on(self, leaving, through_coat=True):
        """``W leaving``: E / pi at each Gaussian from the radiance ``leaving``
        every Gaussian (Color3f, one per Gaussian) towards its sky directions.

        Under a coat (``diffuse_fresnel``) ``leaving`` is the base's diffuse
        light, ``albedo * E / pi``: each entry takes it out through the
        blocker's coat at the angle it leaves (:func:`~.coat.way_out`, as
        the integrator does towards a camera) and in through the receiver's
        at the angle it arrives (:func:`~.coat.transmission`, as the direct
        light). Without them a coated corner's bounce was 3.8x
        ``roughplastic``'s diffuse bounce, with them 1.06-1.07x
        (``tests/test_bounce.py``). ``through_coat=False``
        passes ``leaving`` as radiance already out of its coat (stage 2's
        start passes stage 1's colours on)."""
        cache, G = self.cache, self.table.total
        if cache.bounce_target is None:
            return dr.zeros(mi.Color3f, G)
        passed = self._from_blockers(leaving, through_coat)
        if self.coat_roughness is not None:
            tau_in = dr.gather(mi.Float, self.coat_roughness, cache.bounce_target)
            passed = passed * coat.transmission(cache.bounce_cos_target, tau_in, self.f0)
        return _add_into(passed, cache.bounce_target, G)

    def _from_blockers(self, leaving, through_coat=True):
        """Per entry of W: ``leaving`` (per Gaussian) at the entry's blocker,
        taken out through that blocker's coat at the angle the entry's sky
        ray leaves it (with a coat and ``through_coat``), times the entry's
        weight (blend weight / M). What :meth:`pass_on` brings in through
        the receivers' coats and :meth:`blocked_radiance` hands the lobe."""
        cache = self.cache
        weight = cache.bounce_weight
        if self.coat_roughness is not None and through_coat:
            # way_out = transmission(cos) * inner_scale(roughness): the
            # second depends on the source alone, so it is applied once
            # per Gaussian, not once per entry (there are far more).
            leaving = leaving * coat.inner_scale(self.coat_roughness, self.f0)
            if self._way_out is None:
                tau_out = dr.gather(mi.Float, self.coat_roughness, cache.bounce_source)
                self._way_out = coat.transmission(cache.bounce_cos_source, tau_out, self.f0)
            weight = weight * self._way_out
        return dr.gather(mi.Color3f, leaving, cache.bounce_source) * weight
        weight = cache.bounce_weight
        if self.coat_roughness is not None:
            tau_in = dr.gather(mi.Float, self.coat_roughness, cache.bounce_target)
            weight = weight * coat.transmission(cache.bounce_cos_target, tau_in, self.f0)
            if through_coat:
                # way_out = transmission(cos) * inner_scale(roughness): the
                # second depends on the source alone, so it is applied once
                # per Gaussian, not once per entry (there are far more).
                leaving = leaving * coat.inner_scale(self.coat_roughness, self.f0)
                tau_out = dr.gather(mi.Float, self.coat_roughness, cache.bounce_source)
                weight = weight * coat.transmission(cache.bounce_cos_source, tau_out, self.f0)
        passed = dr.gather(mi.Color3f, leaving, cache.bounce_source) * weight
        for c in range(3):
            dr.scatter_reduce(dr.ReduceOp.Add, out[c], passed[c], cache.bounce_target)
        return mi.Color3f(*out)
