"""Shadow carving (mi_invrgbl/fit/shadow_carving.py).

A sunlit ground of Gaussians under a sun at 45 degrees; above part of it
hangs a slab that shadows it. Which of the slab's Gaussians go depends only
on the masks: droppable ones on the receivers' shadow rays go, those the
masks keep (seen by a camera or the LiDAR) stay, and droppable ones beside
every shadow ray stay too.
"""

import numpy as np
import drjit as dr
import mitsuba as mi
import pytest

from mi_invrgbl.fit.shadow_carving import COS_MIN, LIT, carve_unseen_blockers, sunlit
from mi_invrgbl.physics import hits as hitlib
from mi_invrgbl.physics.lighting import GaussianTable

SUN = np.array([1.0, 0.0, 1.0]) / np.sqrt(2.0)
GRID = np.arange(-2.0, 2.0 + 1e-6, 0.1)
FINE = np.arange(-2.0, 2.0 + 1e-6, 0.05)
SLAB_X = np.arange(-1.0, 3.0 + 1e-6, 0.1)


def sheet(shape_id, xs, ys, z, normal=(0.0, 0.0, 1.0), spacing=0.1, opacity=0.95, seed=0):
    X, Y = np.meshgrid(xs, ys)
    c = np.stack([X.ravel(), Y.ravel(), np.full(X.size, z)], 1).astype(np.float32)
    # Jittered along z: discs entered at the same distance would hide each
    # other from the traversal.
    c[:, 2] += np.random.default_rng(seed).uniform(-0.02, 0.02, len(c)).astype(np.float32)
    n = len(c)
    s = 1.1 * spacing
    t = lambda a: mi.TensorXf(np.asarray(a, np.float32))  # noqa: E731
    return {"type": "gaussians", "id": shape_id, "centers": t(c),
            "scales": t(np.tile([[s, s, 1e-3]], (n, 1))), "opacities": t(np.full(n, opacity)),
            "normals": t(np.tile([normal], (n, 1))), "albedo": t(np.tile([[0.5, 0.5, 0.5]], (n, 1)))}


@pytest.fixture(scope="module")
def scene():
    grid = GRID
    return mi.load_dict({
        "type": "scene",
        # Four receivers per slab Gaussian: each slab disc is the first hit of
        # several shadow rays, as blockers above a densely seen street are.
        "ground": sheet("ground", FINE, FINE, 0.0, spacing=0.05),
        # 2 m up: the shadow ray of a ground point (x, y) leaves 0.1 m above it and
        # meets z = 2 at x + 1.9, so the slab's x in [-0.1, 3] shadows the ground and
        # the part below x = -0.1 no ground point.
        "slab": sheet("slab", SLAB_X, grid, 2.0, seed=1),
        # Far to the side of every shadow ray (y beyond the ground's extent).
        "aside": sheet("aside", grid, np.arange(6.0, 7.0 + 1e-6, 0.1), 2.0, seed=2),
    })


def masks(scene, droppable_nodes, receiver_nodes=("ground",), keep=None):
    table = GaussianTable.build(hitlib.gaussian_nodes(scene))
    rec = np.zeros(table.total, bool)
    drop = np.zeros(table.total, bool)
    index = {}
    for node, off in zip(table.nodes, table.offsets):
        name = node.shape.id()
        index[name] = slice(off, off + node.count)
        if name in receiver_nodes:
            rec[off:off + node.count] = True
        if name in droppable_nodes:
            drop[off:off + node.count] = True
    if keep is not None:
        drop &= ~keep(table, index)
    return rec, drop, index


