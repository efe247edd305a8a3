"""Write the Gaussian assets of the example scenes (run from anywhere).

    python scenes/make_examples.py

gaussians_plane.ply: a 6 m x 6 m patch of ground at z = 0 made of 25 x 25 flat
Gaussians (spacing and in-plane sigma 0.25 m, thickness sigma 0.025 m, opacity
0.99), grey-brown albedo, LiDAR albedo 0.3, roughness 0.6; a darker stripe
across x = 0 (LiDAR albedo 0.08, like road paint's opposite) so that LiDAR
intensity images show structure. Used by gaussians_plane.xml and
lidar_gaussians.xml.

The thickness is a tenth of the width, not thinner: Mitsuba 3.9.1's ellipsoid
intersector loses beams through much flatter Gaussians.
"""

import os

import numpy as np
import mitsuba as mi

if not mi.variant():  # importing the package needs a variant
    mi.set_variant("llvm_ad_rgb")
from mi_invrgbl.physics.gaussian_ply import GaussianCloud, write_ply

HERE = os.path.dirname(os.path.abspath(__file__))


def ground_patch(half=3.0, spacing=0.25):
    xs = np.arange(-half, half + 1e-6, spacing)
    x, y = np.meshgrid(xs, xs)
    n = x.size
    centers = np.stack([x.ravel(), y.ravel(), np.zeros(n)], 1).astype(np.float32)
    stripe = np.abs(centers[:, 0]) < 0.3
    albedo = np.tile(np.float32([0.35, 0.3, 0.25]), (n, 1))
    albedo[stripe] = 0.08
    return GaussianCloud(
        centers=centers,
        scales=np.tile(np.float32([spacing, spacing, 0.1 * spacing]), (n, 1)),
        quaternions=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),   # w x y z
        opacities=np.full(n, 0.99, np.float32),
        normals=np.tile(np.float32([0, 0, 1]), (n, 1)),
        albedo=albedo,
        roughness=np.full(n, 0.6, np.float32),
        lidar_albedo=np.where(stripe, 0.08, 0.3).astype(np.float32),
        sun_visibility=np.ones(n, np.float32))


def main():
    path = os.path.join(HERE, "gaussians_plane.ply")
    write_ply(path, ground_patch())
    print("wrote", path)


if __name__ == "__main__":
    main()
