"""Ray traversal of Gaussians: detached hit lists, differentiable blending.

Both integrators work in two phases, the split that makes them fast and their
gradients correct:

1. :func:`trace` follows each ray through the scene *without derivatives*. It
   records, per ray, up to ``max_hits`` Gaussians (node id + primitive index)
   in the order the ray enters their support, and the first opaque (mesh) hit
   behind them. Traversal stops when the transmittance drops below
   ``min_transmittance``. This is one symbolic Dr.Jit loop, i.e. one kernel.
2. :func:`eval_gaussian_hits` gathers the recorded Gaussians' parameters from
   the shapes' own (possibly grad-enabled) arrays and computes each hit's
   opacity and geometry differentiably; :func:`blend_weights` turns them into
   front-to-back compositing weights ``w_k = a_k prod_j (1 - a_j)`` over the
   hits ``j`` whose response peaks lie in front of ``k``'s.

While geometry is frozen, a :class:`HitList` can be traced once and reused
for every gradient step (only phase 2 runs).

Hits are stored ray-major in flat arrays of length ``n_rays * max_hits``
(index ``ray * max_hits + k``), so per-ray sums are ``dr.block_sum``.

The Gaussian response along a ray is evaluated at its maximum (as in 3DGRT):
``a = min(opacity * exp(-r^2 / 2), alpha_max)`` with ``r`` the Mahalanobis
distance of the closest point of the ray.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

# Per-Gaussian attribute widths and the defaults a plain ``ellipsoids`` shape
# without them reads: from the one table of per-Gaussian fields.
from .fields import ATTRIBUTE_DEFAULTS, ATTRIBUTE_WIDTHS

#: Largest per-hit opacity: keeps log(1 - a) finite for the transmittance.
ALPHA_MAX = 0.99
#: Minimum scale used when mapping rays into a Gaussian's frame.
MIN_SCALE = 1e-7
#: Traversal records a Gaussian hit only from within this distance (scene
#: units); a farther one is approached first (see :func:`trace`).
APPROACH = 0.05
#: Share of a far hit's distance the ray stops short of it when approaching.
APPROACH_BACKOFF = 0.01
#: Approaches allowed per ray beyond its hits (each divides the distance by 100).
MAX_APPROACHES = 16


def shape_id(shape) -> int:
    """The Dr.Jit registry id of a shape, as stored in hit lists (0 = none)."""
    return int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(shape))[0])


class GaussianNode:
    """View of one ``ellipsoids``/``gaussians`` shape's parameter arrays.

    The arrays are those ``mi.traverse`` exposes, so gradients enabled by the
    user on e.g. ``params['background.albedo']`` flow through the integrators.
    """

    def __init__(self, shape):
        self.shape = shape
        self.id = shape_id(shape)
        params = mi.traverse(shape)
        self.data = params["data"]
        self.opacities = params["opacities"]
        self.attributes = {k: params[k] for k in ATTRIBUTE_WIDTHS if k in params}
        self.count = dr.width(self.opacities)


def gaussian_nodes(scene) -> list:
    return [GaussianNode(s) for s in scene.shapes() if s.is_ellipsoids()]


def _gather_scalar(array, index, stride, offset, active):
    return dr.gather(mi.Float, array, index * stride + offset, active)


def gather_geometry(nodes, node_ids, prims, active):
    """Centre, scale, unit quaternion and opacity of the addressed Gaussians."""
    center, scale = mi.Point3f(0), mi.Vector3f(1)
    quat = mi.Quaternion4f(0, 0, 0, 1)
    opacity = mi.Float(0)
    for node in nodes:
        m = active & (node_ids == node.id)
        g = [_gather_scalar(node.data, prims, 10, j, m) for j in range(10)]
        center = dr.select(m, mi.Point3f(g[0], g[1], g[2]), center)
        scale = dr.select(m, mi.Vector3f(g[3], g[4], g[5]), scale)
        quat = dr.select(m, mi.Quaternion4f(g[6], g[7], g[8], g[9]), quat)
        opacity = dr.select(m, dr.gather(mi.Float, node.opacities, prims, m), opacity)
    # Normalise: users and optimisers may leave non-unit quaternions behind.
    quat = quat * dr.rsqrt(dr.maximum(dr.squared_norm(quat), 1e-20))
    return center, dr.maximum(scale, MIN_SCALE), quat, opacity


def gather_attribute(nodes, name, node_ids, prims, active):
    """Per-hit material attribute ``name`` (Float or Color3f/Vector3f)."""
    width = ATTRIBUTE_WIDTHS[name]
    value = mi.Vector3f(0) if width == 3 else mi.Float(ATTRIBUTE_DEFAULTS.get(name, 0.0))
    if width == 3 and name in ATTRIBUTE_DEFAULTS:
        value = mi.Vector3f(ATTRIBUTE_DEFAULTS[name])
    for node in nodes:
        if name not in node.attributes:
            continue
        m = active & (node_ids == node.id)
        arr = node.attributes[name]
        if width == 3:
            v = mi.Vector3f(*[_gather_scalar(arr, prims, 3, j, m) for j in range(3)])
        else:
            v = dr.gather(mi.Float, arr, prims, m)
        value = dr.select(m, v, value)
    return value


def gaussian_response(center, scale, quat, opacity, o, d):
    """Peak opacity of each Gaussian along ray (o, d), the peak distance and the
    shortest-axis normal.

    Returns ``(alpha, t_peak, shortest_axis)``; alpha is clamped to ALPHA_MAX.
    """
    rot = dr.quat_to_matrix(mi.Matrix3f, quat)
    rot_t = rot.T
    o_local = (rot_t @ (o - center)) / scale
    d_local = (rot_t @ d) / scale
    dd = dr.maximum(dr.squared_norm(d_local), 1e-30)
    t_peak = -dr.dot(o_local, d_local) / dd
    closest = o_local + d_local * t_peak
    alpha = dr.minimum(opacity * dr.exp(-0.5 * dr.squared_norm(closest)), ALPHA_MAX)
    # Shortest axis: column of the rotation with the smallest scale.
    sx, sy, sz = scale.x, scale.y, scale.z
    col0 = mi.Vector3f(rot[0][0], rot[1][0], rot[2][0])
    col1 = mi.Vector3f(rot[0][1], rot[1][1], rot[2][1])
    col2 = mi.Vector3f(rot[0][2], rot[1][2], rot[2][2])
    axis = dr.select((sx <= sy) & (sx <= sz), col0, dr.select(sy <= sz, col1, col2))
    return alpha, t_peak, axis


@dataclass
class HitList:
    """Recorded traversal of ``n_rays`` rays (see module docstring)."""
    n_rays: int
    max_hits: int
    node_ids: mi.UInt32        # (n_rays * max_hits,), 0 where unused
    prims: mi.UInt32           # (n_rays * max_hits,)
    count: mi.UInt32           # (n_rays,) Gaussians recorded per ray
    surface: mi.PreliminaryIntersection3f  # first opaque hit behind them
    surface_valid: mi.Bool     # (n_rays,)
    index: mi.UInt32 = None    # flat slots that hold a Gaussian (compacted)

    def __post_init__(self):
        if self.index is None:
            # Shading touches only occupied slots: rays see far fewer Gaussians
            # than max_hits on average, so this saves most of the work.
            self.index = dr.compress(self.node_ids != 0)
            if dr.width(self.index) == 0:
                # No Gaussian was hit: keep one empty slot (node id 0, so
                # inactive) so that every per-hit array has a valid size.
                self.index = dr.zeros(mi.UInt32, 1)

    @property
    def hit_count(self) -> int:
        return dr.width(self.index)

    def ray_index(self):
        """Ray of each compacted hit."""
        return self.index // self.max_hits

    def surface_interaction(self, rays):
        """Full SurfaceInteraction3f at the opaque hits (invalid elsewhere)."""
        return self.surface.compute_surface_interaction(
            rays, mi.RayFlags.All, self.surface_valid)


@dr.syntax
def trace(scene, rays, max_hits=64, min_transmittance=1e-3, nodes=None):
    """Record each ray's Gaussians and first opaque hit (no derivatives).

    ``rays`` is a Ray3f of n rays with unit directions. Returns a :class:`HitList`.
    """
    with dr.suspend_grad():
        nodes = gaussian_nodes(scene) if nodes is None else nodes
        n = dr.width(rays.o)
        K = int(max_hits)
        node_buf = dr.zeros(mi.UInt32, n * K)
        prim_buf = dr.zeros(mi.UInt32, n * K)
        base = dr.arange(mi.UInt32, n) * K

        o = mi.Point3f(rays.o)
        d = mi.Vector3f(rays.d)
        t_offset = mi.Float(0)
        count = mi.UInt32(0)
        transmittance = mi.Float(1)
        surf = dr.zeros(mi.PreliminaryIntersection3f, n)
        surf_valid = mi.Bool(False)
        active = mi.Bool(True)
        maxt = mi.Float(rays.maxt)
        last_sid = mi.UInt32(0)
        last_prim = mi.UInt32(0)
        steps = mi.UInt32(0)

        while active:
            # Mitsuba's Ray3f(o, d, x) reads x as the time, not maxt: set maxt explicitly.
            ray = mi.Ray3f(o, d)
            ray.maxt = maxt - t_offset
            pi = scene.ray_intersect_preliminary(ray, False, active)
            valid = active & pi.is_valid()
            sid = dr.reinterpret_array(mi.UInt32, pi.shape)
            is_gaussian = mi.Bool(False)
            for node in nodes:
                is_gaussian |= sid == node.id
            is_gaussian &= valid

            # Opaque surface: remember it (distance from the ray's true origin)
            # and stop; nothing behind it is visible.
            is_surface = valid & ~is_gaussian
            hit_pi = mi.PreliminaryIntersection3f(pi)
            hit_pi.t = pi.t + t_offset
            surf[is_surface] = hit_pi
            surf_valid |= is_surface

            # The ellipsoid intersector reports a Gaussian where the ray enters
            # it, so the next ray starts just past that entry, inside it, and
            # does not see it again. Two precision limits shape the walk:
            # - For flat Gaussians the intersector's entry distance is off by
            #   about 1e-3 of the distance travelled (Mitsuba 3.9.1: 1.1 mm
            #   at 1.5 m for a 10:1 Gaussian), enough to report a later
            #   Gaussian of a surface first and skip the ones really entered
            #   before it (up to 19 % of a beam's intensity lost at normal
            #   incidence on a dense layer). A hit farther than APPROACH is
            #   therefore not recorded: the ray moves to 99 % of its distance
            #   and asks again from close by, where the error is small.
            # - Flat Gaussians side by side enter at nearly the same distance,
            #   so the step past an entry is a few float32 ulps of the
            #   distance, not a fixed length. Where the intersector's error
            #   puts the new origin still in front of the entry, it reports
            #   the same Gaussian again: that repeat is not recorded, and the
            #   ray steps past it by a larger margin.
            approach = is_gaussian & (pi.t > APPROACH)
            repeat = is_gaussian & ~approach & (sid == last_sid) & (pi.prim_index == last_prim)
            record = is_gaussian & ~repeat & ~approach
            center, scale, quat, opacity = gather_geometry(nodes, sid, pi.prim_index, record)
            alpha, _, _ = gaussian_response(center, scale, quat, opacity, o, d)
            slot = base + count
            dr.scatter(node_buf, sid, slot, record)
            dr.scatter(prim_buf, pi.prim_index, slot, record)
            count[record] += 1
            transmittance[record] *= 1.0 - alpha
            last_sid[record] = sid
            last_prim[record] = pi.prim_index

            reach = pi.t + t_offset
            step = dr.select(approach, (1.0 - APPROACH_BACKOFF) * pi.t,
                             pi.t + dr.select(repeat, 1e-5 + 1e-6 * reach, 1e-7 + 4e-7 * reach))
            o[is_gaussian] = o + d * step
            t_offset[is_gaussian] += step
            steps += 1
            active = (is_gaussian & (count < K) & (transmittance > min_transmittance)
                      & (steps < 2 * K + MAX_APPROACHES))

        dr.eval(node_buf, prim_buf, count, surf, surf_valid)
        return HitList(n, K, node_buf, prim_buf, count, surf, surf_valid)


def expand_rays(rays, hits: HitList):
    """Per-hit copies (one per compacted hit) of each ray's origin and direction."""
    idx = hits.ray_index()
    o = dr.gather(mi.Point3f, rays.o, idx)
    d = dr.gather(mi.Vector3f, rays.d, idx)
    return o, d


