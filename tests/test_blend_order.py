"""Compositing order of the Gaussians a ray meets (physics/hits.blend_weights).

Hits are blended in the order of their response peaks along the ray, not
the order the ray enters their supports. Checked against a sorted numpy
reference (ties, unused slots), by finite differences, and on a scene where
the two orders disagree: a large Gaussian whose support begins in front of a
small opaque one but whose peak lies behind it.
"""

import numpy as np
import drjit as dr
import mitsuba as mi

from mi_invrgbl.fit.render import camera_unlit
from mi_invrgbl.physics import hits as hitlib


def make_hits(alpha, t, K):
    """A GaussianHits over (ray, slot) lists: rows of ``alpha``/``t`` are rays,
    NaN marks an unused slot."""
    n = alpha.shape[0]
    used = ~np.isnan(alpha)
    ray, k = np.nonzero(used)
    slot = (ray * K + k).astype(np.uint32)
    a = mi.Float(alpha[used].astype(np.float32))
    g = hitlib.GaussianHits(a, mi.Float(t[used].astype(np.float32)), dr.zeros(mi.Vector3f, len(slot)),
                            dr.zeros(mi.Float, len(slot)), dr.full(mi.Bool, True, len(slot)),
                            dr.ones(mi.UInt32, len(slot)), mi.UInt32(k.astype(np.uint32)),
                            mi.UInt32(ray.astype(np.uint32)), mi.UInt32(slot), n, K)
    return g, ray, k


def reference(alpha, t):
    """Per used slot: alpha times the product of (1 - a) over the hits whose
    peak is nearer (ties: the earlier slot first); per ray: the product of all."""
    w = np.full(alpha.shape, np.nan)
    after = np.ones(alpha.shape[0])
    for r in range(alpha.shape[0]):
        ks = [k for k in range(alpha.shape[1]) if not np.isnan(alpha[r, k])]
        order = sorted(ks, key=lambda k: (t[r, k], k))
        trans = 1.0
        for k in order:
            w[r, k] = alpha[r, k] * trans
            trans *= 1.0 - alpha[r, k]
        after[r] = trans
    return w, after


def test_weights_follow_the_peaks_not_the_slots():
    rng = np.random.default_rng(0)
    K, n = 6, 40
    alpha = rng.uniform(0.05, 0.95, (n, K))
    t = rng.uniform(0.5, 5.0, (n, K))
    t[:, 3] = t[:, 1]                       # ties: slot order decides
    for r in range(n):                      # rays with fewer hits, one with none
        alpha[r, (r % (K + 1)):] = np.nan
    g, ray, k = make_hits(alpha, t, K)
    w, after = hitlib.blend_weights(g)
    w_ref, after_ref = reference(alpha, t)
    np.testing.assert_allclose(np.array(w), w_ref[ray, k], rtol=2e-5, atol=1e-6)
    np.testing.assert_allclose(np.array(after), after_ref, rtol=2e-5, atol=1e-6)
    # Sorted by slot the answer differs: the test would catch entry order.
    entry = np.where(np.isnan(alpha), 0, alpha)
    front = np.concatenate([np.ones((n, 1)), np.cumprod(1 - entry, 1)[:, :-1]], 1)
    assert np.abs((entry * front)[ray, k] - w_ref[ray, k]).max() > 0.1


def test_weights_gradient_matches_finite_differences():
    rng = np.random.default_rng(1)
    K, n = 5, 8
    alpha = rng.uniform(0.1, 0.8, (n, K))
    t = rng.uniform(0.5, 5.0, (n, K))
    colour = rng.uniform(0, 1, (n, K))
    used = ~np.isnan(alpha)

    def loss(a_np, grad=False):
        g, ray, k = make_hits(a_np, t, K)
        if grad:
            dr.enable_grad(g.alpha)
        w, after = hitlib.blend_weights(g)
        out = dr.sum(w * mi.Float(colour[ray, k].astype(np.float32))) + 0.3 * dr.sum(after)
        if grad:
            dr.backward(out)
            return np.array(dr.grad(g.alpha))
        return float(out[0]) if dr.width(out) else float(out)

    grad = loss(alpha, grad=True)
    eps = 1e-3
    fd = []
    for r, c in zip(*np.nonzero(used)):
        up, dn = alpha.copy(), alpha.copy()
        up[r, c] += eps
        dn[r, c] -= eps
        fd.append((loss(up) - loss(dn)) / (2 * eps))
    np.testing.assert_allclose(grad, np.array(fd), rtol=2e-2, atol=2e-3)


def test_a_large_gaussian_entered_first_does_not_cover_the_surface_in_front_of_its_peak():
    t = lambda a: mi.TensorXf(np.asarray(a, np.float32))  # noqa: E731
    # A small, nearly opaque red disc at x = 5 and a large grey Gaussian whose
    # 3-sigma support begins at x = 4.1 (entered first) but peaks at x = 5.6.
    scene = mi.load_dict({
        "type": "scene",
        "front": {"type": "gaussians", "id": "front", "centers": t([[5.0, 0.0, 0.0]]),
                  "scales": t([[0.01, 0.3, 0.3]]), "opacities": t([0.98]),
                  "albedo": t([[1.0, 0.0, 0.0]])},
        "big": {"type": "gaussians", "id": "big", "centers": t([[5.6, 0.0, 0.0]]),
                "scales": t([[0.5, 0.5, 0.5]]), "opacities": t([0.9]),
                "albedo": t([[0.5, 0.5, 0.5]])},
    })
    rays = mi.Ray3f(mi.Point3f(0.0, 0.0, 0.0), mi.Vector3f(1.0, 0.0, 0.0))
    rays.maxt = mi.Float(100.0)
    with dr.suspend_grad():
        hl = hitlib.trace(scene, rays, 8, 1e-3)
        assert int(hl.count[0]) == 2
        rgb, alpha, depth = camera_unlit(scene, rays, 8, 1e-3)
    rgb = np.array([rgb[i][0] for i in range(3)])
    # Peak order: red in front (0.98), the grey behind it shows through 2 %.
    expected = 0.98 * np.array([1.0, 0, 0]) + 0.02 * 0.9 * np.array([0.5, 0.5, 0.5])
    np.testing.assert_allclose(rgb, expected, atol=2e-3)
    np.testing.assert_allclose(float(depth[0]), 0.98 * 5.0 + 0.02 * 0.9 * 5.6, atol=2e-3)
