"""Camera-only geometry: triangulation with known poses on a synthetic
street of two textured facades (exact answer: the facades' planes)."""

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from mi_invrgbl.io import triangulate as tri  # noqa: E402

W, H, F = 640, 240, 400.0
K = np.array([[F, 0, W / 2 - 0.5], [0, F, H / 2 - 0.5], [0, 0, 1.0]])
TEXEL = 0.02                     # metres per texture pixel
WALLS = (4.0, -4.0)              # x of the right and left facade (camera axes: x right, y down)


def _texture(seed):
    rng = np.random.default_rng(seed)
    tex = np.zeros((250, 2000, 3), np.float32)   # 5 m tall, 40 m long
    for size, amp in ((3, 0.5), (9, 0.3), (31, 0.2)):
        noise = rng.random((250 // size + 2, 2000 // size + 2, 3)).astype(np.float32)
        tex += amp * cv2.resize(noise, (2000, 250), interpolation=cv2.INTER_CUBIC)[:250, :2000]
    return np.clip(tex * 255, 0, 255).astype(np.uint8)


def _poses(n):
    """Camera-to-world: forward along z with a slight sideways sway."""
    out = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        out[i, :3, 3] = [0.15 * np.sin(i), 0.0, 0.6 * i]
    return out


def _render(cam_to_world, textures):
    """Each facade is a plane x = X0 spanning y in [-3, 2], z in [4, 44]:
    its image is the texture warped by the plane's homography."""
    img = np.zeros((H, W, 3), np.uint8)
    w2c = np.linalg.inv(cam_to_world)
    R, t = w2c[:3, :3], w2c[:3, 3]
    for x0, tex in zip(WALLS, textures):
        origin = np.array([x0, -3.0, 4.0])
        a = np.array([0, 0, 1.0]) * TEXEL           # texture column -> along the street
        b = np.array([0, 1.0, 0]) * TEXEL           # texture row -> down
        Hm = K @ np.column_stack([R @ a, R @ b, R @ origin + t])
        warped = cv2.warpPerspective(tex, Hm, (W, H), flags=cv2.INTER_LINEAR)
        mask = cv2.warpPerspective(np.full(tex.shape[:2], 255, np.uint8), Hm, (W, H),
                                   flags=cv2.INTER_NEAREST)
        img[mask > 0] = warped[mask > 0]
    return img


@pytest.fixture(scope="module")
def street():
    poses = _poses(10)
    textures = (_texture(1), _texture(2))
    images = [_render(p, textures) for p in poses]
    return poses, images


def test_points_on_the_facades_and_never_from_held_out_frames(street):
    poses, images = street
    read = []

    def load(i):
        read.append(i)
        return images[i]

    training = [i for i in range(len(images)) if not tri.held_out(i)]
    pts = tri.triangulate_frames(load, poses, K, training)
    assert sorted(set(read)) == training                 # frames 4 and 9 never read
    assert 4 not in pts.first_frame and 9 not in pts.first_frame
    assert len(pts) > 300
    dist = np.min(np.abs(pts.points[:, :1] - np.array(WALLS)[None, :]), axis=1)
    assert np.median(dist) < 0.03
    assert np.percentile(dist, 95) < 0.15
    inside = ((pts.points[:, 1] > -3.2) & (pts.points[:, 1] < 2.2)
              & (pts.points[:, 2] > 3.8) & (pts.points[:, 2] < 44.2))
    assert inside.mean() > 0.97
    assert np.all(pts.reproj_px <= tri.TriangulationOptions().max_reproj_px)
    assert np.all(pts.parallax_deg >= tri.TriangulationOptions().min_parallax_deg)
    # Colours come from the (linearised) images: textured, not flat grey.
    assert pts.colours.std() > 0.05


def test_wrong_poses_give_no_points(street):
    """With the poses scrambled the epipolar and reprojection tests reject
    the matches: the module does not invent geometry."""
    poses, images = street
    wrong = poses.copy()
    wrong[:, :3, 3] = wrong[::-1, :3, 3]
    training = [0, 1, 2, 3]
    good = tri.triangulate_frames(lambda i: images[i], poses, K, training)
    bad = tri.triangulate_frames(lambda i: images[i], wrong, K, training)
    assert len(bad) < 0.05 * len(good)


def test_lidar_covered_points_are_dropped_and_gaussians_are_bounded(street):
    poses, images = street
    pts = tri.triangulate_frames(lambda i: images[i], poses, K, [0, 1, 2, 3, 5, 6])
    # A "LiDAR" that saw only the right facade.
    lidar = pts.points[pts.points[:, 0] > 0] + np.array([0.1, 0.0, 0.0])
    keep = tri.far_from(pts.points, lidar, 0.5)
    assert not keep[pts.points[:, 0] > 0].any()
    assert keep[pts.points[:, 0] < 0].all()
    g = tri.camera_gaussians(pts.subset(keep), K)
    n = int(keep.sum())
    assert g["centers"].shape == (n, 3) and g["quaternions"].shape == (n, 4)
    # Normals of the left facade face the cameras (+x), scales within 6 pixels.
    assert np.median(g["normals"][:, 0]) > 0.9
    pixel = pts.depth[keep] / F
    assert np.all(g["scales"][:, 0] <= 6 * pixel + 1e-6)


def test_excluded_pixels_give_no_keypoints(street):
    """Masked pixels (moving objects) are not used: masking the right half of
    every image leaves only the left facade."""
    poses, images = street
    half = np.zeros((H // 2, W // 2), np.uint8)          # a mask at half resolution
    half[:, W // 4:] = 255
    pts = tri.triangulate_frames(lambda i: images[i], poses, K, [0, 1, 2, 3],
                                 exclude=lambda i: half)
    assert len(pts) > 50
    assert (pts.points[:, 0] < 0).all()


def test_dense_flow_points_on_the_facades(street):
    poses, images = street
    read = []

    def load(i):
        read.append(i)
        return images[i]

    training = [i for i in range(len(images)) if not tri.held_out(i)]
    pts = tri.dense_frames(load, poses, K, training)
    assert 4 not in read and 9 not in read
    assert len(pts) > 2000
    dist = np.min(np.abs(pts.points[:, :1] - np.array(WALLS)[None, :]), axis=1)
    assert np.median(dist) < 0.05
    assert np.percentile(dist, 90) < 0.3