@dataclass
class GaussianHits:
    """Differentiable per-hit quantities, one entry per compacted hit."""
    alpha: mi.Float
    t: mi.Float            # distance from the ray origin to the response peak
    normal: mi.Vector3f    # unit normal facing the ray
    cos_theta: mi.Float    # |n . d|
    active: mi.Bool
    node_ids: mi.UInt32
    prims: mi.UInt32
    ray: mi.UInt32         # ray of each hit
    slot: mi.UInt32        # flat slot (ray * max_hits + k)
    n_rays: int
    max_hits: int


def eval_gaussian_hits(scene_or_nodes, rays, hits: HitList):
    """Per-hit opacity, peak distance and ray-facing normal (differentiable)."""
    nodes = scene_or_nodes if isinstance(scene_or_nodes, list) else gaussian_nodes(scene_or_nodes)
    node_ids = dr.gather(mi.UInt32, hits.node_ids, hits.index)
    prims = dr.gather(mi.UInt32, hits.prims, hits.index)
    active = node_ids != 0
    o, d = expand_rays(rays, hits)
    center, scale, quat, opacity = gather_geometry(nodes, node_ids, prims, active)
    alpha, t_peak, axis = gaussian_response(center, scale, quat, opacity, o, d)
    normal = axis
    has_normal = mi.Bool(False)
    for node in nodes:
        if "normal" in node.attributes:
            has_normal |= node_ids == node.id
    stored = gather_attribute(nodes, "normal", node_ids, prims, active & has_normal)
    normal = dr.select(has_normal, stored, normal)
    normal = normal * dr.rsqrt(dr.maximum(dr.squared_norm(normal), 1e-20))
    cos_d = dr.dot(normal, d)
    normal = dr.select(cos_d > 0, -normal, normal)  # two-sided: face the ray
    alpha = dr.select(active, alpha, 0.0)
    return GaussianHits(alpha, dr.maximum(t_peak, 0.0), normal, dr.abs(cos_d), active,
                        node_ids, prims, hits.ray_index(), hits.index, hits.n_rays, hits.max_hits)


