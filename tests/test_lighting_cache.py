"""The ``invrgbl`` lighting cache follows the Gaussians' normals.

Each Gaussian's M sky directions are cosine-weighted about its normal, so
they turn with it. A scene whose normals were changed through
``mi.traverse`` after a render must render as the same scene loaded fresh
with those normals (its visibility and bounce matrix traced from nothing):
:func:`~mi_invrgbl.physics.lighting.retrace_turned` re-traces only the
turned Gaussians and must give the full trace's result.
"""

import drjit as dr
import mitsuba as mi
import numpy as np

from test_bounce import gaussian_corner

from mi_invrgbl.physics.lighting import GaussianLighting, LightingCache, retrace_turned
from mi_invrgbl.physics import hits as hitlib


def turn_normals(scene, degrees, every=2, seed=3):
    """Turn every ``every``-th Gaussian's normal of each layer by ``degrees``."""
    params = mi.traverse(scene)
    rng = np.random.default_rng(seed)
    for key in [k for k in params.keys() if k.endswith(".normal")]:
        n = np.array(params[key], np.float64).reshape(-1, 3)
        t = rng.normal(size=n.shape)
        t -= np.sum(t * n, axis=1, keepdims=True) * n
        t /= np.linalg.norm(t, axis=1, keepdims=True)
        a = np.radians(degrees)
        turned = n.copy()
        turned[::every] = np.cos(a) * n[::every] + np.sin(a) * t[::every]
        params[key] = mi.Float(turned.ravel().astype(np.float32))
    params.update()


def test_render_after_turning_normals_matches_a_fresh_load():
    scene = mi.load_dict(gaussian_corner(1, samples=16))
    before = np.array(mi.render(scene, spp=1, seed=0))
    turn_normals(scene, 25.0)
    after = np.array(mi.render(scene, spp=1, seed=0))
    fresh = mi.load_dict(gaussian_corner(1, samples=16))
    turn_normals(fresh, 25.0)
    reference = np.array(mi.render(fresh, spp=1, seed=0))
    assert np.all(np.isfinite(after))
    # The change is visible...
    assert np.abs(after - before)[..., :3].max() > 0.02
    # ...and the re-traced cache renders as a full trace does.
    np.testing.assert_allclose(after[..., :3], reference[..., :3], atol=2e-5)


def bounce_triples(cache):
    if cache.bounce_target is None:
        return np.zeros((0, 3))
    t = np.array(cache.bounce_target, np.float64)
    s = np.array(cache.bounce_source, np.float64)
    w = np.array(cache.bounce_weight, np.float64)
    order = np.lexsort((w, s, t))
    return np.stack([t, s, w], axis=1)[order]


