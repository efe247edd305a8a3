"""Losses: closed forms, gradients against float64 central differences, edge cases."""

import math

import numpy as np
import pytest
import drjit as dr
import mitsuba as mi

from mi_invrgbl.fit import losses as L

RNG = np.random.default_rng(7)


# ------------------------------------------------------- numpy references
def np_masked_mean(err, mask=None):
    err = np.asarray(err, np.float64)
    if err.ndim == 1:
        err = err[:, None]
    if mask is None:
        return err.mean()
    m = np.asarray(mask, np.float64)
    s = m.sum() * err.shape[1]
    return 0.0 if s == 0 else float((err * m[:, None]).sum() / s)


def np_bilateral(bl, brgb, h, w, sigma, mask=None):
    bl = bl.reshape(h, w)
    brgb = brgb.reshape(h, w, 3)
    m = np.ones((h, w)) if mask is None else np.asarray(mask, np.float64).reshape(h, w)
    tot, cnt = 0.0, 0.0
    for (a, b), (c, d) in (((slice(None), slice(None, -1)), (slice(None), slice(1, None))),
                           ((slice(None, -1), slice(None)), (slice(1, None), slice(None)))):
        wgt = np.exp(-((brgb[a, b] - brgb[c, d]) ** 2).sum(-1) / sigma ** 2) * m[a, b] * m[c, d]
        tot += (np.abs(bl[a, b] - bl[c, d]) * wgt).sum()
        cnt += (m[a, b] * m[c, d]).sum()
    return tot / cnt if cnt > 0 else 0.0


def np_superpixel(brgb, labels, n_labels, mask=None):
    brgb = brgb.reshape(-1, 3)
    m = np.ones(len(labels)) if mask is None else np.asarray(mask, np.float64)
    m = m * (labels < n_labels)
    tot = 0.0
    for k in range(n_labels):
        sel = (labels == k) & (m > 0)
        if not sel.any():
            continue
        wk = m[sel]
        mean = (brgb[sel] * wk[:, None]).sum(0) / wk.sum()
        tot += (((brgb[sel] - mean) ** 2).sum(1) * wk).sum()
    return tot / (m.sum() * 3) if m.sum() > 0 else 0.0


def fd_grad(f, x, eps=1e-6):
    x = np.asarray(x, np.float64)
    g = np.zeros_like(x)
    for i in range(x.size):
        xp, xm = x.copy(), x.copy()
        xp.flat[i] += eps
        xm.flat[i] -= eps
        g.flat[i] = (f(xp) - f(xm)) / (2 * eps)
    return g


def dr_grad(loss_fn, x, make):
    """Value and gradient of loss_fn(make(x)) with respect to the flat array x."""
    v = mi.Float(np.asarray(x, np.float32).ravel())
    dr.enable_grad(v)
    out = loss_fn(make(v))
    assert dr.width(out) == 1
    dr.backward(out)
    return float(out[0]), np.array(dr.grad(v), np.float64)