def blend_weights(g: GaussianHits):
    """Front-to-back weights ``w_k`` (per hit) and the transmittance left behind (per ray).

    ``w_k = a_k prod_{j in front of k} (1 - a_j)``, where "in front" orders a
    ray's recorded hits by the distance of their response peaks (ties by the
    order the ray met them), as 3DGRT's k-buffer does. :func:`trace` records
    Gaussians in the order the ray enters their support, which is not the
    order they occlude in: a large Gaussian's support (3 sigma) begins well in
    front of its peak, so in entry order it covered the smaller Gaussians that
    sit on the surface in front of its peak. On the KITTI excerpt, stage 1
    fitted to one view alone stalled near 22 dB that way
    (``tests/bench/stage1_steps.py --only-frame``).

    Each hit's rank among its ray's hits is counted from the detached peak
    distances (a fixed loop over the ``max_hits`` slots, no derivatives);
    the opacities then go through the same differentiable scatter, blocked
    prefix sum and gather as in slot order, at the ranked positions.
    """
    K = g.max_hits
    size = g.n_rays * K
    first = g.ray * K
    with dr.suspend_grad():
        t_own = dr.detach(g.t)
        peak = dr.full(mi.Float, dr.inf, size)
        dr.scatter(peak, t_own, g.slot)
        own = g.slot - first
        rank = dr.zeros(mi.UInt32, dr.width(g.slot))
        for j in range(K):
            t_j = dr.gather(mi.Float, peak, first + j)
            rank += dr.select((t_j < t_own) | ((t_j == t_own) & (own > j)), 1, 0)
        ranked = first + rank
    log_t = dr.zeros(mi.Float, size)
    dr.scatter(log_t, dr.log(1.0 - g.alpha), ranked)
    t_before = dr.exp(dr.gather(mi.Float, dr.block_prefix_sum(log_t, K, exclusive=True), ranked))
    t_after = dr.exp(dr.block_sum(log_t, K))
    return g.alpha * t_before, t_after