def test_retrace_turned_equals_a_full_trace_and_skips_small_turns():
    scene = mi.load_dict(gaussian_corner(1, samples=8))
    nodes = hitlib.gaussian_nodes(scene)
    cache = LightingCache()
    GaussianLighting(scene, nodes, 8, cache, bounces=1)
    traced_before = np.array(cache.sky_visibility)
    first = LightingCache()
    first.bounce_target, first.bounce_source, first.bounce_weight = (
        mi.UInt32(cache.bounce_target), mi.UInt32(cache.bounce_source), mi.Float(cache.bounce_weight))
    # A turn below the threshold re-traces nothing.
    turn_normals(scene, 0.5, every=1)
    nodes = hitlib.gaussian_nodes(scene)
    assert retrace_turned(scene, nodes, cache, 8, bounces=1, max_turn_deg=1.0) == 0
    np.testing.assert_array_equal(np.array(cache.sky_visibility), traced_before)
    # Half of them turned by 30 degrees: those are traced again.
    turn_normals(scene, 30.0, every=2)
    nodes = hitlib.gaussian_nodes(scene)
    count = retrace_turned(scene, nodes, cache, 8, bounces=1, max_turn_deg=1.0)
    total = sum(n.count for n in nodes)
    assert total // 2 <= count < total
    full = LightingCache()
    GaussianLighting(scene, nodes, 8, full, bounces=1)
    # The 0.5-degree turn left un-retraced is below the threshold: compare
    # where a full trace and the retraced cache used the same directions.
    same = np.repeat(np.sum(cache.normals * full.normals, axis=1) > 1 - 1e-6, 8)
    assert same.mean() >= 0.5
    # Mitsuba's ellipsoid intersector answers a ray according to the other
    # rays traced in its SIMD packet (rolling the ray order by one moved a
    # quarter of this corner's first hits, by 16 none), and the shadow rays
    # start inside their Gaussians: about 1 % of them change visibility by
    # more than 1e-3 when traced in another batch. The re-traced subset is
    # another batch, so most, not all, entries must agree (tracing the turned
    # directions as if unturned agrees on about 65 %).
    diff = np.abs(np.array(cache.sky_visibility) - np.array(full.sky_visibility))[same]
    assert np.mean(diff < 1e-3) > 0.97 and np.mean(diff < 0.05) > 0.99
    # The same for the bounce matrix: the re-traced rows hold as much weight
    # per Gaussian as a full trace's, and the other rows are kept as they were.
    rows = np.flatnonzero(np.sum(cache.normals * full.normals, axis=1) > 1 - 1e-6)
    a, b = bounce_triples(cache), bounce_triples(full)
    a, b = a[np.isin(a[:, 0], rows)], b[np.isin(b[:, 0], rows)]
    assert a.shape[0] > 0 and abs(a.shape[0] - b.shape[0]) <= 0.05 * b.shape[0]
    wa = np.bincount(a[:, 0].astype(int), a[:, 2], minlength=total)[rows]
    wb = np.bincount(b[:, 0].astype(int), b[:, 2], minlength=total)[rows]
    assert np.mean(np.abs(wa - wb) < 1e-3) > 0.95
    kept = np.setdiff1d(np.arange(total), rows)
    before = bounce_triples(first)
    after = bounce_triples(cache)
    np.testing.assert_array_equal(after[np.isin(after[:, 0], kept)],
                                  before[np.isin(before[:, 0], kept)])


def test_retrace_turned_keeps_visibility_finite_for_degenerate_normals():
    scene = mi.load_dict(gaussian_corner(0, samples=8))
    nodes = hitlib.gaussian_nodes(scene)
    cache = LightingCache()
    GaussianLighting(scene, nodes, 8, cache)
    params = mi.traverse(scene)
    key = [k for k in params.keys() if k.endswith(".normal")][0]
    n = np.array(params[key]).reshape(-1, 3)
    n[0] = 0.0            # a zero normal: the table falls back to a unit vector
    n[1] = [0, 0, -1]     # flipped
    params[key] = mi.Float(n.ravel())
    params.update()
    nodes = hitlib.gaussian_nodes(scene)
    assert retrace_turned(scene, nodes, cache, 8) >= 1
    vis = np.array(cache.sky_visibility)
    assert np.all(np.isfinite(vis)) and vis.min() >= 0 and vis.max() <= 1 + 1e-6
    dr.eval()


def test_moving_the_sun_retraces_the_lights_not_the_sky():
    # The sun trial and the start's candidates switch the sun back and forth;
    # each switch must not pay for the sky's G x M shadow rays again, and the
    # lights' visibility must be what a fresh cache traces for the new sun.
    scene = mi.load_dict(gaussian_corner(1, samples=8))
    nodes = hitlib.gaussian_nodes(scene)
    cache = LightingCache()
    GaussianLighting(scene, nodes, 8, cache, bounces=1)
    sky, target = cache.sky_visibility, cache.bounce_target
    lit_before = np.array(cache.light_visibility[0])
    params = mi.traverse(scene)
    key = [k for k in params.keys() if k.endswith("sun_direction")][0]
    params[key] = mi.Vector3f(-0.6, 0.3, 0.5)   # lights the wall's back: its front in shadow
    params.update()
    moved = GaussianLighting(scene, nodes, 8, cache, bounces=1)
    assert cache.sky_visibility is sky and cache.bounce_target is target
    fresh = LightingCache()
    reference = GaussianLighting(scene, nodes, 8, fresh, bounces=1)
    lit = np.array(cache.light_visibility[0])
    assert np.mean(np.abs(lit - lit_before) > 0.5) > 0.05       # the sun did move
    np.testing.assert_allclose(lit, np.array(fresh.light_visibility[0]), atol=1e-5)
    np.testing.assert_allclose(np.array(moved.diffuse), np.array(reference.diffuse), atol=1e-5)
    # Stored sun visibility (a learned field) leaves the sky's trace alone too.
    GaussianLighting(scene, nodes, 8, cache, trace_sun=False, bounces=1)
    assert cache.sky_visibility is sky and cache.light_visibility == [None]


