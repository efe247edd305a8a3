"""Gaussians that only stand in for the sky (mi_invrgbl/fit/sky_lookalikes.py).

Three semi-transparent walls face a row of cameras under a uniform sky:
a sky-coloured wall with nothing behind it (a wall extended above a lower
roof), the same sky-coloured wall in front of a dark building, and a dark
wall in front of the sky. Only the first may go: removing it leaves every
pixel as it is, removing either of the others does not.
"""

import numpy as np
import drjit as dr
import mitsuba as mi

from mi_invrgbl.fit.sky_lookalikes import accumulate, frame_statistics, lookalike_masks

SKY = np.array([0.3, 0.38, 0.5])


def wall(shape_id, x, y0, y1, colour, opacity, spacing=0.1):
    ys = np.arange(y0, y1 + 1e-6, spacing)
    zs = np.arange(0.0, 2.0 + 1e-6, spacing)
    Y, Z = np.meshgrid(ys, zs)
    c = np.stack([np.full(Y.size, x), Y.ravel(), Z.ravel()], 1).astype(np.float32)
    # Jittered in depth too: discs entered at the same distance would hide
    # each other from the traversal (it steps just past each entry point).
    c += np.random.default_rng(2).uniform(-0.03, 0.03, c.shape).astype(np.float32)
    n = c.shape[0]
    s = 1.1 * spacing
    t = lambda a: mi.TensorXf(np.asarray(a, np.float32))  # noqa: E731
    return {"type": "gaussians", "id": shape_id, "centers": t(c),
            "scales": t(np.tile([[1e-3, s, s]], (n, 1))), "opacities": t(np.full(n, opacity)),
            "normals": t(np.tile([[-1.0, 0, 0]], (n, 1))), "albedo": t(np.tile([colour], (n, 1)))}


def test_only_the_sky_coloured_wall_against_the_sky_is_a_lookalike():
    # Order-0 SH: radiance = c0 * 0.2821, the same in every direction.
    sh = " ".join("%.6f" % (v / 0.28209479) for v in SKY)
    scene = mi.load_dict({
        "type": "scene",
        "sky": {"type": "shsun", "order": 0, "sh": sh, "sun_irradiance": [0.0, 0.0, 0.0]},
        "phantom": wall("phantom", 5.0, -4.0, -2.0, SKY, 0.3),
        "front": wall("front", 5.0, 2.0, 4.0, SKY, 0.3),
        "building": wall("building", 8.0, 1.0, 5.0, (0.05, 0.05, 0.05), 0.99),
        "dark": wall("dark", 5.0, -1.0, 1.0, (0.1, 0.08, 0.06), 0.3),
    })
    # Parallel rays towards +x through all three walls' middles.
    ys, zs = np.meshgrid(np.linspace(-3.8, 3.8, 160), np.linspace(0.3, 1.7, 20))
    o = mi.Point3f(mi.Float(np.zeros(ys.size)), mi.Float(ys.ravel()), mi.Float(zs.ravel()))
    rays = mi.Ray3f(o, mi.Vector3f(dr.ones(mi.Float, ys.size), 0.0, 0.0))
    from mi_invrgbl.physics import hits as hitlib
    ids = {s.id(): hitlib.shape_id(s) for s in scene.shapes()}
    acc = {name: np.zeros((dr.width(mi.traverse(scene)[name + ".opacities"]), 3)) for name in ids}
    with dr.suspend_grad():
        stats = frame_statistics(scene, rays)
    assert all(np.all(np.isfinite(a)) for a in stats[:3])
    accumulate(acc, ids, stats)
    masks = lookalike_masks(acc)
    seen = {name: acc[name][:, 0] > 0.05 for name in ids}
    for name in ids:
        print(name, seen[name].sum(), masks[name].sum())
    assert seen["phantom"].sum() > 50
    assert np.mean(masks["phantom"][seen["phantom"]]) > 0.9
    for name in ("front", "building", "dark"):
        assert seen[name].sum() > 50 and not masks[name].any(), name


def test_no_hits_no_lookalikes():
    scene = mi.load_dict({"type": "scene", "sky": {"type": "shsun", "order": 0, "sh": "1 1 1"},
                          "far": wall("far", 50.0, -1.0, 1.0, SKY, 0.3)})
    rays = mi.Ray3f(mi.Point3f(dr.zeros(mi.Float, 8), 0.0, 1.0), mi.Vector3f(dr.zeros(mi.Float, 8), 0.0, 1.0))
    with dr.suspend_grad():
        ids, prims, w, c_off, b_off = frame_statistics(scene, rays)
    assert ids.size == 0 and w.size == 0
    acc = {"far": np.zeros((441, 3))}
    accumulate(acc, {"far": 1}, (ids, prims, w, c_off, b_off))
    assert not lookalike_masks(acc)["far"].any()


def test_a_wall_too_dense_to_see_through_gives_no_evidence():
    # Behind an opaque sky-coloured wall the trace ends: whether sky or a
    # building is behind it is unknown, so it is kept.
    sh = " ".join("%.6f" % (v / 0.28209479) for v in SKY)
    scene = mi.load_dict({"type": "scene", "sky": {"type": "shsun", "order": 0, "sh": sh},
                          "opaque": wall("opaque", 5.0, -1.0, 1.0, SKY, 0.99)})
    ys = np.linspace(-0.8, 0.8, 64)
    rays = mi.Ray3f(mi.Point3f(mi.Float(np.zeros(64)), mi.Float(ys), mi.Float(np.ones(64))),
                    mi.Vector3f(dr.ones(mi.Float, 64), 0.0, 0.0))
    with dr.suspend_grad():
        stats = frame_statistics(scene, rays)
    acc = {"opaque": np.zeros((dr.width(mi.traverse(scene)["opaque.opacities"]), 3))}
    from mi_invrgbl.physics import hits as hitlib
    accumulate(acc, {"opaque": hitlib.shape_id(scene.shapes()[0])}, stats)
    assert (acc["opaque"][:, 0] > 0.05).sum() > 5
    assert not lookalike_masks(acc)["opaque"].any()