def composite(g: GaussianHits, weights, values):
    """Per-ray sum of ``w_k * value_k`` (values per hit: Float or 3-vectors)."""
    def reduce(v):
        out = dr.zeros(mi.Float, g.n_rays)
        dr.scatter_reduce(dr.ReduceOp.Add, out, v, g.ray)
        return out
    if isinstance(values, (float, int)):
        values = mi.Float(values)
    v = weights * values
    if isinstance(v, mi.Float):
        return reduce(v)
    return type(v)(*[reduce(v[i]) for i in range(len(v))])


def composite_front_to_back(g: GaussianHits, weights, t_after, per_hit: dict, behind: dict = None):
    """Alpha compositing of every channel: ``sum_k w_k c_k + T c_behind``.

    ``weights`` and ``t_after`` come from :func:`blend_weights` (or a frozen
    trace); ``per_hit`` maps a channel name to its per-hit values (or a
    constant, e.g. 1 for the accumulated opacity); ``behind`` maps a channel
    name to the per-ray value of what the ray meets behind the Gaussians (a
    mesh, the sky), already zero where there is nothing, seen through the
    transmittance ``T`` they leave. Returns channel name -> per-ray value.
    Every integrator and the fit composite through this one function.
    """
    out = {name: composite(g, weights, v) for name, v in per_hit.items()}
    for name, v in (behind or {}).items():
        out[name] = out[name] + t_after * v
    return out