def test_switching_the_sun_off_and_on_keeps_the_sky_and_retraces_the_sun():
    # The sun trial switches between no sun (irradiance 0: the emitter
    # drops its sun) and a sun: the lights' visibility follows each switch,
    # the sky's is traced once.
    scene = mi.load_dict(gaussian_corner(1, samples=8))
    nodes = hitlib.gaussian_nodes(scene)
    cache = LightingCache()
    GaussianLighting(scene, nodes, 8, cache, bounces=1)
    sky, lit = cache.sky_visibility, np.array(cache.light_visibility[0])
    params = mi.traverse(scene)
    key = [k for k in params.keys() if k.endswith("sun_irradiance")][0]
    on = mi.Color3f(params[key])
    params[key] = mi.Color3f(0.0)
    params.update()
    off = GaussianLighting(scene, nodes, 8, cache, bounces=1)
    assert cache.sky_visibility is sky and cache.light_visibility == [] and off.light_irr == []
    params[key] = on
    params.update()
    GaussianLighting(scene, nodes, 8, cache, bounces=1)
    assert cache.sky_visibility is sky
    np.testing.assert_allclose(np.array(cache.light_visibility[0]), lit, atol=1e-5)


# ------------------------------------------------------------------ moved nodes
def roof_over_ground(samples=16):
    """A ground layer and a small roof (another node) 0.3 m above it, at x = -0.8."""
    from test_invrgbl import camera, layer, sky
    ground, _ = layer(extent=2.0, spacing=0.1)
    roof, _ = layer(extent=0.2, spacing=0.08, shape_id="roof", albedo=(0.2, 0.3, 0.8))
    roof["to_world"] = mi.ScalarTransform4f().translate([-0.8, 0.0, 0.3])
    return {"type": "scene",
            "integrator": {"type": "invrgbl", "samples": samples, "bounces": 1},
            "ground": ground, "roof": roof, "sky": sky(sun_direction=[0.3, -0.2, 1.0]),
            "sensor": camera([0.0, -3.0, 2.0], [0, 0, 0], size=32)}


def move_roof(scene, x):
    from mi_invrgbl.scene.posing import place
    to = np.eye(4)
    to[:3, 3] = [x, 0.0, 0.3]
    loaded = np.eye(4)
    loaded[:3, 3] = [-0.8, 0.0, 0.3]
    place(scene, {"roof": to}, {"roof": loaded})


def mean_visibility(cache, M):
    return np.array(cache.sky_visibility, np.float64).reshape(-1, M).mean(axis=1)