def as_color(v):
    idx = dr.arange(mi.UInt32, dr.width(v) // 3) * 3
    return mi.Color3f(dr.gather(mi.Float, v, idx), dr.gather(mi.Float, v, idx + 1),
                      dr.gather(mi.Float, v, idx + 2))


def check(value, grad, ref_f, x, rtol=2e-3, atol=1e-6):
    assert math.isfinite(value)
    assert value == pytest.approx(ref_f(np.asarray(x, np.float64)), rel=1e-4, abs=1e-6)
    np.testing.assert_allclose(grad, fd_grad(ref_f, x), rtol=rtol, atol=atol)


# ------------------------------------------------------------- closed forms
def test_closed_forms():
    assert L.rgb_loss(mi.Float([1, 2]), mi.Float([0, 0]))[0] == pytest.approx(2.5)
    c = mi.Color3f([1, 0], [0, 0], [0, 2])
    assert L.rgb_loss(c, mi.Color3f(0))[0] == pytest.approx(5 / 6)
    assert L.rgb_loss(c, mi.Color3f(0), mask=mi.Bool([True, False]))[0] == pytest.approx(1 / 3)
    # Saturated channels (target 1) are lower bounds: above costs nothing.
    sat = mi.Color3f([1.5, 0.5], [1.0, 1.0], [0.2, 0.2])
    assert L.rgb_loss(sat, mi.Color3f(1.0))[0] == pytest.approx((0.25 + 0.64 * 2) / 6)
    assert L.rgb_loss(mi.Float([3.0, 0.0]), mi.Float([0.98, 0.98]))[0] == pytest.approx(
        ((3 - 0.98) ** 2 + 0.98 ** 2) / 2)
    m = mi.Bool([True, False, True])
    assert L.lidar_loss(mi.Float([1, 5, 3]), mi.Float([0, 0, 0]), m)[0] == pytest.approx(5.0)
    assert L.range_loss(mi.Float([1, 5, -3]), mi.Float(0), m)[0] == pytest.approx(2.0)
    assert L.prior_loss(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 0, 1))[0] == pytest.approx(2 / 3)
    # BCE: p = 0.5 everywhere -> log 2
    assert L.ray_drop_loss(mi.Float([0.5, 0.5]), mi.Float([1, 0]))[0] == pytest.approx(math.log(2))
    # Tensor inputs and interleaved channels with a per-pixel mask
    t = mi.TensorXf(mi.Float([1, 1, 1, 2, 2, 2]), shape=(1, 2, 3))
    assert L.rgb_loss(t, mi.TensorXf(dr.zeros(mi.Float, 6), shape=(1, 2, 3)),
                      mask=mi.Bool([False, True]))[0] == pytest.approx(4.0)
    # bilateral: 1x3 map, lidar 0,1,1, equal rgb -> pairs |0-1| + |1-1| over 2 pairs
    v = L.bilateral_smoothness(mi.Float([0, 1, 1]), mi.Color3f(0.5), 1, 3)
    assert v[0] == pytest.approx(0.5)
    # rgb edge between pixel 0 and 1 of size 0.1 in one channel -> weight e^-1 with sigma 0.1
    rgb = mi.Color3f([0.0, 0.1, 0.1], [0, 0, 0], [0, 0, 0])
    v = L.bilateral_smoothness(mi.Float([0, 1, 1]), rgb, 1, 3, sigma=0.1)
    assert v[0] == pytest.approx(math.exp(-1) / 2, rel=1e-5)
    # superpixel variance: segment {0, 1} grey values 0 and 1 -> var 0.25, segment {2} -> 0
    v = L.superpixel_variance(mi.Float([0, 1, 7]), mi.UInt32([0, 0, 1]), 2)
    assert v[0] == pytest.approx(0.25 * 2 / 3)
    v = L.superpixel_variance(mi.Color3f([0, 1, 7], [0, 1, 7], [0, 1, 7]), mi.UInt32([0, 0, 1]), 2)
    assert v[0] == pytest.approx(0.25 * 2 / 3)


# ---------------------------------------------------------------- gradients
def test_grad_rgb_and_prior():
    n = 12
    x = RNG.uniform(0, 1, 3 * n)
    tgt = RNG.uniform(0, 1, 3 * n)
    mask = RNG.uniform(size=n) > 0.3
    tc = as_color(mi.Float(tgt.astype(np.float32)))
    for fn in (L.rgb_loss, L.prior_loss):
        val, g = dr_grad(lambda c: fn(c, tc, mi.Bool(mask)), x, as_color)
        check(val, g, lambda y: np_masked_mean((y - tgt).reshape(-1, 3) ** 2, mask), x)
    # interleaved float, no mask
    val, g = dr_grad(lambda v: L.rgb_loss(v, mi.Float(tgt.astype(np.float32))), x, lambda v: v)
    check(val, g, lambda y: np.mean((y - tgt) ** 2), x)


def test_grad_rgb_saturated_channels():
    # Half the targets at the camera's clip (a lower bound): predictions
    # above them have zero gradient, below them the usual 2 (y - t) / n.
    # Predictions stay 0.05 from the kink so the finite differences do not
    # straddle it.
    n = 24
    tgt = np.where(np.arange(n) % 2 == 0, 1.0, RNG.uniform(0.1, 0.8, n))
    x = tgt + np.where(RNG.uniform(size=n) > 0.5, 1, -1) * RNG.uniform(0.05, 0.4, n)
    ref = lambda y: np.mean(np.where((tgt >= L.SATURATED) & (y > tgt), 0.0, y - tgt) ** 2)  # noqa: E731
    val, g = dr_grad(lambda v: L.rgb_loss(v, mi.Float(tgt.astype(np.float32))), x, lambda v: v)
    check(val, g, ref, x)
    above = (tgt >= L.SATURATED) & (x > tgt)
    assert above.any() and not g[above].any() and g[~above].all()


