"""Gaussians no training sensor sees (mi_invrgbl/fit/unseen.py).

A row of rays meets a wall; above the rays' reach the wall goes on (an
extension above a roof no camera looked past), and behind the opaque part
of the wall stands a second wall no ray reaches. Only the front of the
band the rays meet is seen, and removing the rest leaves what the rays
see; a pixel left out by a mask gives no evidence.
"""

import numpy as np
import drjit as dr
import mitsuba as mi

import gaussian_walls
from mi_invrgbl.fit.unseen import accumulate, frame_weights, unseen_masks
from mi_invrgbl.physics import hits as hitlib


def wall(shape_id, x, z0, z1, opacity):
    return gaussian_walls.wall(shape_id, x, (-1.0, 1.0), (z0, z1), (0.5, 0.5, 0.5), opacity, seed=3)


def scene_and_rays():
    walls = {"front": wall("front", 5.0, 0.0, 4.0, 0.99), "behind": wall("behind", 8.0, 0.0, 1.0, 0.99)}
    scene = mi.load_dict(dict({"type": "scene"}, **walls))
    ys, zs = np.meshgrid(np.linspace(-0.9, 0.9, 40), np.linspace(0.2, 1.0, 12))
    o = mi.Point3f(mi.Float(np.zeros(ys.size)), mi.Float(ys.ravel()), mi.Float(zs.ravel()))
    rays = mi.Ray3f(o, mi.Vector3f(dr.ones(mi.Float, ys.size), 0.0, 0.0))
    ids = {s.id(): hitlib.shape_id(s) for s in scene.shapes()}
    centres = {name: np.array(walls[name]["centers"]).reshape(-1, 3) for name in ids}
    return scene, rays, ids, centres, zs.ravel()


def weights(scene, rays, ids, centres, valid=None):
    acc = {name: np.zeros(len(c)) for name, c in centres.items()}
    with dr.suspend_grad():
        stats = frame_weights(scene, rays, 64, valid)
    assert all(np.all(np.isfinite(a)) for a in stats)
    accumulate(acc, ids, stats)
    return acc


def subset(shape, keep):
    return {k: (mi.TensorXf(np.array(v)[keep]) if isinstance(v, mi.TensorXf) else v)
            for k, v in shape.items()}


def transmittance(scene, rays):
    from mi_invrgbl.physics.lighting import transmittance as t
    return np.array(t(scene, rays.o, rays.d, mi.Float(dr.inf), hitlib.gaussian_nodes(scene)))


def test_only_what_the_rays_meet_is_seen():
    scene, rays, ids, centres, _ = scene_and_rays()
    acc = weights(scene, rays, ids, centres)
    z = centres["front"][:, 2]
    seen = acc["front"] >= 0.05
    # The wall's extension above the rays is not seen, nor the wall behind
    # the opaque one; of the band the rays cross, the Gaussians in front of
    # the layer are (those behind them in the same layer get no weight).
    assert not seen[z > 1.5].any()
    assert not (acc["behind"] >= 0.05).any()
    band = (z > 0.3) & (z < 0.9) & (np.abs(centres["front"][:, 1]) < 0.8)
    assert seen[band].mean() > 0.3
    # Removing every unseen Gaussian leaves what the rays see.
    walls = {"front": wall("front", 5.0, 0.0, 4.0, 0.99)}
    kept = mi.load_dict({"type": "scene", "front": subset(walls["front"], seen)})
    full = mi.load_dict({"type": "scene", **walls})
    before, after = transmittance(full, rays), transmittance(kept, rays)
    change = np.abs(after - before)
    print("unseen: %d of %d; transmittance before %.4f after %.4f (change: 95th percentile "
          "%.4f, max %.4f)" % ((~seen).sum(), seen.size, before.mean(), after.mean(),
                               np.percentile(change, 95), change.max()))
    # Each removed Gaussian had under 0.05 of blend weight summed over all
    # rays; a ray at the band's edge that only grazed several of them sees
    # more change (measured max 0.22, 95th percentile below 0.01).
    assert np.percentile(change, 95) < 0.02 and abs(after.mean() - before.mean()) < 0.005


def test_masked_pixels_give_no_evidence():
    scene, rays, ids, centres, zs = scene_and_rays()
    valid = zs < 0.6
    acc = weights(scene, rays, ids, centres, valid)
    z = centres["front"][:, 2]
    seen = acc["front"] >= 0.05
    assert not seen[z > 0.85].any()
    assert seen[(z > 0.3) & (z < 0.5) & (np.abs(centres["front"][:, 1]) < 0.8)].mean() > 0.3


def test_no_rays_meet_anything():
    scene, _, ids, centres, _ = scene_and_rays()
    rays = mi.Ray3f(mi.Point3f(dr.zeros(mi.Float, 8), 0.0, 1.0),
                    mi.Vector3f(dr.zeros(mi.Float, 8), 0.0, -1.0))
    acc = weights(scene, rays, ids, centres)
    assert all(not a.any() for a in acc.values())


def test_a_node_nothing_sees_is_kept_whole():
    masks = unseen_masks({"seen": np.array([0.0, 0.2, 0.01]), "never": np.zeros(4)})
    assert masks["seen"].tolist() == [True, False, True]
    assert not masks["never"].any()