def test_a_moved_node_retraces_only_the_rays_it_can_change():
    M = 16
    scene = mi.load_dict(roof_over_ground(M))
    cache = LightingCache()
    built = GaussianLighting(scene, hitlib.gaussian_nodes(scene), M, cache, bounces=1)
    total = sum(n.count for n in hitlib.gaussian_nodes(scene))
    assert built.retraced == total
    before = np.array(cache.sky_visibility)
    first = bounce_triples(cache)
    move_roof(scene, 0.8)
    nodes = hitlib.gaussian_nodes(scene)
    roof = next(n for n in nodes if n.id != nodes[0].id and n.count < nodes[0].count)
    patched = GaussianLighting(scene, nodes, M, cache, bounces=1)
    # The roof's own Gaussians and the ground under its old and new place,
    # not the whole ground.
    assert roof.count < patched.retraced < 0.5 * total
    full = LightingCache()
    GaussianLighting(scene, nodes, M, full, bounces=1)
    new, ref, old = mean_visibility(cache, M), mean_visibility(full, M), before.reshape(-1, M).mean(1)
    # The move changes the sky of many ground Gaussians (uncovered at the
    # old place, covered at the new one)...
    ground = slice(0, nodes[0].count)
    changed = np.abs(ref[ground] - old[ground]) > 0.05
    assert changed.sum() > 40
    assert (ref[ground] - old[ground] > 0.05).sum() > 20 and (ref[ground] - old[ground] < -0.05).sum() > 20
    # ...and the patched cache follows a fresh trace wherever it changed (up
    # to the intersector's batch dependence, see above).
    diff = np.abs(new - ref)
    assert np.mean(diff < 1e-3) > 0.97 and diff.max() < 0.1
    assert np.all(diff[ground][changed] < 0.05)
    # Rays that were not traced again kept their values exactly.
    kept = np.abs(np.array(cache.sky_visibility) - before) == 0
    assert kept.mean() > 0.3
    # The bounce matrix: per receiving Gaussian as much weight as a fresh trace.
    a, b = bounce_triples(cache), bounce_triples(full)
    wa = np.bincount(a[:, 0].astype(int), a[:, 2], minlength=total)
    wb = np.bincount(b[:, 0].astype(int), b[:, 2], minlength=total)
    assert np.mean(np.abs(wa - wb) < 1e-3) > 0.95 and np.abs(wa - wb).max() < 0.1
    assert not np.array_equal(a, first)


def test_a_render_after_moving_a_node_matches_a_fresh_load():
    scene = mi.load_dict(roof_over_ground())
    mi.render(scene, spp=1, seed=0)
    move_roof(scene, 0.5)
    after = np.array(mi.render(scene, spp=1, seed=0))
    fresh = mi.load_dict(roof_over_ground())
    move_roof(fresh, 0.5)
    reference = np.array(mi.render(fresh, spp=1, seed=0))
    assert np.all(np.isfinite(after))
    err = np.abs(after - reference)[..., :3]
    assert np.mean(err < 1e-3) > 0.98 and err.max() < 0.05


def test_other_changes_trace_the_sky_afresh():
    from mi_invrgbl.physics.lighting import cache_keys, moved_since, point_lights
    scene = mi.load_dict(roof_over_ground(8))
    nodes = hitlib.gaussian_nodes(scene)
    cache = LightingCache()
    GaussianLighting(scene, nodes, 8, cache)
    lights = point_lights(scene)
    key = lambda M=8, bounces=0, pattern=0: cache_keys(scene, nodes, lights, M, bounces,  # noqa: E731
                                                        pattern)[0]
    assert cache.key == key() and moved_since(cache, key(), nodes) is None   # nothing moved
    move_roof(scene, 0.2)
    nodes = hitlib.gaussian_nodes(scene)
    moved = moved_since(cache, key(), nodes)
    assert moved.nodes == [1] and moved.surfaces == []
    # Another M, pattern or bounce setting: every ray is another ray.
    for other in (key(M=16), key(bounces=1), key(pattern=1)):
        assert moved_since(cache, other, nodes) is None
    # The ground moved too: more than PATCH_LIMIT of the Gaussians.
    params = mi.traverse(scene)
    data = np.array(params["ground.data"])
    data[2::10] += 0.01
    params["ground.data"] = mi.Float(data)
    params.update()
    nodes = hitlib.gaussian_nodes(scene)
    assert moved_since(cache, key(), nodes) is None
    built = GaussianLighting(scene, nodes, 8, cache)
    assert built.retraced == sum(n.count for n in nodes)


def roof_mesh_over_ground():
    """:func:`roof_over_ground` with the roof a mesh (an inserted object)."""
    d = roof_over_ground()
    d["roof"] = {"type": "cube", "id": "roof",
                 "to_world": mi.ScalarTransform4f().translate([-0.8, 0.0, 0.45])
                 @ mi.ScalarTransform4f().scale([0.25, 0.25, 0.05])}
    return d


