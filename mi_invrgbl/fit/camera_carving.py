"""Geometry the cameras see and the LiDAR does not, carved from stage 1's residuals.

The import places Gaussians where LiDAR points are. What stands above the
top beam and is not a facade the import extends upward (a tree crown at
3-6.6 m seen from a car whose top beam reaches 2 m at 10 m), or lies beyond
the LiDAR's range, has no Gaussian, and stage 1 cannot move one there from
the surfaces it holds: the crown's pixels keep the colour of the facade or
the sky behind, which no view-independent colour can match in every view.

Those pixels are the evidence. Part way through stage 1, every training
image is rendered with the current Gaussians (colour, opacity and depth,
:func:`.render.camera_unlit`). A pixel is *unexplained* where the render
differs from the image by more than ``residual`` (sRGB, mean of the
channels) and the sky mask does not claim it. Points are sampled along the
ray of every unexplained pixel, from ``near`` up to just in front of what the
render shows there (its depth where the ray is mostly covered, else up to
``far``). Each point is checked in the other training views (a
space-carving vote):

* where it projects outside the image, or lies behind what that view
  renders (occluded by the current geometry), the view says nothing;
* where it would be visible, the pixel it lands on must be unexplained
  too and of the same colour (within ``colour_tolerance``): one vote for;
  a pixel the render already explains (no unexplained pixel within one
  pixel of it), or a sky pixel, or another colour is one vote against.

A point with at least ``min_support`` votes for and none against stands
where the images need geometry. Points are pooled in cells of ``cell``
metres; a cell reached from at least two source views becomes one Gaussian
(isotropic, ``cell`` across, opacity ``START_OPACITY``, the mean colour of
the pixels that voted for it). Stage 1 then goes on with them: where the
vote left the hull too deep along a ray (a textureless crown is
photo-consistent over a range of depths), the wrong ones block some view
and lose their opacity to the colour loss, and pruning removes them.

Held-out and validation frames give nothing: only training frames render,
vote and colour the new Gaussians. Moving objects stay in their own nodes
(rendered at each frame's pose); the new Gaussians go to the static
background.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import cv2
import drjit as dr

from ..physics.colour import linear_to_srgb, srgb_to_linear
from ..physics.gaussian_ply import GaussianCloud
from .render import camera_unlit
from .sky_mask import PinholeProjection

#: Opacity of a carved Gaussian when stage 1 takes it up: seen through, so
#: that a wrong one costs little before the colour loss removes it.
START_OPACITY = 0.5

#: How far stage 1 is (0..1) when it carves: its Gaussians have settled on
#: the LiDAR's surfaces, so what is left unexplained is missing geometry
#: rather than geometry still moving, and enough of the stage is left for
#: the new Gaussians to be fitted and pruned.
CARVE_AT = 0.3


@dataclass(frozen=True)
class CarvingSettings:
    """The thresholds of one carving (see the module text)."""
    residual: float = 0.12          # sRGB, mean over channels
    colour_tolerance: float = 0.08  # sRGB, largest channel difference
    min_support: int = 2            # other views voting for a point
    near: float = 1.5               # metres along a ray
    far: float = 60.0
    depth_samples: int = 64
    depth_margin: float = 0.1       # relative: a point this far in front of the render is "in front"
    cell: float = 0.25              # metres
    max_new: int = 20000


@dataclass
class View:
    """One training frame's evidence: its image and what stage 1 renders."""
    index: int
    projection: PinholeProjection
    origin: np.ndarray        # (3,)
    directions: np.ndarray    # (H*W, 3)
    image: np.ndarray         # (H*W, 3) sRGB
    depth: np.ndarray         # (H*W,) distance to what the render shows; inf where open
    unexplained: np.ndarray   # (H*W,) bool
    near_unexplained: np.ndarray  # (H*W,) bool: unexplained within one pixel
    sky: np.ndarray           # (H*W,) bool
    width: int
    height: int


def render_view(scene, frame, settings: CarvingSettings, max_hits=32) -> View:
    """Render ``frame`` (a :class:`.observations.FrameObservation` with a
    camera; the model already pushed at its poses) and mark its unexplained
    pixels."""
    cam = frame.camera
    with dr.suspend_grad():
        rgb, alpha, depth = camera_unlit(scene, cam.rays, max_hits)
    n = cam.width * cam.height
    rgb = np.stack([np.broadcast_to(np.array(rgb[k], np.float64), (n,)) for k in range(3)], 1)
    alpha = np.broadcast_to(np.array(alpha, np.float64), (n,))
    depth = np.broadcast_to(np.array(depth, np.float64), (n,))
    # Where the ray is mostly covered, what it shows sits at its blended
    # depth; a ray mostly open shows what lies behind every Gaussian.
    shown = np.where(alpha > 0.5, depth / np.maximum(alpha, 1e-6), np.inf)
    image = linear_to_srgb(np.clip(cam.image.reshape(-1, 3), 0, None))
    render = linear_to_srgb(np.clip(rgb, 0, None))
    valid = cam.valid()
    sky = cam.sky if cam.sky is not None else np.zeros(n, bool)
    off = np.abs(render - image).mean(axis=1) > settings.residual
    unexplained = off & valid & ~sky
    grown = cv2.dilate(unexplained.reshape(cam.height, cam.width).astype(np.uint8),
                       np.ones((3, 3), np.uint8)).ravel() > 0
    T = np.array(cam.sensor.world_transform().matrix, np.float64).reshape(4, 4)
    d = np.stack([np.array(cam.rays.d[k], np.float64) for k in range(3)], 1)
    o = np.array([np.array(cam.rays.o[k], np.float64)[0] for k in range(3)])
    return View(frame.index, PinholeProjection(T, d, cam.width, cam.height), o, d, image,
                shown, unexplained, grown | ~valid, sky & valid, cam.width, cam.height)


