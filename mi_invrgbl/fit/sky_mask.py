"""Which pixels of a training image show the sky.

Stage 1 explains every pixel with Gaussians or with the SH sky behind them.
Without a sky mask it prefers Gaussians: the import puts geometry above the
LiDAR's top beam (extended walls, triangulated points), densification
stretches it, and the sky behind them then gets no gradient. On the KITTI
excerpt this covered 16-17 % of each image, the bright sky above the bridge
(image 0.96, stage-1 alpha 0.96, Gaussian colour 0.85), with Gaussians,
while the SH sky was fitted to the 1-2 % of pixels left uncovered (dark gaps,
image 0.06-0.12) and came out at 0.44. Stage 2 then has to light Gaussians
as bright as the sky with a sky at half its brightness: the albedo clips at
1 and stage 2 starts 4 dB below stage 1 at any light level.

A pixel is *sky* here when all of these hold (on the fit's image grid):

* it is bright (sRGB luminance at least :data:`MIN_BRIGHTNESS`) and not
  strongly red or yellow (blue at least red minus :data:`MAX_WARMTH`);
* the image is smooth there (Sobel gradient of the sRGB luminance below
  :data:`MAX_GRADIENT`);
* no LiDAR return of the frame projects within :data:`RETURN_MARGIN`
  pixels or above it in its column, and it lies outside the projected outline of every moving
  object, extended :data:`OBJECT_HEADROOM` up where the top beam cut it
  (a white truck beside the car is bright and smooth too, and above the
  top beam the LiDAR does not see it);
* its region of such pixels touches the top edge of the image.

The mask is conservative: sky seen through a tree crown or past a wall's
edge is left out (it is still fitted, only not forced to be sky). It needs
nothing but the image, the scan and the objects' Gaussians of the same
frame, so it is computed for the training and validation frames only (the
held-out frames are for ``eval``).
"""

from __future__ import annotations

import numpy as np
import cv2

from ..physics.colour import LUMINANCE, linear_to_srgb
from ..io.objects import OBJECT_HEADROOM

#: Least sRGB luminance of a sky pixel (a white or blue daylight sky reads
#: 0.6-1.0; the bridge, trees and road in the KITTI excerpt stay below 0.45).
MIN_BRIGHTNESS = 0.5
#: Most Sobel gradient (sRGB luminance per pixel) inside the sky.
MAX_GRADIENT = 0.06
#: How much redder than blue a sky pixel may be (sunset skies are not handled).
MAX_WARMTH = 0.05
#: Pixels within this distance (columns and rows) of a projected LiDAR
#: return, or below it, are not sky.
RETURN_MARGIN = 2
#: A moving object whose highest Gaussian is within :data:`CUT_DEG` of the
#: scan's highest return (its top was cut by the top beam, not measured) has
#: its outline extended :data:`~mi_invrgbl.io.objects.OBJECT_HEADROOM` up
#: (world z): beside the car a truck rises far above the top beam, so its
#: LiDAR points end at about the sensor's height (the white tank of a truck in
#: the KITTI excerpt read as sky without this; an import that extended the
#: object already, its Gaussians reach above the cut). Cars ahead, whose
#: roofs the scan measured, keep their outline (extended, they hid a third of
#: the sky).
CUT_DEG = 1.0


class PinholeProjection:
    """World points to pixel positions of a camera, from its rays.

    The rays through the pixel centres of a pinhole camera are an affine map
    of the pixel position in the camera's ``x/z``, ``y/z``; fitting that map
    to the rays (exact up to rounding) avoids depending on how the sensor
    stores its field of view and principal point."""

    def __init__(self, camera_to_world, directions, width, height):
        T = np.asarray(camera_to_world, np.float64)
        self.R, self.o = T[:3, :3], T[:3, 3]
        local = np.asarray(directions, np.float64) @ self.R
        u, v = local[:, 0] / local[:, 2], local[:, 1] / local[:, 2]
        idx = np.arange(width * height)
        col, row = idx % width + 0.5, idx // width + 0.5
        one = np.ones_like(u)
        self.cx = np.linalg.lstsq(np.stack([u, one], 1), col, rcond=None)[0]
        self.cy = np.linalg.lstsq(np.stack([v, one], 1), row, rcond=None)[0]
        self.width, self.height = width, height

    def __call__(self, points, near=0.1):
        """(col, row) of the ``points`` (N, 3) in front of the camera (beyond ``near``)."""
        p = (np.asarray(points, np.float64).reshape(-1, 3) - self.o) @ self.R
        p = p[p[:, 2] > near]
        return (self.cx[0] * p[:, 0] / p[:, 2] + self.cx[1],
                self.cy[0] * p[:, 1] / p[:, 2] + self.cy[1])


