"""``depth_normals.py``'s normals from a rendered depth: a tilted plane, a
step between two surfaces and uncovered pixels (no renders: point grids)."""

import pathlib
import sys

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))

import depth_normals as dn  # noqa: E402


def _rays(h=36, w=48, fov=0.6):
    """Unit directions of a pinhole camera looking down +z (camera-centred)."""
    u = np.linspace(-fov, fov, w)
    v = np.linspace(-fov * h / w, fov * h / w, h)
    d = np.stack(np.broadcast_arrays(u[None, :], v[:, None], np.ones((h, w))), -1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def _on_plane(d, normal, offset):
    """Points where the rays ``d`` meet the plane n . x = offset."""
    t = offset / (d @ normal)
    return d * t[..., None]


def test_a_tilted_plane_gives_its_normal_towards_the_camera():
    d = _rays()
    n = np.array([0.3, -0.2, -1.0])
    n /= np.linalg.norm(n)
    pts = _on_plane(d, n, -5.0)           # n . x = -5: in front, facing the camera
    normals, ok = dn.depth_normals(pts, np.ones(d.shape[:2]))
    assert ok[1:-1, 1:-1].all() and not ok[0].any() and not ok[:, -1].any()
    assert np.allclose(normals[ok], n, atol=1e-6)
    # The other side of the plane: the normal still faces the camera.
    normals, _ = dn.depth_normals(_on_plane(d, -n, 5.0), np.ones(d.shape[:2]))
    assert np.allclose(normals[ok], n, atol=1e-6)


def test_a_step_between_surfaces_and_uncovered_pixels_have_none():
    d = _rays()
    near = _on_plane(d, np.array([0.0, 0.0, -1.0]), -4.0)
    far = _on_plane(d, np.array([0.0, 0.0, -1.0]), -8.0)
    pts = np.where((np.arange(d.shape[1]) < 20)[None, :, None], near, far)
    alpha = np.ones(d.shape[:2])
    alpha[5, 3] = 0.5                    # a pixel not covered enough
    _, ok = dn.depth_normals(pts, alpha)
    assert not ok[1:-1, 19:21].any()     # either side of the step
    assert not ok[5, 2:5].any() and not ok[4:7, 3].any()   # the pixel and its four neighbours
    assert ok[4, 2] and ok[6, 4]         # its diagonal neighbours keep theirs
    assert ok[1:-1, 22:-1].all() and ok[8:-1, 1:18].all()


def test_angle_is_symmetric_and_bounded():
    a = np.array([[1.0, 0.0, 0.0]])
    assert dn.angle(a, a)[0] == 0.0
    assert np.isclose(dn.angle(a, -a)[0], 180.0)
