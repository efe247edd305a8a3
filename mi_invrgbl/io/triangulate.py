"""Geometry the cameras see and the LiDAR does not: multi-view triangulation
with known poses.

A spinning LiDAR sees nothing above its top beam (tree crowns, a bridge deck,
upper facades) and little beyond its range; the cameras see all of it. This
module finds those surfaces from the training images alone:

features
    SIFT keypoints and descriptors per training frame (OpenCV), on the
    full-resolution images (the import may downscale the observations).
matches
    Each training frame against the next ``pair_span`` training frames:
    mutual nearest neighbours with Lowe's ratio test, then an epipolar check
    with the *known* relative pose (Sampson distance below ``epipolar_px``):
    no RANSAC, since the poses are given.
tracks
    Matches chained into multi-view tracks (union-find); a track that holds
    two keypoints of one frame is ambiguous and dropped.
triangulation
    Linear (DLT) triangulation of each track from all its views in
    normalised camera coordinates, then three filters: cheirality (in front
    of every camera that saw it, at least ``min_depth``), reprojection error
    (largest over the views, at most ``max_reproj_px``) and parallax (largest
    angle between two viewing rays, at least ``min_parallax_deg``: a short
    baseline leaves depth undetermined). A vehicle driving ahead moves
    along the epipolar lines of a camera following it and would pass these
    tests at a wrong depth: keypoints on moving things found in the LiDAR
    (:mod:`mi_invrgbl.io.motion`) are not used.
dense points
    Sparse tracks are few on a slowly driving car's trees and bridges, so
    :func:`dense_frames` adds two-view points from optical flow (OpenCV DIS)
    between training frames ``dense_baseline`` metres apart, with a
    forward-backward and an epipolar check, deduplicated on a voxel grid.
colour
    Mean linear RGB of the track's observations (bilinear).
cameras only
    Points within ``lidar_clearance`` metres of a LiDAR point are dropped:
    the LiDAR already gives that surface. The rest become ordinary Gaussians
    (:func:`camera_gaussians`), sized from their neighbours' spacing but
    bounded by a few pixels' footprint, so that a sparse far point never
    turns into a stretched splat: sky pixels stay for the sky model.

Held-out frames (``index % 5 == 4`` in the import) are never read: the
caller passes which frames are for training, and only those images are
loaded.

API::

    pts = triangulate_frames(load_image, cam_to_world, K, training, options)
    pts = concatenate([pts, dense_frames(load_image, cam_to_world, K, training)])
    pts = pts.subset(far_from(pts.points, lidar_points, clearance))
    g = camera_gaussians(pts, K)                    # dict of Gaussian arrays
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from . import init_gaussians as ig


@dataclass
class TriangulationOptions:
    max_features: int = 6000        # SIFT keypoints per image
    ratio: float = 0.8              # Lowe's ratio test
    pair_span: int = 4              # match each frame with the next N training frames
    epipolar_px: float = 1.5        # Sampson distance to the known epipolar geometry
    max_reproj_px: float = 1.5      # largest reprojection error over a track's views
    min_parallax_deg: float = 0.5   # largest angle between two of a track's rays
    min_views: int = 2
    min_depth: float = 1.0          # metres in front of every camera
    max_depth: float = 300.0
    lidar_clearance: float = 0.5    # metres: nearer a LiDAR point -> the LiDAR has it
    dense: bool = True              # also dense two-view points from optical flow
    dense_baseline: float = 0.5     # metres: partner = first later training frame this far
    dense_stride: int = 4           # pixels between flow samples
    dense_fb_px: float = 0.5        # forward-backward flow consistency
    dense_min_parallax_deg: float = 1.0
    dense_voxel: float = 0.15       # metres: one dense point per voxel


@dataclass
class TriangulatedPoints:
    """Triangulated tracks, world frame."""
    points: np.ndarray          # (N, 3)
    colours: np.ndarray         # (N, 3) linear RGB in [0, 1]
    views: np.ndarray           # (N,) number of frames in the track
    first_frame: np.ndarray     # (N,) frame index of the track's first view
    reproj_px: np.ndarray       # (N,) largest reprojection error
    parallax_deg: np.ndarray    # (N,) largest angle between two rays
    view_dir: np.ndarray        # (N, 3) unit mean direction point -> cameras
    depth: np.ndarray           # (N,) distance to the nearest camera that saw it
    frames_used: list = field(default_factory=list)   # frame indices whose images were read
    stats: dict = field(default_factory=dict)

    def __len__(self):
        return len(self.points)

    def subset(self, keep: np.ndarray) -> "TriangulatedPoints":
        keep = np.asarray(keep)
        return TriangulatedPoints(
            self.points[keep], self.colours[keep], self.views[keep], self.first_frame[keep],
            self.reproj_px[keep], self.parallax_deg[keep], self.view_dir[keep],
            self.depth[keep], list(self.frames_used), dict(self.stats))


# ----------------------------------------------------------------------------
# Features and matches
# ----------------------------------------------------------------------------

class _PointBatches:
    """Accepted points of the sparse and the dense triangulation, batch by
    batch, turned into one :class:`TriangulatedPoints` at the end."""

    KEYS = ("points", "colours", "views", "first", "reproj", "parallax", "vdir", "depth")

    def __init__(self):
        self.parts = {k: [] for k in self.KEYS}

    def add(self, X, colours, views, first, reproj, parallax, rays, dist):
        """``rays`` (N, V, 3) unit directions point -> camera, ``dist`` (N, V)."""
        vdir = rays.mean(axis=1)
        vdir /= np.maximum(np.linalg.norm(vdir, axis=1, keepdims=True), 1e-12)
        for key, value in zip(self.KEYS, (X, colours, views, first, reproj, parallax, vdir,
                                          dist.min(axis=1))):
            self.parts[key].append(value)

    def result(self, frames_used) -> "TriangulatedPoints":
        def cat(key, shape):
            return np.concatenate(self.parts[key]) if self.parts[key] else np.zeros(shape)
        return TriangulatedPoints(cat("points", (0, 3)), np.clip(cat("colours", (0, 3)), 0, 1),
                                  cat("views", (0,)).astype(np.int64),
                                  cat("first", (0,)).astype(np.int64), cat("reproj", (0,)),
                                  cat("parallax", (0,)), cat("vdir", (0, 3)), cat("depth", (0,)),
                                  frames_used=list(frames_used))


def detect(image_rgb: np.ndarray, max_features: int):
    """SIFT keypoints ``(N, 2)`` float64 pixel coordinates and descriptors
    ``(N, 128)`` float32 of an RGB image (uint8 or float in [0, 1])."""
    import cv2

    img = np.asarray(image_rgb)
    if img.dtype != np.uint8:
        img = np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)
    gray = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img
    sift = cv2.SIFT_create(nfeatures=int(max_features))
    kps, desc = sift.detectAndCompute(gray, None)
    if desc is None or not kps:
        return np.zeros((0, 2)), np.zeros((0, 128), np.float32)
    xy = np.array([k.pt for k in kps], np.float64)
    return xy, desc.astype(np.float32)


def match(desc_a: np.ndarray, desc_b: np.ndarray, ratio: float) -> np.ndarray:
    """Mutual nearest neighbours passing the ratio test: (M, 2) index pairs."""
    import cv2

    if len(desc_a) < 2 or len(desc_b) < 2:
        return np.zeros((0, 2), np.int64)
    bf = cv2.BFMatcher(cv2.NORM_L2)
    ab = bf.knnMatch(desc_a, desc_b, k=2)
    ba = bf.match(desc_b, desc_a)
    back = np.full(len(desc_b), -1, np.int64)
    for m in ba:
        back[m.queryIdx] = m.trainIdx
    out = [(m[0].queryIdx, m[0].trainIdx) for m in ab
           if len(m) == 2 and m[0].distance < ratio * m[1].distance
           and back[m[0].trainIdx] == m[0].queryIdx]
    return np.array(out, np.int64).reshape(-1, 2)


def _skew(t):
    return np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])


def fundamental(K: np.ndarray, cam_a: np.ndarray, cam_b: np.ndarray) -> np.ndarray:
    """F with x_b^T F x_a = 0 for the cameras ``cam_a``, ``cam_b``
    (camera-to-world, OpenCV camera axes: x right, y down, z forward)."""
    T = np.linalg.inv(cam_b) @ cam_a            # a -> b
    R, t = T[:3, :3], T[:3, 3]
    Kinv = np.linalg.inv(K)
    return Kinv.T @ _skew(t) @ R @ Kinv


def sampson_px(F: np.ndarray, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """Sampson distance (pixels) of correspondences ``xa`` <-> ``xb`` (N, 2)."""
    ha = np.hstack([xa, np.ones((len(xa), 1))])
    hb = np.hstack([xb, np.ones((len(xb), 1))])
    Fa = ha @ F.T
    Fb = hb @ F
    num = np.sum(hb * Fa, axis=1) ** 2
    den = Fa[:, 0] ** 2 + Fa[:, 1] ** 2 + Fb[:, 0] ** 2 + Fb[:, 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-30))


# ----------------------------------------------------------------------------
# Tracks and triangulation
# ----------------------------------------------------------------------------

class _UnionFind:
    def __init__(self, n):
        self.parent = np.arange(n)

    def find(self, x):
        p = self.parent
        root = x
        while p[root] != root:
            root = p[root]
        while p[x] != root:
            p[x], x = root, p[x]
        return root

    def union(self, a, b):
        ra, rb = self.find(a), self.find(b)
        if ra != rb:
            self.parent[max(ra, rb)] = min(ra, rb)


def triangulate_dlt(rays_cam: np.ndarray, w2c: np.ndarray) -> np.ndarray:
    """Points from ``V`` views each: ``rays_cam`` (N, V, 2) normalised image
    coordinates (x/z, y/z), ``w2c`` (N, V, 4, 4). Linear least squares
    (the DLT's SVD); returns (N, 3)."""
    P = w2c[:, :, :3, :]                                   # (N, V, 3, 4)
    x = rays_cam[:, :, 0:1]
    y = rays_cam[:, :, 1:2]
    A = np.concatenate([x * P[:, :, 2, :] - P[:, :, 0, :],
                        y * P[:, :, 2, :] - P[:, :, 1, :]], axis=1)   # (N, 2V, 4)
    _, _, vt = np.linalg.svd(A)
    X = vt[:, -1, :]
    w = X[:, 3:4]
    w = np.where(np.abs(w) < 1e-12, 1e-12, w)
    return X[:, :3] / w



def triangulate_views(xy, w2c, centres, K, Kinv, min_depth, max_depth, max_reproj_px,
                      min_parallax_deg):
    """Triangulate N tracks seen in V views and check them in every view.

    ``xy`` (N, V, 2) pixels, ``w2c`` (N, V, 4, 4) and ``centres`` (N, V, 3)
    the views' poses. A point is kept when it lies at least ``min_depth`` in
    front of every camera, within ``max_depth`` of the nearest, reprojects
    within ``max_reproj_px`` in every view and is seen under at least
    ``min_parallax_deg`` by its most separated pair of views. Returns
    ``(X, ok, err, parallax, rays, dist)``: rays (N, V, 3) from the point to
    each camera, dist (N, V) their lengths."""
    h = np.concatenate([xy, np.ones(xy.shape[:2] + (1,))], axis=2) @ Kinv.T
    X = triangulate_dlt(h[:, :, :2] / h[:, :, 2:3], w2c)
    pc = np.einsum("nvij,nj->nvi", w2c[:, :, :3, :3], X) + w2c[:, :, :3, 3]
    z = pc[:, :, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * pc[:, :, 0] / z + K[0, 2]
        v = K[1, 1] * pc[:, :, 1] / z + K[1, 2]
    err = np.sqrt((u - xy[:, :, 0]) ** 2 + (v - xy[:, :, 1]) ** 2)
    err = np.where(np.isfinite(err), err, np.inf).max(axis=1)
    rays = centres - X[:, None, :]
    dist = np.linalg.norm(rays, axis=2)
    rays = rays / np.maximum(dist[:, :, None], 1e-12)
    cosang = np.einsum("nai,nbi->nab", rays, rays)
    parallax = np.degrees(np.arccos(np.clip(cosang.min(axis=(1, 2)), -1, 1)))
    ok = ((z.min(axis=1) >= min_depth) & (dist.min(axis=1) <= max_depth)
          & (err <= max_reproj_px) & (parallax >= min_parallax_deg)
          & np.all(np.isfinite(X), axis=1))
    return X, ok, err, parallax, rays, dist

def _bilinear(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    H, W = image.shape[:2]
    x = np.clip(xy[:, 0], 0, W - 1.001)
    y = np.clip(xy[:, 1], 0, H - 1.001)
    x0 = np.floor(x).astype(np.int64)
    y0 = np.floor(y).astype(np.int64)
    fx = (x - x0)[:, None]
    fy = (y - y0)[:, None]
    im = image.astype(np.float64)
    return ((1 - fx) * (1 - fy) * im[y0, x0] + fx * (1 - fy) * im[y0, x0 + 1]
            + (1 - fx) * fy * im[y0 + 1, x0] + fx * fy * im[y0 + 1, x0 + 1])


def triangulate_frames(load_image: Callable[[int], np.ndarray], cam_to_world: np.ndarray,
                       K: np.ndarray, training: Sequence[int],
                       options: TriangulationOptions | None = None,
                       log=None, exclude: Callable[[int], np.ndarray] | None = None
                       ) -> TriangulatedPoints:
    """Triangulate the surfaces seen by the frames ``training``.

    ``load_image(i)`` returns frame ``i``'s image as RGB (uint8, or float
    *linear* RGB in [0, 1]); it is called for the frames in ``training``
    only. ``cam_to_world`` (F, 4, 4) in OpenCV camera axes, ``K`` the
    intrinsics of the images ``load_image`` returns. ``exclude(i)``, when
    given, returns a mask (any resolution of the same aspect, or None) of
    pixels whose keypoints are not used: moving objects, whose tracks would
    triangulate to the wrong depth along the epipolar lines of a camera
    driving behind them.
    """
    from .kitti import srgb_to_linear

    opts = options or TriangulationOptions()
    frames = [int(i) for i in sorted(set(training))]
    K = np.asarray(K, np.float64)
    Kinv = np.linalg.inv(K)
    feats, linear = {}, {}
    for i in frames:
        img = np.asarray(load_image(i))
        xy, desc = detect(img, opts.max_features)
        mask = exclude(i) if exclude is not None else None
        if mask is not None and len(xy):
            sx, sy = mask.shape[1] / img.shape[1], mask.shape[0] / img.shape[0]
            mx = np.clip((xy[:, 0] * sx).astype(np.int64), 0, mask.shape[1] - 1)
            my = np.clip((xy[:, 1] * sy).astype(np.int64), 0, mask.shape[0] - 1)
            free = mask[my, mx] == 0
            xy, desc = xy[free], desc[free]
        feats[i] = (xy, desc)
        if img.dtype == np.uint8:
            linear[i] = srgb_to_linear(img.astype(np.float32) / 255.0)
        else:
            linear[i] = img.astype(np.float32)
    offset = {}
    n_nodes = 0
    for i in frames:
        offset[i] = n_nodes
        n_nodes += len(feats[i][0])
    uf = _UnionFind(max(n_nodes, 1))
    n_raw = n_epi = 0
    for a_pos, a in enumerate(frames):
        for b in frames[a_pos + 1:a_pos + 1 + opts.pair_span]:
            m = match(feats[a][1], feats[b][1], opts.ratio)
            n_raw += len(m)
            if not len(m):
                continue
            xa, xb = feats[a][0][m[:, 0]], feats[b][0][m[:, 1]]
            F = fundamental(K, cam_to_world[a], cam_to_world[b])
            ok = sampson_px(F, xa, xb) <= opts.epipolar_px
            n_epi += int(ok.sum())
            for ia, ib in m[ok]:
                uf.union(offset[a] + ia, offset[b] + ib)

    # Gather tracks: node -> (frame, keypoint).
    node_frame = np.concatenate([np.full(len(feats[i][0]), i) for i in frames]) \
        if n_nodes else np.zeros(0, np.int64)
    node_kp = np.concatenate([np.arange(len(feats[i][0])) for i in frames]) \
        if n_nodes else np.zeros(0, np.int64)
    roots = np.array([uf.find(k) for k in range(n_nodes)], np.int64)
    uniq, track_of, sizes = np.unique(roots, return_inverse=True, return_counts=True)
    # A track with two keypoints in one frame is ambiguous.
    pair = track_of.astype(np.int64) * (int(node_frame.max()) + 1 if n_nodes else 1) + node_frame
    _, pair_inv, pair_count = np.unique(pair, return_inverse=True, return_counts=True)
    dup_tracks = np.unique(track_of[pair_count[pair_inv.ravel()] > 1])
    good_track = sizes >= max(opts.min_views, 2)
    good_track[dup_tracks] = False

    w2c_all = np.linalg.inv(cam_to_world)
    centres = cam_to_world[:, :3, 3]
    out = _PointBatches()
    node_sel = good_track[track_of]
    order = np.lexsort((node_frame[node_sel], track_of[node_sel]))
    t_ids = track_of[node_sel][order]
    f_ids = node_frame[node_sel][order]
    k_ids = node_kp[node_sel][order]
    if t_ids.size:
        starts = np.r_[0, np.nonzero(np.diff(t_ids))[0] + 1]
        lens = np.diff(np.r_[starts, t_ids.size])
        for V in np.unique(lens):
            s = starts[lens == V]
            idx = s[:, None] + np.arange(V)[None, :]                 # (N, V)
            fr = f_ids[idx]
            kp = k_ids[idx]
            xy = np.empty(idx.shape + (2,))
            for i in np.unique(fr):
                sel = fr == i
                xy[sel] = feats[int(i)][0][kp[sel]]
            X, ok, err, parallax, rays, dist = triangulate_views(
                xy, w2c_all[fr], centres[fr], K, Kinv, opts.min_depth, opts.max_depth,
                opts.max_reproj_px, opts.min_parallax_deg)
            if not ok.any():
                continue
            col = np.zeros((int(ok.sum()), 3))
            fr_ok, xy_ok = fr[ok], xy[ok]
            for i in np.unique(fr_ok):
                sel = fr_ok == i
                rows = np.nonzero(sel)[0]
                col[rows] += _bilinear(linear[int(i)], xy_ok[sel])
            col /= V
            out.add(X[ok], col, np.full(int(ok.sum()), V), fr[ok, 0], err[ok], parallax[ok],
                    rays[ok], dist[ok])

    res = out.result(frames)
    res.stats = {"keypoints": int(n_nodes), "matches": int(n_raw),
                 "epipolar_inliers": int(n_epi), "tracks": int(good_track.sum()),
                 "points": len(res)}
    if log is not None:
        log("[triangulate] %d frames, %d keypoints, %d matches (%d epipolar inliers), "
            "%d tracks -> %d points" % (len(frames), n_nodes, n_raw, n_epi,
                                        int(good_track.sum()), len(res)))
    return res


def dense_frames(load_image: Callable[[int], np.ndarray], cam_to_world: np.ndarray,
                 K: np.ndarray, training: Sequence[int],
                 options: TriangulationOptions | None = None, log=None,
                 exclude: Callable[[int], np.ndarray] | None = None) -> TriangulatedPoints:
    """Dense two-view points: optical flow (OpenCV DIS) from each training
    frame to the first later training frame at least ``dense_baseline``
    metres away (longer baselines break the flow), on a grid of
    ``dense_stride`` pixels. A pixel is kept when the backward flow returns
    within ``dense_fb_px``, the flow's end lies within ``epipolar_px`` of the
    known epipolar line, and the DLT point passes the cheirality, depth and
    parallax tests of :func:`triangulate_frames`. Sparse tracks are few on a
    slowly driving car's textured trees and bridges; the flow sees all of
    them. Same arguments as :func:`triangulate_frames`."""
    import cv2
    from .kitti import srgb_to_linear

    opts = options or TriangulationOptions()
    frames = [int(i) for i in sorted(set(training))]
    K = np.asarray(K, np.float64)
    Kinv = np.linalg.inv(K)
    w2c_all = np.linalg.inv(cam_to_world)
    centres = cam_to_world[:, :3, 3]
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    gray, linear = {}, {}

    def get(i):
        if i not in gray:
            img = np.asarray(load_image(i))
            u8 = img if img.dtype == np.uint8 else \
                np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)
            gray[i] = cv2.cvtColor(u8, cv2.COLOR_RGB2GRAY)
            linear[i] = srgb_to_linear(img.astype(np.float32) / 255.0) if img.dtype == np.uint8 \
                else img.astype(np.float32)
        return gray[i]

    out = _PointBatches()
    n_cand = 0
    pairs = []
    for pos, a in enumerate(frames):
        later = [b for b in frames[pos + 1:]
                 if np.linalg.norm(centres[b] - centres[a]) >= opts.dense_baseline]
        if later:
            pairs.append((a, later[0]))
    for a, b in pairs:
        ga, gb = get(a), get(b)
        fwd = dis.calc(ga, gb, None)
        bwd = dis.calc(gb, ga, None)
        H, W = ga.shape
        ys, xs = np.mgrid[opts.dense_stride // 2:H:opts.dense_stride,
                          opts.dense_stride // 2:W:opts.dense_stride]
        xa = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)
        if exclude is not None:
            mask = exclude(a)
            if mask is not None:
                mx = np.clip((xa[:, 0] * mask.shape[1] / W).astype(np.int64), 0, mask.shape[1] - 1)
                my = np.clip((xa[:, 1] * mask.shape[0] / H).astype(np.int64), 0, mask.shape[0] - 1)
                xa = xa[mask[my, mx] == 0]
        n_cand += len(xa)
        xb = xa + fwd[xa[:, 1].astype(np.int64), xa[:, 0].astype(np.int64)]
        inside = (xb[:, 0] >= 0) & (xb[:, 0] <= W - 1) & (xb[:, 1] >= 0) & (xb[:, 1] <= H - 1)
        xa, xb = xa[inside], xb[inside]
        back = _bilinear(bwd, xb)
        fb = np.linalg.norm(xb + back - xa, axis=1)
        F = fundamental(K, cam_to_world[a], cam_to_world[b])
        ok = (fb <= opts.dense_fb_px) & (sampson_px(F, xa, xb) <= opts.epipolar_px)
        xa, xb = xa[ok], xb[ok]
        if not len(xa):
            continue
        xy = np.stack([xa, xb], 1)                                   # (N, 2, 2)
        fr = np.array([a, b])
        n = len(xa)
        X, keep, err, parallax, rays, dist = triangulate_views(
            xy, np.broadcast_to(w2c_all[fr], (n, 2, 4, 4)), np.broadcast_to(centres[fr], (n, 2, 3)),
            K, Kinv, opts.min_depth, opts.max_depth, opts.max_reproj_px,
            opts.dense_min_parallax_deg)
        if not keep.any():
            continue
        col = 0.5 * (_bilinear(linear[a], xa[keep]) + _bilinear(linear[b], xb[keep]))
        n_keep = int(keep.sum())
        out.add(X[keep], col, np.full(n_keep, 2), np.full(n_keep, a), err[keep], parallax[keep],
                rays[keep], dist[keep])

    res = out.result(sorted(gray))
    n = len(res)
    res.stats = {"flow_pixels": int(n_cand), "points": n}
    if log is not None:
        log("[triangulate] dense flow: %d pixels of %d frame pairs -> %d points"
            % (n_cand, len(pairs), n))
    return res


def concatenate(parts) -> TriangulatedPoints:
    """One :class:`TriangulatedPoints` from several."""
    parts = list(parts)
    cat = lambda key: np.concatenate([getattr(p, key) for p in parts])  # noqa: E731
    return TriangulatedPoints(cat("points"), cat("colours"), cat("views"), cat("first_frame"),
                              cat("reproj_px"), cat("parallax_deg"), cat("view_dir"),
                              cat("depth"), sorted({f for p in parts for f in p.frames_used}),
                              {k: v for p in parts for k, v in p.stats.items()})


# ----------------------------------------------------------------------------
# Keep what the LiDAR lacks; Gaussians
# ----------------------------------------------------------------------------

def far_from(points: np.ndarray, reference: np.ndarray, clearance: float) -> np.ndarray:
    """Mask of ``points`` with no ``reference`` point within ``clearance``
    (max-norm, on a voxel grid of that size: exact up to the grid's
    neighbourhood, i.e. anything nearer than ``clearance`` is caught, some
    up to 2 x ``clearance`` too)."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if len(points) == 0 or len(reference) == 0:
        return np.ones(len(points), bool)
    occupied = np.unique(ig.voxel_keys(reference, clearance))
    q = np.floor(points / clearance).astype(np.int64)
    near = np.zeros(len(points), bool)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                k = ig.voxel_keys((q + [dx, dy, dz] + 0.5) * clearance, clearance)
                near |= np.isin(k, occupied)
    return ~near


def camera_gaussians(pts: TriangulatedPoints, K: np.ndarray, knn: int = 8,
                     max_footprint_px: float = 6.0) -> dict:
    """Gaussian arrays (the importer's background layout) for triangulated
    points: PCA normals over their k nearest triangulated neighbours
    (oriented towards the cameras), tangent scales from the neighbours'
    spacing but no larger than ``max_footprint_px`` pixels of ``K`` at the
    point's depth (nor smaller than half a pixel)."""
    n = len(pts)
    if n == 0:
        z3 = np.zeros((0, 3), np.float32)
        return {"centers": z3, "scales": z3, "quaternions": np.zeros((0, 4), np.float32),
                "normals": z3, "lidar_albedo": np.zeros(0, np.float32), "albedo": z3}
    k = min(knn, n)
    idx, dist = ig.knn(pts.points, k)
    if n >= 3:
        normals, tangents, _ = ig.pca_frames(pts.points, idx)
    else:
        normals, tangents = pts.view_dir.copy(), np.zeros((n, 3))
    normals = ig.orient_towards(normals, pts.view_dir)
    pixel = pts.depth / float(K[0, 0])                  # metres per pixel at that depth
    d = dist[:, 1:] if dist.shape[1] > 1 else dist
    s = np.clip(0.5 * d.mean(axis=1), 0.5 * pixel, max_footprint_px * pixel)
    scales = np.stack([s, s, 0.1 * s], axis=1).astype(np.float32)
    return {"centers": pts.points.astype(np.float32), "scales": scales,
            "quaternions": ig.frames_to_quaternions(tangents, normals).astype(np.float32),
            "normals": normals.astype(np.float32),
            "lidar_albedo": np.zeros(n, np.float32),
            "albedo": pts.colours.astype(np.float32)}


# ----------------------------------------------------------------------------
# The import step
# ----------------------------------------------------------------------------

def held_out(index: int) -> bool:
    """The evaluation split of ``import``: every fifth frame is held out."""
    return index % 5 == 4


def import_step(src, state, opts, log, options: TriangulationOptions | None = None):
    """``mi-invrgbl import``'s camera-geometry step: triangulate the training
    frames (full-resolution images, the drive's own intrinsics), keep the
    points the LiDAR lacks and append them as Gaussians to the background
    (``state.background``, before colours). LiDAR albedo of those
    Gaussians: the median of the LiDAR's (they are never scanned). They
    count towards ``--max-points`` (at most a quarter of it): as many LiDAR
    Gaussians, drawn at random, make room."""
    from .images import read_image_uint8

    options = options or TriangulationOptions()
    drive = src.drive
    positions = state.positions
    W0, H0 = drive.image_size
    training = [i for i in range(len(positions)) if not held_out(i)]
    if len(training) < 2:
        log("[import] fewer than two training frames: no triangulation")
        return

    cache = {}

    def load(i):
        if i not in cache:
            cache[i] = read_image_uint8(drive.image_paths[positions[i]], (W0, H0))
        return cache[i]

    exclude = None
    if state.motion is not None:
        from .motion import image_masks
        masks = image_masks(state, which="dynamic")
        exclude = masks.__getitem__
    pts = triangulate_frames(load, state.cam_poses, drive.K, training, options, log=log,
                             exclude=exclude)
    if options.dense:
        dense = dense_frames(load, state.cam_poses, drive.K, training, options, log=log,
                             exclude=exclude)
        first, _ = ig.voxel_dedupe(dense.points, options.dense_voxel)
        pts = concatenate([pts, dense.subset(np.sort(first))])
    n_all = len(pts)
    pts = pts.subset(far_from(pts.points, state.bg.points, options.lidar_clearance))
    bg = state.background
    n_bg = len(bg["centers"])
    # The camera-only Gaussians take their place inside --max-points: the
    # same number of LiDAR Gaussians (drawn at random, seeded) make room.
    cap = min(len(pts), opts.max_points // 4)
    if cap < len(pts):      # keep the farthest: nearer surfaces have LiDAR points around
        far_first = np.argsort(-pts.depth, kind="stable")[:cap]
        pts = pts.subset(np.sort(far_first))
    room = max(0, n_bg + len(pts) - opts.max_points)
    if room:
        rng = np.random.default_rng([opts.seed, 2])
        keep = np.sort(rng.choice(n_bg, n_bg - room, replace=False))
        for key in ("centers", "scales", "quaternions", "normals", "lidar_albedo"):
            bg[key] = bg[key][keep]
    g = camera_gaussians(pts, drive.K)
    g["lidar_albedo"][:] = float(np.median(bg["lidar_albedo"])) if len(bg["lidar_albedo"]) else 0.0
    for key in ("centers", "scales", "quaternions", "normals", "lidar_albedo"):
        bg[key] = np.concatenate([bg[key], g[key].astype(bg[key].dtype)])
    state.counts["camera_gaussians"] = len(pts)
    state.counts["background_gaussians"] = int(len(bg["centers"]))
    log("[import] %d triangulated points, %d where the LiDAR has no point within %.2f m "
        "-> camera-only Gaussians" % (n_all, len(pts), options.lidar_clearance))