def test_sky_coloured_wall_in_front_of_a_mesh_is_kept():
    sh = " ".join("%.6f" % (v / 0.28209479) for v in SKY)
    scene = mi.load_dict({
        "type": "scene", "sky": {"type": "shsun", "order": 0, "sh": sh},
        "front": wall("front", 5.0, -1.0, 1.0, SKY, 0.3),
        "mesh": {"type": "rectangle", "bsdf": {"type": "diffuse"},
                 "to_world": mi.ScalarTransform4f().translate([8.0, 0.0, 1.0])
                 @ mi.ScalarTransform4f().rotate([0, 1, 0], -90) @ mi.ScalarTransform4f().scale(3.0)}})
    ys, zs = np.meshgrid(np.linspace(-0.8, 0.8, 32), np.linspace(0.3, 1.7, 8))
    rays = mi.Ray3f(mi.Point3f(mi.Float(np.zeros(ys.size)), mi.Float(ys.ravel()), mi.Float(zs.ravel())),
                    mi.Vector3f(dr.ones(mi.Float, ys.size), 0.0, 0.0))
    from mi_invrgbl.physics import hits as hitlib
    front = [s for s in scene.shapes() if s.id() == "front"][0]
    with dr.suspend_grad():
        stats = frame_statistics(scene, rays)
    acc = {"front": np.zeros((dr.width(mi.traverse(scene)["front.opacities"]), 3))}
    accumulate(acc, {"front": hitlib.shape_id(front)}, stats)
    assert (acc["front"][:, 0] > 0.05).sum() > 5
    assert not lookalike_masks(acc)["front"].any()


def test_the_unseen_part_of_a_column_above_a_lookalike_goes_with_it():
    # The sky-coloured phantom wall again, but the cameras see only its lower
    # part (rays at z 0.1-0.7 m): its upper part stands for what the import
    # extends above every camera's view. Beside it, the dark wall's upper part
    # is as unseen but stands on no look-alike: it stays.
    from mi_invrgbl.fit.sky_lookalikes import unseen_above
    from mi_invrgbl.physics import hits as hitlib
    sh = " ".join("%.6f" % (v / 0.28209479) for v in SKY)
    walls = {"phantom": wall("phantom", 5.0, -4.0, -2.0, SKY, 0.3),
             "dark": wall("dark", 5.0, -1.0, 1.0, (0.1, 0.08, 0.06), 0.3)}
    scene = mi.load_dict({"type": "scene", "sky": {"type": "shsun", "order": 0, "sh": sh}, **walls})
    ys, zs = np.meshgrid(np.linspace(-3.8, 0.8, 160), np.linspace(0.1, 0.7, 12))
    o = mi.Point3f(mi.Float(np.zeros(ys.size)), mi.Float(ys.ravel()), mi.Float(zs.ravel()))
    rays = mi.Ray3f(o, mi.Vector3f(dr.ones(mi.Float, ys.size), 0.0, 0.0))
    ids = {s.id(): hitlib.shape_id(s) for s in scene.shapes()}
    acc = {name: np.zeros((dr.width(mi.traverse(scene)[name + ".opacities"]), 3)) for name in ids}
    with dr.suspend_grad():
        accumulate(acc, ids, frame_statistics(scene, rays))
    masks = lookalike_masks(acc)
    for name in ids:
        centres = walls[name]["centers"].numpy()
        seen = acc[name][:, 0] > 0.05
        over = unseen_above(centres, masks[name], acc[name][:, 0])
        assert not (over & masks[name]).any() and not (over & seen).any()
        high = centres[:, 2] > 1.2
        if name == "phantom":
            assert masks[name].sum() > 50 and not masks[name][high].any()
            # Every column (0.25 m cell) that has a look-alike loses all it
            # has above 1.2 m; nearly every column has one.
            cell = lambda p: np.floor(p[:, :2] / 0.25).astype(int) @ [1, 1000]  # noqa: E731
            in_col = np.isin(cell(centres), cell(centres[masks[name]]))
            assert np.all(over[high & in_col]) and over[high].mean() > 0.8
            assert not over[centres[:, 2] < 0.5].any()
        else:
            assert not over.any()


def test_unseen_above_keeps_other_columns_and_what_lies_below():
    from mi_invrgbl.fit.sky_lookalikes import unseen_above
    c = np.array([[0.1, 0.1, 5.0],     # look-alike
                  [0.1, 0.1, 6.0],     # unseen above it: goes
                  [0.12, 0.1, 7.0],    # same cell, unseen: goes
                  [0.1, 0.1, 8.0],     # seen above it: keeps its own verdict
                  [0.1, 0.1, 4.0],     # unseen below it: stays
                  [0.4, 0.1, 9.0]])    # next cell: stays
    look = np.array([True, False, False, False, False, False])
    w = np.array([1.0, 0.0, 0.01, 0.5, 0.0, 0.0])
    assert unseen_above(c, look, w).tolist() == [False, True, True, False, False, False]
    assert not unseen_above(c, np.zeros(6, bool), w).any()
    assert unseen_above(np.zeros((0, 3)), np.zeros(0, bool), np.zeros(0)).shape == (0,)
