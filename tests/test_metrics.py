"""Metrics against closed forms and a direct numpy SSIM."""

import math

import numpy as np
import pytest

from mi_invrgbl.eval import metrics as M

RNG = np.random.default_rng(3)


def ssim_reference(x, y, peak=1.0, win=11, sigma=1.5):
    """Wang et al. 2004 with an explicit 'valid' 2-D Gaussian convolution."""
    r = win // 2
    ax = np.arange(-r, r + 1)
    g = np.exp(-(ax[:, None] ** 2 + ax[None] ** 2) / (2 * sigma ** 2))
    g /= g.sum()
    c1, c2 = (0.01 * peak) ** 2, (0.03 * peak) ** 2
    h, w = x.shape
    out = np.zeros((h - 2 * r, w - 2 * r))
    for i in range(out.shape[0]):
        for j in range(out.shape[1]):
            px = x[i:i + win, j:j + win]
            py = y[i:i + win, j:j + win]
            mx, my = (g * px).sum(), (g * py).sum()
            vx = (g * (px - mx) ** 2).sum()
            vy = (g * (py - my) ** 2).sum()
            cxy = (g * (px - mx) * (py - my)).sum()
            out[i, j] = ((2 * mx * my + c1) * (2 * cxy + c2)
                         / ((mx ** 2 + my ** 2 + c1) * (vx + vy + c2)))
    return out.mean()


def test_psnr_closed_form():
    t = RNG.uniform(0, 1, (16, 20, 3))
    p = t + 0.01 * np.where(RNG.uniform(size=t.shape) > 0.5, 1, -1)   # MSE = 1e-4
    assert M.mse(p, t) == pytest.approx(1e-4)
    assert M.psnr(p, t) == pytest.approx(40.0)
    assert M.psnr(p * 2, t * 2, peak=2.0) == pytest.approx(40.0)
    assert M.psnr(t, t) == math.inf
    mask = np.zeros((16, 20), bool)
    assert math.isnan(M.psnr(p, t, mask=mask))
    # sRGB option: identical after conversion, transfer function round trip
    x = np.linspace(0, 1, 101)
    np.testing.assert_allclose(M.srgb_to_linear(M.linear_to_srgb(x)), x, atol=1e-12)
    assert M.linear_to_srgb(0.0031308) == pytest.approx(12.92 * 0.0031308, abs=1e-9)
    assert M.linear_to_srgb(1.0) == pytest.approx(1.0)
    assert M.psnr(t, t, srgb=True) == math.inf


def test_ssim_identity_and_reference():
    x = RNG.uniform(0, 1, (24, 30))
    assert M.ssim(x, x) == pytest.approx(1.0)
    y = np.clip(x + RNG.normal(0, 0.1, x.shape), 0, 1)
    assert M.ssim(y, x) == pytest.approx(ssim_reference(y, x), abs=1e-6)
    # per channel, averaged
    xc = RNG.uniform(0, 1, (20, 22, 3))
    yc = np.clip(xc * 0.8 + 0.05, 0, 1)
    ref = np.mean([ssim_reference(yc[..., c], xc[..., c]) for c in range(3)])
    assert M.ssim(yc, xc) == pytest.approx(ref, abs=1e-6)
    assert M.ssim(yc, xc) < 1
    # tiny image: no crash, still 1 for identical
    t = RNG.uniform(0, 1, (5, 6, 3))
    assert M.ssim(t, t) == pytest.approx(1.0)


def test_rmse_mae_masks():
    t = np.zeros((4, 5))
    p = np.ones((4, 5))
    p[0, 0] = 3
    mask = np.ones((4, 5), bool)
    mask[0, 0] = False
    assert M.rmse(p, t, mask) == pytest.approx(1.0)
    assert M.mae(p, t) == pytest.approx((19 + 3) / 20)
    t2 = t.copy()
    t2[1, 1] = np.nan     # not scored
    assert M.mae(p, t2, mask) == pytest.approx(1.0)
    with pytest.raises(ValueError):
        M.rmse(np.zeros((2, 2)), np.zeros((2, 3)))


def test_angular_error():
    n = np.zeros((3, 4, 3))
    n[..., 2] = 1
    m = n.copy()
    m[0, 0] = [1, 0, 0]            # 90 degrees
    m[0, 1] = [0, 0, 5]            # unnormalised: 0 degrees
    assert M.angular_error_deg(n, n) == pytest.approx(0.0, abs=1e-6)
    assert M.angular_error_deg(m, n) == pytest.approx(90 / 12)
    assert M.angular_error_deg(m, n, reduce="median") == pytest.approx(0.0, abs=1e-6)
    gt = n.copy()
    gt[0, 0] = 0                   # sky: not scored
    assert M.angular_error_deg(m, gt) == pytest.approx(0.0, abs=1e-6)


def test_albedo_scale_fit_invariance():
    gt = RNG.uniform(0.1, 0.8, (10, 12, 3))
    noisy = gt * (1 + RNG.normal(0, 0.05, gt.shape))
    base = M.albedo_rmse_scaled(noisy, gt)
    for s in (0.3, 2.0, 7.5):
        assert M.albedo_rmse_scaled(noisy * s, gt) == pytest.approx(base, rel=1e-9)
        assert M.albedo_rmse_scaled(noisy * [s, 2 * s, 0.5 * s], gt) == pytest.approx(base, rel=1e-9)
    assert M.albedo_rmse_scaled(gt * 0.5, gt) == pytest.approx(0.0, abs=1e-12)
    g1 = gt[..., 0]
    assert M.albedo_rmse_scaled(g1 * 3, g1) == pytest.approx(0.0, abs=1e-12)
    # global scale: a per-channel tint is not forgiven
    assert M.albedo_rmse_scaled(gt * [1, 2, 1], gt, per_channel=False) > 0.01
    np.testing.assert_allclose(M.scale_fit(gt * 4, gt), 0.25)


def test_lidar_metrics():
    ph = np.array([[1, 1, 0, 0]])
    oh = np.array([[1, 0, 0, 1]])
    assert M.ray_drop_accuracy(ph, oh) == pytest.approx(0.5)
    pr = np.array([[10.0, 5.0, 0.0, 0.0]])
    orr = np.array([[10.5, 0.0, 0.0, 7.0]])
    assert M.range_error(pr, orr, ph, oh) == pytest.approx(0.5)
    assert M.range_error(pr, orr) == pytest.approx(0.5)
    assert math.isnan(M.range_error(np.zeros(3), np.zeros(3)))