def free_fraction(scene, dropped, receivers):
    """Share of the receivers whose sun a trace through the scene without
    ``dropped`` leaves above one half (traced independently of the carving)."""
    from mi_invrgbl.physics.lighting import shadow_origins, transmittance
    p = mi.traverse(scene)
    nodes = hitlib.gaussian_nodes(scene)
    table = GaussianTable.build(nodes)
    saved = {}
    for node, off in zip(table.nodes, table.offsets):
        key = node.shape.id() + ".opacities"
        saved[key] = mi.Float(p[key])
        p[key] = mi.Float(np.where(dropped[off:off + node.count], 0.0, np.array(p[key])).astype(np.float32))
    p.update()
    try:
        g = GaussianTable.build(nodes).load_geometry()
        d = [float(v) for v in SUN]
        o = np.array(shadow_origins(g, dr.zeros(mi.Vector3f, g.total) + mi.Vector3f(*d)), np.float32).T[receivers]
        with dr.suspend_grad():
            t = transmittance(scene, mi.Point3f(*[mi.Float(o[:, k]) for k in range(3)]),
                              dr.zeros(mi.Vector3f, len(o)) + mi.Vector3f(*d), mi.Float(dr.inf), nodes)
        return float(np.mean(np.array(t) > 0.5))
    finally:
        for k, v in saved.items():
            p[k] = v
        p.update()


def opacities(scene):
    p = mi.traverse(scene)
    return {k: np.array(p[k]).copy() for k in p.keys() if k.endswith(".opacities")}


def test_unseen_blockers_of_sunlit_gaussians_go_and_the_scene_is_restored(scene):
    before = opacities(scene)
    rec, drop, index = masks(scene, ("slab", "aside"))
    dropped, report = carve_unseen_blockers(scene, rec, drop, SUN)
    slab = dropped[index["slab"]]
    X, Y = np.meshgrid(SLAB_X, GRID)
    x = X.ravel()
    assert not slab[x < -0.6].any()    # 4.5 standard deviations from every shadow ray
    # The rest of the slab need not all go: where discs overlap in one plane the
    # traversal registers some of them on no ray, and those block no light in a
    # relit scene either (it traces the same way). What counts is the light.
    assert slab[(x > 0.2) & (x < 2.8)].mean() > 0.5
    assert report.shadowed_before > 0.5 and report.shadowed_after == 0.0
    assert free_fraction(scene, dropped, rec) == 1.0
    assert not dropped[index["aside"]].any()
    assert not dropped[index["ground"]].any()          # not droppable
    assert report.dropped and sum(report.dropped) == dropped.sum()
    after = opacities(scene)
    assert all(np.array_equal(before[k], after[k]) for k in before)


def test_seen_blockers_stay(scene):
    rec, drop, index = masks(scene, ("aside",))
    dropped, report = carve_unseen_blockers(scene, rec, drop, SUN)
    assert not dropped.any() and report.dropped == []
    assert report.shadowed_before == report.shadowed_after > 0.05


def test_no_receivers_or_nothing_droppable_traces_nothing(scene):
    rec, drop, _ = masks(scene, ("slab",), receiver_nodes=())
    dropped, report = carve_unseen_blockers(scene, rec, drop, SUN)
    assert not dropped.any() and report.receivers == 0


@pytest.mark.parametrize("direction", [(0.0, 0.0, 0.0), (np.nan, 0.0, 1.0), (1.0, 0.0)])
def test_a_direction_that_is_none_is_refused(scene, direction):
    rec, drop, _ = masks(scene, ("slab",))
    with pytest.raises(ValueError, match="direction"):
        carve_unseen_blockers(scene, rec, drop, direction)


def test_masks_of_the_wrong_length_are_refused(scene):
    rec, drop, _ = masks(scene, ("slab",))
    with pytest.raises(ValueError, match="masks"):
        carve_unseen_blockers(scene, rec[:-1], drop, SUN)


def test_a_receiver_is_lit_and_faces_the_sun():
    # Turned away from the sun, a Gaussian's learned visibility had no
    # gradient (its sun term is zero): it is no evidence of a clear path.
    d = np.array([0.0, 0.0, 2.0])   # not unit: normalised
    up, down = [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]
    grazing = [np.sqrt(1 - (COS_MIN / 2) ** 2), 0.0, COS_MIN / 2]
    normals = np.array([up, up, down, grazing, [0.0, 0.0, 3.0]])
    vis = np.array([1.0, LIT - 1e-3, 1.0, 1.0, LIT])
    assert sunlit(vis, normals, d).tolist() == [True, False, False, False, True]
