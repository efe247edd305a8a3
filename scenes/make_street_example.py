"""Writes the Gaussians of the bundled example street (scenes/street.xml).

Run from the repository root: ``python scenes/make_street_example.py``.
Seeded, so the committed PLY is reproducible: a road with lane markings and
sidewalks, and a facade with windows, as flat Gaussians with materials.
"""

import os

import numpy as np

from mi_invrgbl.physics.gaussian_ply import GaussianCloud, write_ply

OUT = os.path.join(os.path.dirname(__file__), "street_assets", "street_gaussians.ply")


def flat_layer(u, v, to_world, normal, spacing, rng):
    """Flat Gaussians on a grid (u, v) mapped by ``to_world`` (3x3 basis, origin)."""
    uu, vv = np.meshgrid(u, v, indexing="ij")
    basis, origin = to_world
    pts = origin + uu.ravel()[:, None] * basis[0] + vv.ravel()[:, None] * basis[1]
    pts += rng.normal(0, spacing * 0.05, pts.shape) * (basis[0] + basis[1])
    n = pts.shape[0]
    scales = np.tile([spacing * 0.6, spacing * 0.6, spacing * 0.02], (n, 1))
    rot = np.stack([basis[0], basis[1], normal], 1)  # columns = local axes
    w = np.sqrt(max(1 + np.trace(rot), 1e-12)) / 2
    q = np.array([w, (rot[2, 1] - rot[1, 2]) / (4 * w), (rot[0, 2] - rot[2, 0]) / (4 * w),
                  (rot[1, 0] - rot[0, 1]) / (4 * w)])
    return pts, scales, np.tile(q, (n, 1)), np.tile(normal, (n, 1))


def main():
    rng = np.random.default_rng(7)
    parts = []
    # Ground (z = 0, normal +z): road |y| < 4, sidewalks beyond.
    sp = 0.25
    pts, sc, q, nrm = flat_layer(np.arange(-5, 40, sp), np.arange(-8, 8, sp),
                                 (np.eye(3), np.zeros(3)), np.array([0, 0, 1.0]), sp, rng)
    y = pts[:, 1]
    road = np.abs(y) < 4
    marking = (np.abs(y) < 0.15) & ((pts[:, 0] % 6) < 3)
    albedo = np.where(road[:, None], [0.11, 0.11, 0.12], [0.33, 0.32, 0.30])
    albedo[marking] = [0.75, 0.75, 0.72]
    lidar = np.where(road, 0.10, 0.28)
    lidar[marking] = 0.65
    rough = np.where(road, 0.85, 0.7)
    rough[marking] = 0.5
    parts.append((pts, sc, q, nrm, albedo, rough, lidar))
    # Facade at y = 8 facing -y, windows darker and glossy.
    sp = 0.3
    basis = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
    pts, sc, q, nrm = flat_layer(np.arange(-5, 40, sp), np.arange(0.15, 6, sp),
                                 (basis, np.array([0, 8.0, 0])), np.array([0, -1.0, 0]), sp, rng)
    window = ((pts[:, 0] % 4) > 1.2) & ((pts[:, 0] % 4) < 2.8) & (((pts[:, 2] % 3) > 1.0) & ((pts[:, 2] % 3) < 2.2))
    albedo = np.where(window[:, None], [0.05, 0.06, 0.08], [0.55, 0.45, 0.35])
    rough = np.where(window, 0.08, 0.8)
    lidar = np.where(window, 0.08, 0.45)
    parts.append((pts, sc, q, nrm, albedo, rough, lidar))

    cat = lambda i: np.concatenate([p[i] for p in parts]).astype(np.float32)  # noqa: E731
    n = cat(0).shape[0]
    cloud = GaussianCloud(centers=cat(0), scales=cat(1), quaternions=cat(2),
                          opacities=np.full(n, 0.95, np.float32), normals=cat(3), albedo=cat(4),
                          roughness=cat(5), lidar_albedo=cat(6), sun_visibility=np.ones(n, np.float32))
    os.makedirs(os.path.dirname(OUT), exist_ok=True)
    write_ply(OUT, cloud)
    print("wrote %s (%d Gaussians)" % (OUT, n))


if __name__ == "__main__":
    main()