def test_a_moved_mesh_shades_the_gaussians_as_a_fresh_load():
    """An inserted mesh driving along its track: the Gaussians under its old
    place get their sky (and sun) back, those under the new one lose it."""
    scene = mi.load_dict(roof_mesh_over_ground())
    nodes = hitlib.gaussian_nodes(scene)
    first = np.array(mi.render(scene, spp=1, seed=0))
    move_roof(scene, 0.8)
    after = np.array(mi.render(scene, spp=1, seed=0))
    fresh = mi.load_dict(roof_mesh_over_ground())
    move_roof(fresh, 0.8)
    reference = np.array(mi.render(fresh, spp=1, seed=0))
    assert np.abs(reference - first)[..., :3].max() > 0.1      # the move shows
    err = np.abs(after - reference)[..., :3]
    assert np.mean(err < 1e-3) > 0.98 and err.max() < 0.05
    # Only the ground under the mesh's old and new place was traced again.
    cache = LightingCache()
    GaussianLighting(scene, nodes, 16, cache)
    move_roof(scene, 0.0)
    built = GaussianLighting(scene, hitlib.gaussian_nodes(scene), 16, cache)
    assert 0 < built.retraced < 0.5 * nodes[0].count


def test_a_sky_copy_serves_another_integrator_without_a_trace():
    """``eval`` relights with a second integrator (traced sun) that starts
    from the scoring pass's sky: nothing is traced again, the lights are."""
    scene = mi.load_dict(roof_over_ground(8))
    nodes = hitlib.gaussian_nodes(scene)
    cache = LightingCache()
    GaussianLighting(scene, nodes, 8, cache, bounces=1, trace_sun=False)
    copy = cache.sky_copy()
    assert copy.light_key == () and copy.light_visibility == []
    built = GaussianLighting(scene, nodes, 8, copy, bounces=1, trace_sun=True)
    assert built.retraced == 0 and len(copy.light_visibility) == 1
    np.testing.assert_array_equal(np.array(copy.sky_visibility), np.array(cache.sky_visibility))
    # A move patches the copy; the original keeps its own normals and sky.
    before = np.array(cache.sky_visibility)
    normals = cache.normals.copy()
    move_roof(scene, 0.5)
    patched = GaussianLighting(scene, hitlib.gaussian_nodes(scene), 8, copy, bounces=1)
    assert 0 < patched.retraced < sum(n.count for n in nodes)
    np.testing.assert_array_equal(np.array(cache.sky_visibility), before)
    np.testing.assert_array_equal(cache.normals, normals)


def test_nodes_whose_bounds_are_unknown_are_traced_afresh():
    """The fit's virtual nodes carry arrays that are not their shape's
    (``shape`` None): a move of one cannot be patched. An empty node has
    no bounds and moves nothing."""
    from types import SimpleNamespace
    from mi_invrgbl.physics.lighting import (cache_keys, moved_since, node_boxes, point_lights,
                                             shape_boxes)
    scene = mi.load_dict(roof_over_ground(8))
    nodes = hitlib.gaussian_nodes(scene)
    cache = LightingCache()
    GaussianLighting(scene, nodes, 8, cache)
    move_roof(scene, 0.3)
    moved = hitlib.gaussian_nodes(scene)
    key = cache_keys(scene, moved, point_lights(scene), 8)[0]
    assert moved_since(cache, key, moved).nodes == [1]
    virtual = [moved[0], SimpleNamespace(id=moved[1].id, data=moved[1].data,
                                         count=moved[1].count, shape=None)]
    assert node_boxes(virtual)[1] is None
    assert moved_since(cache, key, virtual) is None
    empty = SimpleNamespace(id=7, data=mi.Float(), count=0, shape=None)
    assert node_boxes([empty]) == [None]
    # A shape whose box is not finite gives no bounds either.
    bad = SimpleNamespace(bbox=lambda: SimpleNamespace(min=[np.nan, 0, 0], max=[1, 1, 1]))
    assert shape_boxes([bad]) == [None]