def test_srgb_encode_matches_eval_and_stays_differentiable():
    # The loss's sRGB curve is eval's (PSNR is scored through it), and its
    # gradient is finite at 0 and across the curve's kink.
    from mi_invrgbl.eval.metrics import linear_to_srgb
    x = np.concatenate([[0.0, 1e-6, 0.0031308, 0.00314, 0.5, 1.0, 1.7], RNG.uniform(0, 1, 40)])
    v = mi.Float(x.astype(np.float32))
    dr.enable_grad(v)
    y = L.srgb_encode(v)
    dr.backward(dr.sum(y))
    np.testing.assert_allclose(np.array(y), linear_to_srgb(x), rtol=2e-5, atol=2e-6)
    g = np.array(dr.grad(v))
    assert np.isfinite(g).all() and (g > 0).all()
    assert g[0] == pytest.approx(12.92)
    smooth = x > 0.004
    fd = (linear_to_srgb(x[smooth] + 1e-6) - linear_to_srgb(x[smooth] - 1e-6)) / 2e-6
    np.testing.assert_allclose(g[smooth], fd, rtol=2e-3)


def test_rgb_loss_in_srgb():
    # The same loss, compared through the sRGB curve; saturated targets stay
    # a lower bound (judged on the linear target), dark pixels and 0 finite.
    from mi_invrgbl.eval.metrics import linear_to_srgb
    n = 30
    tgt = np.where(np.arange(n) % 3 == 0, 1.0, RNG.uniform(0.0, 0.8, n))
    tgt[1] = 0.0
    x = np.clip(tgt + RNG.uniform(-0.3, 0.3, n), 0.01, None)
    x[np.arange(n) % 3 == 0] = np.where(np.arange(n)[np.arange(n) % 3 == 0] % 2 == 0, 1.2, 0.7)
    enc = lambda y: np.asarray(linear_to_srgb(np.maximum(y, 0.0)), np.float64)  # noqa: E731
    ref = lambda y: np.mean(np.where((tgt >= L.SATURATED) & (y > tgt), 0.0,  # noqa: E731
                                     enc(y) - enc(tgt)) ** 2)
    val, g = dr_grad(lambda v: L.rgb_loss(v, mi.Float(tgt.astype(np.float32)), space="srgb"),
                     x, lambda v: v)
    check(val, g, ref, x, rtol=5e-3, atol=1e-5)
    val0, g0 = dr_grad(lambda v: L.rgb_loss(v, mi.Float(np.zeros(4, np.float32)), space="srgb"),
                       np.zeros(4), lambda v: v)
    assert val0 == 0.0 and np.isfinite(g0).all()
    with pytest.raises(ValueError, match="space"):
        L.rgb_loss(mi.Float([0.5]), mi.Float([0.4]), space="log")


def test_rgb_loss_l1_with_saturated_channels_and_a_mask():
    # The absolute difference: gradient sign(y - t) / n under the mask,
    # saturated targets still a lower bound; predictions stay 0.05 from the
    # kink at the target so the finite differences do not straddle it.
    n = 24
    tgt = np.where(np.arange(3 * n) % 4 == 0, 1.0, RNG.uniform(0.1, 0.8, 3 * n))
    x = tgt + np.where(RNG.uniform(size=3 * n) > 0.5, 1, -1) * RNG.uniform(0.05, 0.3, 3 * n)
    mask = RNG.uniform(size=n) > 0.3
    d = lambda y: np.where((tgt >= L.SATURATED) & (y > tgt), 0.0, y - tgt)  # noqa: E731
    tc = as_color(mi.Float(tgt.astype(np.float32)))
    val, g = dr_grad(lambda c: L.rgb_loss(c, tc, mi.Bool(mask), norm="l1"), x, as_color)
    check(val, g, lambda y: np_masked_mean(np.abs(d(y)).reshape(-1, 3), mask), x)
    # At the kink itself (a perfect prediction) value and gradient stay finite.
    val0, g0 = dr_grad(lambda v: L.rgb_loss(v, mi.Float([0.0, 0.3, 1.0]), norm="l1"),
                       np.array([0.0, 0.3, 1.0]), lambda v: v)
    assert val0 == 0.0 and np.isfinite(g0).all() and np.abs(g0).max() <= 1 / 3 + 1e-6
    with pytest.raises(ValueError, match="norm"):
        L.rgb_loss(mi.Float([0.5]), mi.Float([0.4]), norm="l3")