def ad_integrator_base():
    """Mitsuba's Python ``ADIntegrator`` base class for the active variant."""
    import importlib
    import mitsuba.python.ad.integrators.common as common
    if mi.CppADIntegrator not in common.ADIntegrator.__mro__:
        common = importlib.reload(common)
    return common.ADIntegrator


def surface_bsdfs(scene):
    """The distinct BSDFs of the scene's non-Gaussian shapes."""
    seen, out = set(), []
    for shape in scene.shapes():
        if shape.is_ellipsoids():
            continue
        bsdf = shape.bsdf()
        if bsdf is not None and id(bsdf) not in seen:
            seen.add(id(bsdf))
            out.append(bsdf)
    return out


def surface_lidar_material(scene, si, active, model="pbr", f0=0.04):
    """LiDAR reflectance at opaque (mesh) hits.

    Returns ``(factor, lidar_albedo)`` where ``factor = pi f_r(w, w)`` seen by a
    co-located LiDAR. A BSDF with a ``material()`` method (``cooktorrance``)
    supplies its LiDAR albedo and roughness to the paper's equation; any other
    BSDF is evaluated with light and viewer co-located (RGB luminance).
    """
    from . import brdf
    cos_theta = dr.abs(mi.Frame3f.cos_theta(si.wi))
    factor, rho = mi.Float(0), mi.Float(0)
    bsdf_ptr = si.bsdf()
    for bsdf in surface_bsdfs(scene):
        m = active & (bsdf_ptr == mi.BSDFPtr(bsdf))
        material = getattr(bsdf, "material", None)
        if material is not None:
            _, tau, rho_l = material(si, m)
            f = brdf.lidar_return_factor(rho_l, tau, cos_theta, model, f0)
            r = rho_l
        else:
            ctx = mi.BSDFContext()
            if model == "lambertian":
                ctx.type_mask = mi.BSDFFlags.DiffuseReflection
            value = bsdf.eval(ctx, si, si.wi, m)
            f = dr.pi * mi.luminance(value) / dr.maximum(cos_theta, 1e-6)
            r = f
        factor = dr.select(m, f, factor)
        rho = dr.select(m, r, rho)
    return factor, rho
