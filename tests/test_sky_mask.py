"""The sky mask of training images (mi_invrgbl/fit/sky_mask.py) and the
stage-1 sky term (losses.sky_loss).

A camera at the origin looks along +x (z up) at a 64 x 40 image: a smooth
bright sky over the top half, a dark street below. Pixels stop being sky
where a LiDAR return or a moving object projects, where the image is
textured or warm, or where a bright region does not reach the top edge.
"""

from types import SimpleNamespace

import numpy as np
import drjit as dr
import mitsuba as mi

from mi_invrgbl.fit import losses
from mi_invrgbl.fit.observations import CameraObservation, camera_rays
from mi_invrgbl.fit.sky_mask import (CUT_DEG, OBJECT_HEADROOM, PinholeProjection, frame_sky_mask,
                                     sky_mask)

W, H = 64, 40


def camera():
    sensor = mi.load_dict({
        "type": "perspective", "fov": 60.0,
        "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=[1, 0, 0], up=[0, 0, 1]),
        "film": {"type": "hdrfilm", "width": W, "height": H}})
    rays = camera_rays(sensor, W, H)
    d = np.stack([np.array(rays.d[k]) for k in range(3)], 1)
    T = np.array(sensor.world_transform().matrix, np.float64).reshape(4, 4)
    return sensor, rays, d, PinholeProjection(T, d, W, H)