def test_grad_lidar_range_raydrop():
    n = 20
    x = RNG.uniform(0.05, 0.95, n)
    tgt = RNG.uniform(0, 1, n)
    mask = RNG.uniform(size=n) > 0.4
    tf = mi.Float(tgt.astype(np.float32))
    val, g = dr_grad(lambda v: L.lidar_loss(v, tf, mi.Bool(mask)), x, lambda v: v)
    check(val, g, lambda y: np_masked_mean((y - tgt) ** 2, mask), x)
    tgt2 = np.where(np.abs(x - tgt) < 0.01, tgt + 0.05, tgt)
    val, g = dr_grad(lambda v: L.range_loss(v, mi.Float(tgt2.astype(np.float32)), mi.Bool(mask)),
                     x, lambda v: v)
    check(val, g, lambda y: np_masked_mean(np.abs(y - tgt2), mask), x)
    hit = (RNG.uniform(size=n) > 0.5).astype(np.float64)
    val, g = dr_grad(lambda v: L.ray_drop_loss(v, mi.Float(hit.astype(np.float32))), x, lambda v: v)
    check(val, g, lambda y: -np.mean(hit * np.log(y) + (1 - hit) * np.log(1 - y)), x)


@pytest.mark.parametrize("use_mask", [False, True])
def test_grad_bilateral(use_mask):
    h, w = 4, 5
    bl = RNG.uniform(0, 1, h * w)
    rgb = RNG.uniform(0, 0.3, 3 * h * w)
    mask = (RNG.uniform(size=h * w) > 0.2) if use_mask else None
    rgb_c = as_color(mi.Float(rgb.astype(np.float32)))
    mk = None if mask is None else mi.Bool(mask)
    val, g = dr_grad(lambda v: L.bilateral_smoothness(v, rgb_c, h, w, 0.1, mk), bl, lambda v: v)
    check(val, g, lambda y: np_bilateral(y, rgb, h, w, 0.1, mask), bl)
    # no gradient into the RGB albedo (weights are detached)
    blf = mi.Float(bl.astype(np.float32))
    vr = mi.Float(rgb.astype(np.float32))
    dr.enable_grad(vr)
    assert not dr.grad_enabled(L.bilateral_smoothness(blf, as_color(vr), h, w))


@pytest.mark.parametrize("use_mask", [False, True])
def test_grad_superpixel(use_mask):
    n = 30
    x = RNG.uniform(0, 1, 3 * n)
    labels = RNG.integers(0, 5, n).astype(np.uint32)
    labels[3] = 99  # ignored (>= n_labels)
    mask = (RNG.uniform(size=n) > 0.3) if use_mask else None
    mk = None if mask is None else mi.Bool(mask)
    val, g = dr_grad(lambda c: L.superpixel_variance(c, mi.UInt32(labels), 5, mk), x, as_color)
    check(val, g, lambda y: np_superpixel(y, labels, 5, mask), x)