def _pixel(view: View, points):
    """Flat pixel index of ``points`` in ``view`` (-1 outside the image or
    behind the camera) and their distance from its centre."""
    p = (points - view.projection.o) @ view.projection.R
    z = p[:, 2]
    front = z > 1e-3
    zs = np.where(front, z, 1.0)
    col = view.projection.cx[0] * p[:, 0] / zs + view.projection.cx[1]
    row = view.projection.cy[0] * p[:, 1] / zs + view.projection.cy[1]
    inside = front & (col >= 0) & (col < view.width) & (row >= 0) & (row < view.height)
    idx = np.where(inside, np.floor(row).astype(np.int64).clip(0, view.height - 1) * view.width
                   + np.floor(col).astype(np.int64).clip(0, view.width - 1), -1)
    return idx, np.linalg.norm(points - view.origin, axis=1)


def vote(views: list[View], settings: CarvingSettings):
    """Points where the training images need geometry the render lacks:
    ``(points (N, 3), colours (N, 3) sRGB, source view of each (N,))``."""
    out_p, out_c, out_v = [], [], []
    s = settings
    for i, src in enumerate(views):
        pix = np.nonzero(src.unexplained)[0]
        if not pix.size:
            continue
        t = np.geomspace(s.near, s.far, s.depth_samples)
        limit = np.minimum(src.depth[pix] / (1.0 + s.depth_margin), s.far)
        P = src.origin + src.directions[pix][:, None, :] * t[None, :, None]   # (n, K, 3)
        ok = t[None, :] < limit[:, None]
        pts = P[ok]
        colour = np.repeat(src.image[pix][:, None, :], s.depth_samples, axis=1)[ok]
        support = np.zeros(len(pts), np.int32)
        against = np.zeros(len(pts), bool)
        for j, other in enumerate(views):
            if j == i or not len(pts):
                continue
            idx, dist = _pixel(other, pts)
            seen = idx >= 0
            seen[seen] = dist[seen] < other.depth[idx[seen]] / (1.0 + s.depth_margin)
            if not seen.any():
                continue
            k = idx[seen]
            match = np.abs(other.image[k] - colour[seen]).max(axis=1) <= s.colour_tolerance
            good = other.unexplained[k] & match
            bad = other.sky[k] | ~other.near_unexplained[k] | (other.unexplained[k] & ~match)
            support[np.nonzero(seen)[0][good]] += 1
            against[np.nonzero(seen)[0][bad]] = True
            keep = ~against
            pts, colour, support, against = pts[keep], colour[keep], support[keep], against[keep]
        keep = support >= s.min_support
        out_p.append(pts[keep])
        out_c.append(colour[keep])
        out_v.append(np.full(int(keep.sum()), i, np.int32))
    if not out_p:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int32)
    return np.concatenate(out_p), np.concatenate(out_c), np.concatenate(out_v)


def pool(points, colours, sources, settings: CarvingSettings):
    """Cells of ``settings.cell`` metres reached from at least two source
    views: ``(centres (M, 3), mean sRGB colours (M, 3), votes (M,))``, the
    most voted first, at most ``max_new``."""
    if not len(points):
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64)
    key = np.floor(points / settings.cell).astype(np.int64)
    cells, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.ravel()
    m = len(cells)
    votes = np.bincount(inv, minlength=m)
    pairs = np.unique(np.stack([inv, sources], 1), axis=0)
    views = np.bincount(pairs[:, 0], minlength=m)
    colour = np.stack([np.bincount(inv, colours[:, k], minlength=m) for k in range(3)], 1) \
        / np.maximum(votes, 1)[:, None]
    centre = np.stack([np.bincount(inv, points[:, k], minlength=m) for k in range(3)], 1) \
        / np.maximum(votes, 1)[:, None]
    keep = np.nonzero(views >= 2)[0]
    keep = keep[np.argsort(-votes[keep], kind="stable")][: settings.max_new]
    return centre[keep], colour[keep], votes[keep]


def carved_cloud(centres, srgb, views: list[View], settings: CarvingSettings, source="<carving>"):
    """New Gaussians at the pooled cells: isotropic, half a cell in standard
    deviation (neighbours overlap into one surface), the cells' mean colour
    (linear, stage 1's colour field), normals towards the mean training
    camera; every other material field at its default."""
    n = len(centres)
    eye = np.mean([v.origin for v in views], axis=0)
    normal = eye - centres
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-9)
    cloud = GaussianCloud(
        centers=np.asarray(centres, np.float32),
        scales=np.full((n, 3), 0.5 * settings.cell, np.float32),
        quaternions=np.tile(np.array([1.0, 0.0, 0.0, 0.0], np.float32), (n, 1)),
        opacities=np.full(n, START_OPACITY, np.float32),
        normals=normal.astype(np.float32),
        albedo=np.clip(srgb_to_linear(np.clip(srgb, 0, 1)), 0, 1).astype(np.float32),
        source=source)
    return cloud.with_defaults()