def sky_mask(image, projection: PinholeProjection, returns=None, objects=()):
    """(H, W) bool: the sky pixels of ``image`` ((H, W, 3) linear RGB).

    ``returns``: (N, 3) world positions of the frame's LiDAR returns;
    ``objects``: (M, 3) world points of each moving object at the frame
    (its Gaussians' centres), whose projected convex hull is not sky."""
    h, w = image.shape[:2]
    srgb = linear_to_srgb(np.clip(image, 0.0, None))
    lum = (srgb @ LUMINANCE).astype(np.float32)
    grad = np.hypot(cv2.Sobel(lum, cv2.CV_32F, 1, 0, ksize=3),
                    cv2.Sobel(lum, cv2.CV_32F, 0, 1, ksize=3)) / 8.0
    candidate = (lum >= MIN_BRIGHTNESS) & (grad < MAX_GRADIENT) \
        & (srgb[..., 2] >= srgb[..., 0] - MAX_WARMTH)
    blocked = np.zeros((h, w), np.uint8)
    if returns is not None and len(returns):
        col, row = projection(returns)
        ok = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        # Sky lies above everything the scan measured in its column: a
        # column's pixels from its highest return down are not sky (also
        # between the rows of a sparse scanner's beams, which a margin
        # around each return would let through).
        top = np.full(w, float(h))
        np.minimum.at(top, col[ok].astype(int), row[ok])
        r = RETURN_MARGIN
        spread = top.copy()             # the highest return within r columns
        for k in range(1, r + 1):
            spread[k:] = np.minimum(spread[k:], top[:-k])
            spread[:-k] = np.minimum(spread[:-k], top[k:])
        blocked[np.arange(h)[:, None] >= np.floor(spread)[None, :] - r] = 1
    for pts in objects:
        col, row = projection(pts)
        if col.size < 3:
            continue
        # Far outside the image the hull is still right; keep the numbers small.
        xy = np.clip(np.stack([col, row], 1), -4 * max(w, h), 5 * max(w, h)).astype(np.int32)
        cv2.fillConvexPoly(blocked, cv2.convexHull(xy), 1)
    candidate &= blocked == 0
    _, labels = cv2.connectedComponents(candidate.astype(np.uint8), connectivity=4)
    top = np.unique(labels[0][candidate[0]])
    return np.isin(labels, top) & candidate


def _elevation(points, origin):
    """Elevation (degrees above the xy plane) of ``points`` seen from ``origin``."""
    v = np.asarray(points, np.float64) - origin
    return np.degrees(np.arctan2(v[:, 2], np.hypot(v[:, 0], v[:, 1])))


def frame_sky_mask(model, frame):
    """Flat bool sky mask of ``frame``'s image (a :class:`.observations.FrameObservation`
    with a camera), from its image, its LiDAR returns and the moving nodes of
    ``model`` (a :class:`.model.GaussianModel`) at the frame's poses."""
    cam = frame.camera
    T = np.array(cam.sensor.world_transform().matrix, np.float64).reshape(4, 4)
    d = np.stack([np.array(cam.rays.d[k]) for k in range(3)], 1)
    projection = PinholeProjection(T, d, cam.width, cam.height)
    returns, sensor, top = None, None, None
    lid = frame.lidar
    if lid is not None:
        hit = lid.hit.ravel() & lid.valid()
        o = np.stack([np.array(lid.rays.o[k]) for k in range(3)], 1)[hit]
        u = np.stack([np.array(lid.rays.d[k]) for k in range(3)], 1)[hit]
        # Ray origins sit ``near`` in front of the sensor; range is from the sensor.
        near = np.broadcast_to(np.array(lid.near), hit.shape)[hit]
        returns = o + u * (lid.range.ravel()[hit] - near)[:, None]
        if len(returns):
            sensor = np.median(o - u * near[:, None], axis=0)
            top = float(np.max(_elevation(returns, sensor)))
    objects = []
    for name, node in model.nodes.items():
        pose = frame.poses.get(name)
        if node.dynamic and pose is not None and node.count:
            c = model.cloud(name).centers.astype(np.float64)
            pose = np.asarray(pose, np.float64)
            c = c @ pose[:3, :3].T + pose[:3, 3]
            if top is not None and np.max(_elevation(c, sensor)) >= top - CUT_DEG:
                c = np.concatenate([c, c + [0.0, 0.0, OBJECT_HEADROOM]])
            objects.append(c)
    mask = sky_mask(cam.image.reshape(cam.height, cam.width, 3), projection, returns, objects)
    return mask.ravel() & cam.valid()