# ---------------------------------------------------------------- edge cases
def test_edge_cases_finite():
    zero = mi.Float(np.zeros(6, np.float32))
    empty = mi.Bool(np.zeros(6, bool))
    for fn in (L.lidar_loss, L.range_loss, L.prior_loss):
        v = mi.Float(np.ones(6, np.float32))
        dr.enable_grad(v)
        out = fn(v, zero, empty)
        dr.backward(out)
        assert out[0] == 0.0 and np.all(np.isfinite(np.array(dr.grad(v))))
    # BCE at exactly 0 and 1 stays finite, gradient too
    a = mi.Float([0.0, 1.0, 0.0, 1.0])
    dr.enable_grad(a)
    out = L.ray_drop_loss(a, mi.Float([0, 1, 1, 0]))
    dr.backward(out)
    assert math.isfinite(out[0]) and out[0] > 0
    assert np.all(np.isfinite(np.array(dr.grad(a))))
    # constant maps: bilateral and superpixel terms are 0 with finite gradients
    h, w = 3, 4
    bl = mi.Float(np.full(h * w, 0.3, np.float32))
    dr.enable_grad(bl)
    out = L.bilateral_smoothness(bl, mi.Color3f(0.2), h, w)
    dr.backward(out)
    assert out[0] == 0 and np.all(np.isfinite(np.array(dr.grad(bl))))
    rgb = mi.Color3f(np.full((3, h * w), 0.4, np.float32))
    dr.enable_grad(rgb)
    out = L.superpixel_variance(rgb, mi.UInt32(np.zeros(h * w, np.uint32)), 1)  # one segment
    dr.backward(out)
    assert out[0] == pytest.approx(0, abs=1e-12)
    assert np.all(np.isfinite(np.array(dr.grad(rgb))))
    # empty masks -> 0, not NaN
    none = mi.Bool(np.zeros(h * w, bool))
    assert L.bilateral_smoothness(bl, mi.Color3f(0.2), h, w, mask=none)[0] == 0
    assert L.superpixel_variance(rgb, mi.UInt32(np.zeros(h * w, np.uint32)), 1, none)[0] == 0
    assert L.rgb_loss(mi.Color3f(1.0, 1.0, 1.0), mi.Color3f(0.0), mi.Bool(False))[0] == 0
    # single-pixel and single-row maps
    assert L.bilateral_smoothness(mi.Float([1.0]), mi.Color3f(0.0), 1, 1)[0] == 0
    assert L.superpixel_variance(mi.Float([0.5]), mi.UInt32([0]), 1)[0] == 0
    with pytest.raises(ValueError):
        L.bilateral_smoothness(mi.Float([1.0, 2.0]), mi.Color3f(0.0), 3, 3)


# ------------------------------------------------------------------ weights
def test_loss_weights():
    w = L.LossWeights()
    assert (w.lidar, w.rgb, w.nor, w.mat, w.rgb2lidar, w.lidar2rgb) == (1, 1, 0.1, 0.1, 0.05, 0.05)
    w2 = L.LossWeights.parse("rgb2lidar=0, lidar2rgb=0.1")
    assert w2.rgb2lidar == 0 and w2.lidar2rgb == 0.1 and w2.rgb == 1
    assert "rgb2lidar" not in w2.active() and "lidar2rgb" in w2.active()
    assert L.LossWeights.parse("normal=0.2,material=0").nor == 0.2
    assert L.LossWeights.parse(str(w2)) == w2
    for bad in ("foo=1", "rgb", "rgb=x", "rgb=-1", "rgb=nan"):
        with pytest.raises(ValueError):
            L.LossWeights.parse(bad)
    total = w2.combine({"rgb": mi.Float(2.0), "rgb2lidar": None, "lidar2rgb": mi.Float(10.0)})
    assert total[0] == pytest.approx(3.0)
    assert L.LossWeights.parse("").combine({})[0] == 0


# -------------------------------------------------------------- superpixels
def two_region_map(h, w, a, b, slope, offset, noise=0.0, seed=0):
    yy, xx = np.mgrid[:h, :w]
    region = (xx + slope * yy) > offset
    img = np.where(region, b, a).astype(np.float32)
    img += np.random.default_rng(seed).normal(0, noise, img.shape).astype(np.float32)
    return img, region


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("channels", [1, 3])
def test_slic_never_straddles(seed, channels):
    from mi_invrgbl.fit.superpixels import slic_labels
    img, region = two_region_map(40 + 7 * seed, 60 + 5 * seed, 0.12, 0.45, 0.3 + 0.4 * seed,
                                 25 + 3 * seed, noise=0.003 * (seed % 2), seed=seed)
    if channels == 3:
        img = np.stack([img, 0.5 * img, 1 - img], -1)
    for size in (6, 12):
        labels, n = slic_labels(img, region_size=size)
        assert labels.shape == region.shape and labels.dtype == np.int32
        assert labels.min() == 0 and labels.max() == n - 1
        assert len(np.unique(labels)) == n
        for k in range(n):
            frac = region[labels == k].mean()
            assert frac in (0.0, 1.0)