def street_image():
    img = np.full((H, W, 3), 0.02)
    img[: H // 2] = [0.55, 0.65, 0.85]          # linear: sRGB luminance ~0.85
    return img


def test_projection_puts_points_on_their_pixels():
    _, _, d, proj = camera()
    for dist in (0.5, 10.0, 1e4):
        col, row = proj(d * dist)
        idx = np.arange(W * H)
        assert np.allclose(col, idx % W + 0.5, atol=1e-3)
        assert np.allclose(row, idx // W + 0.5, atol=1e-3)
    # Points behind the camera are dropped, not mirrored into the image.
    col, _ = proj(-d[:10] * 5.0)
    assert col.size == 0


def test_the_smooth_bright_top_is_sky_and_nothing_else():
    _, _, d, proj = camera()
    img = street_image()
    m = sky_mask(img, proj)
    assert m[: H // 2 - 1].all() and not m[H // 2 + 1:].any()
    # A bright region that does not reach the top edge (a white van) is not sky.
    img2 = img.copy()
    img2[30:36, 10:30] = [0.8, 0.8, 0.8]
    assert not sky_mask(img2, proj)[30:36, 10:30].any()
    # Texture (a facade's windows) and warm colours (a red roof) are not sky.
    img3 = img.copy()
    img3[:20:2, 0:20] = 0.05
    img3[:20, 40:60] = [0.9, 0.3, 0.1]
    m3 = sky_mask(img3, proj)
    assert not m3[:20, 0:20].any() and not m3[:20, 40:60].any() and m3[:18, 24:36].all()


def test_lidar_returns_and_moving_objects_are_not_sky():
    _, _, d, proj = camera()
    img = street_image()
    # A return 20 m away along the ray of pixel (row 5, col 40).
    ret = d[5 * W + 40][None] * 20.0
    m = sky_mask(img, proj, returns=ret)
    assert not m[3:8, 38:43].any() and m[5, 30] and m[5, 50]
    # Below it in its column (between a sparse scanner's beam rows) is not
    # sky either; above it is.
    assert not m[8:, 38:43].any() and m[:3, 38:43].all()
    # A bright truck 6 m ahead fills part of the sky region.
    ys, zs = np.meshgrid(np.linspace(-1.0, 1.0, 9), np.linspace(0.0, 2.0, 9))
    truck = np.stack([np.full(ys.size, 6.0), ys.ravel(), zs.ravel()], 1)
    m = sky_mask(img, proj, objects=[truck])
    col, row = proj(truck)
    inside = (slice(int(row.min()) + 1, int(row.max())), slice(int(col.min()) + 1, int(col.max())))
    assert not m[inside].any() and m[0, 2] and m[0, W - 3]


def frame(proj_rays, sensor, lidar_points, truck):
    img = street_image()
    cam = CameraObservation(sensor, img.reshape(H, W, 3), W, H)
    cam.rays = proj_rays
    n = len(lidar_points)
    u = lidar_points / np.linalg.norm(lidar_points, axis=1, keepdims=True)
    near = 0.1
    lid = SimpleNamespace(
        hit=np.ones((1, n), bool), valid=lambda: np.ones(n, bool),
        rays=SimpleNamespace(o=mi.Point3f(*(u * near).T.astype(np.float32)),
                             d=mi.Vector3f(*u.T.astype(np.float32))),
        near=mi.Float(np.full(n, near, np.float32)),
        range=np.linalg.norm(lidar_points, axis=1)[None])
    model = SimpleNamespace(nodes={"truck": SimpleNamespace(dynamic=True, count=len(truck))},
                            cloud=lambda name, stage=2: SimpleNamespace(centers=truck))
    return SimpleNamespace(camera=cam, lidar=lid, poses={"truck": np.eye(4)}), model


def test_a_truck_cut_by_the_top_beam_reaches_up_into_the_sky():
    """Beside the car a truck's LiDAR points end at the top beam; its
    outline is extended up, a car whose roof the scan measured keeps its own."""
    sensor, rays, d, proj = camera()
    # The scan's highest return: 2 deg up, far away.
    far = np.array([[50.0, -20.0, 50.0 * np.tan(np.radians(2.0))]])
    # Truck side 4 m ahead, 1.5-3.5 m to the left, measured up to the top beam.
    ys, zs = np.meshgrid(np.linspace(1.5, 3.5, 5), np.linspace(-1.5, 4 * np.tan(np.radians(2.0)), 5))
    truck = np.stack([np.full(ys.size, 4.0), ys.ravel(), zs.ravel()], 1)
    f, model = frame(rays, sensor, far, truck)
    m = frame_sky_mask(model, f).reshape(H, W)
    # Above the measured top of the truck, within the headroom: not sky.
    top = truck + [0.0, 0.0, 0.9 * OBJECT_HEADROOM]
    col, row = proj(top)
    ok = (col >= 0) & (col < W) & (row >= 0) & (row < H)
    assert ok.any() and not m[row[ok].astype(int), col[ok].astype(int)].any()
    assert m[0, W - 3]
    # The same truck lowered by 1 m is a car whose top the scan saw: only its outline.
    low = truck - [0.0, 0.0, 1.0]
    f, model = frame(rays, sensor, far, low)
    m_low = frame_sky_mask(model, f).reshape(H, W)
    above = low + [0.0, 0.0, 1.0 + 0.9 * OBJECT_HEADROOM]
    col, row = proj(above)
    ok = (col >= 0) & (col < W) & (row >= 0) & (row < H) & (row < H // 2 - 1)
    assert ok.any() and m_low[row[ok].astype(int), col[ok].astype(int)].all()
    assert CUT_DEG > 0


def test_sky_loss_is_finite_and_pushes_opacity_down():
    alpha = mi.Float([0.0, 0.5, 1.0, 0.9])
    dr.enable_grad(alpha)
    mask = mi.Bool([True, True, True, False])
    loss = losses.sky_loss(alpha, mask)
    dr.backward(loss)
    g = np.array(dr.grad(alpha))
    assert np.isfinite(float(loss[0])) and np.all(np.isfinite(g))
    assert g[1] > 0 and g[3] == 0            # lower opacity lowers the loss; unmasked: no pull
    # No sky pixel in the batch: no loss.
    assert float(losses.sky_loss(mi.Float([0.7, 0.2]), mi.Bool([False, False]))[0]) == 0.0


def test_no_sky_mask_leaves_the_frames_unmarked():
    """``fit --no-sky-mask`` (or a zero weight): no mask, no sky term, no report."""
    from mi_invrgbl.fit.init import attach_sky_masks
    sensor, rays, _, _ = camera()
    far = np.array([[50.0, -20.0, 1.0]])
    f, model = frame(rays, sensor, far, np.zeros((0, 3)))
    for sky_mask_on, weight in ((False, 0.1), (True, 0.0)):
        state = SimpleNamespace(config=SimpleNamespace(sky_mask=sky_mask_on, stage1_sky=weight),
                                train_frames=[f], validation_frames=[], model=model, selection={})
        attach_sky_masks(state)
        assert f.camera.sky is None and "sky_mask" not in state.selection
    state.config.stage1_sky = 0.1
    attach_sky_masks(state)
    assert f.camera.sky is not None and state.selection["sky_mask"]["share"] > 0.3