def test_slic_nan_tiny_and_loss():
    from mi_invrgbl.fit.superpixels import slic_labels, labels_to_drjit
    img, region = two_region_map(30, 40, 0.2, 0.7, 0.5, 20)
    img[3:6, 4:9] = np.nan
    labels, n = slic_labels(img, region_size=8)
    assert np.all(labels[3:6, 4:9] == -1)
    good = labels >= 0
    assert np.all(labels[~np.isnan(img)] >= 0) and n > 1
    for k in range(n):
        assert region[labels == k].mean() in (0.0, 1.0)
    # uint8 input and explicit valid mask
    lab8, n8 = slic_labels((0.5 * region * 255).astype(np.uint8), region_size=8,
                           valid=good)
    assert n8 >= 2 and np.all(lab8[~good] == -1)
    # tiny and degenerate maps
    assert slic_labels(np.zeros((1, 5), np.float32))[1] == 1
    assert slic_labels(np.full((2, 2), np.nan, np.float32))[1] == 0
    lab, n = slic_labels(np.full((3, 3), 0.4, np.float32), region_size=16)
    assert n == 1 and np.all(lab == 0)
    with pytest.raises(ValueError):
        slic_labels(np.zeros((4, 4, 2)))
    # the loss on the labels: an RGB albedo that is constant per LiDAR region -> 0
    rgb = np.where(region[..., None], [0.6, 0.5, 0.4], [0.1, 0.1, 0.1]).astype(np.float32)
    flat = mi.Color3f(rgb.reshape(-1, 3).T.copy())
    assert L.superpixel_variance(flat, labels_to_drjit(labels), n)[0] == pytest.approx(0, abs=1e-10)
    rgb[0, 0] += 0.3
    flat = mi.Color3f(rgb.reshape(-1, 3).T.copy())
    assert L.superpixel_variance(flat, labels_to_drjit(labels), n)[0] > 0
    # numpy labels with -1 (invalid) work directly
    assert L.superpixel_variance(flat, labels, n)[0] == \
        pytest.approx(L.superpixel_variance(flat, labels_to_drjit(labels), n)[0])


# ------------------------------------------------------------ normal anchor
def np_anchor(n, n0):
    n, n0 = np.asarray(n, np.float64).reshape(-1, 3), np.asarray(n0, np.float64).reshape(-1, 3)
    return float(np.mean(1.0 - np.sum(n * n0, 1) / np.linalg.norm(n, axis=1)))


def test_normal_anchor_closed_form_and_gradient():
    n0 = RNG.normal(size=(6, 3))
    n0 /= np.linalg.norm(n0, axis=1, keepdims=True)
    n = n0 * RNG.uniform(0.5, 2.0, (6, 1)) + 0.3 * RNG.normal(size=(6, 3))
    # unchanged directions (any length) cost nothing; a quarter turn costs 1, a half turn 2
    assert L.normal_anchor(mi.Float(2.0 * n0.ravel()), mi.Float(n0.ravel()))[0] == pytest.approx(0.0, abs=1e-6)
    assert L.normal_anchor(mi.Float([0, 1, 0, 0, 0, -3]), mi.Float([1, 0, 0, 0, 0, 1]))[0] == pytest.approx(1.5)
    x = mi.Float(n.ravel())
    dr.enable_grad(x)
    val = L.normal_anchor(x, mi.Float(n0.ravel()))
    dr.backward(val)
    assert val[0] == pytest.approx(np_anchor(n, n0), rel=1e-5)
    fd = fd_grad(lambda v: np_anchor(v, n0), n.ravel())
    assert np.allclose(np.array(dr.grad(x)), fd, rtol=1e-3, atol=1e-5)


def test_normal_anchor_edge_cases():
    # zero-length normals stay finite; mismatched sizes are refused; no Gaussians cost nothing
    v = L.normal_anchor(mi.Float([0, 0, 0]), mi.Float([0, 0, 1]))
    assert np.isfinite(v[0])
    with pytest.raises(ValueError):
        L.normal_anchor(mi.Float([0, 0, 1, 0, 0, 1]), mi.Float([0, 0, 1]))
    assert L.normal_anchor(mi.Float([]), mi.Float([]))[0] == 0
    assert L.LossWeights().anchor >= 0 and L.LossWeights.parse("normal_anchor=0.3").anchor == 0.3
