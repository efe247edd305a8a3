"""LiDAR sweeps as range images, and LiDAR points projected into a camera.

Range image (the layout the ``lidar`` sensor plugin renders)
-----------------------------------------------------------
Rows are beams, row 0 the top beam (largest elevation). Columns are azimuth
steps: column ``c`` of ``W`` looks along

    phi(c) = pi * (1 - 2 (c + 0.5) / W)

so column 0 looks backwards (phi ~ +pi), column W/2 along +x (forward), and
azimuth (measured from +x towards +y, i.e. to the left) decreases from left
to right, like a panorama seen from inside. A point falls into column
``floor((1 - phi/pi) * W/2) mod W``. Where several points fall into one pixel
the nearest wins (it is the one a ray through that pixel would hit).

Channels: ``intensity`` (in [0, 1]), ``range`` (metres, Euclidean from the
sensor origin), ``hit`` (True where a return exists; False = ray drop or
nothing within range) and ``index`` (the point that filled the pixel, -1 if
none). ``elevations`` holds the per-row elevation table (radians, descending),
which is what the ``lidar`` sensor's ``elevations`` parameter expects.

Which beam a point belongs to (``assign_beams``)
-----------------------------------------------
Elevation computed from the sensor origin is a poor beam label on the HDL-64:
its lasers sit at different heights and angles on the head, so one laser's
points spread over ~1-2 degrees of apparent elevation at short range while
neighbouring lasers are only ~0.4 degrees apart. KITTI stores each sweep in
firing order, laser by laser: within one laser's ring the azimuth increases
monotonically (+x towards +y), passing once through the +-pi seam behind the
car, and the next laser starts again near the forward direction. So
``method='scan_order'`` starts a new ring wherever the azimuth steps from
negative to non-negative (crossing the forward direction, not the seam behind)
after the current ring has passed the seam at least once; the pass-the-seam
condition keeps azimuth jitter near 0 deg from splitting a ring. Rings are
then ordered by their median elevation to give rows top to bottom, and each
row's elevation is that median.

If the point order has been lost (shuffled, cropped, merged sweeps) or a laser
returned nothing, the ring count differs from ``n_beams``; ``method='auto'``
then falls back to ``method='elevation'``: cut the sorted elevations at
their ``n_beams - 1`` widest gaps, refined by 1-D k-means. That is exact for
sensors whose beams share one origin (synthetic sweeps, most modern
sensors) and approximate on the HDL-64. When the beam table is known (a
sensor's spec sheet, the synthetic-scene generator) pass it as
``beam_elevations``: each point goes to the nearest beam.

Camera projection
-----------------
``points_to_image`` maps points ``X`` (sensor frame) to pixels with
``P @ T_velo_to_cam @ X``. ``P`` is a 3x4 projection in the OpenCV/KITTI
convention (integer pixel coordinates at pixel centres; pixel (i, j) covers
u in [i-0.5, i+0.5)). The returned depth is the third homogeneous coordinate,
i.e. z in the camera that ``P`` describes (for KITTI's ``P_rect_02`` that is
camera 2, 6 mm further along z than rectified camera 0). ``pixels_to_points``
inverts it exactly.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

from ..errors import UserError


# ----------------------------------------------------------------------------
# Azimuth <-> column
# ----------------------------------------------------------------------------

def column_azimuth(width: int) -> np.ndarray:
    """Azimuth (radians) of each column's centre: pi * (1 - 2 (c + 0.5) / W)."""
    c = np.arange(width, dtype=np.float64)
    return math.pi * (1.0 - 2.0 * (c + 0.5) / width)


def azimuth_to_column(phi, width: int) -> np.ndarray:
    """Column index of azimuth ``phi`` (radians, any range)."""
    phi = np.asarray(phi, np.float64)
    col = np.floor((1.0 - phi / math.pi) * (width / 2.0)).astype(np.int64)
    return np.mod(col, width)


# ----------------------------------------------------------------------------
# Beam assignment
# ----------------------------------------------------------------------------

def _elevation(points):
    p = np.asarray(points, np.float64)
    return np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1]))


def scan_order_rings(points) -> np.ndarray:
    """Ring index (firing order, 0-based) of each point of a KITTI-ordered
    sweep; see the module docstring for the rule."""
    p = np.asarray(points, np.float64)
    if p.shape[0] == 0:
        return np.zeros(0, np.int64)
    az = np.arctan2(p[:, 1], p[:, 0])
    step = np.diff(az)
    # A step below -pi is the pass through the seam behind the sensor.
    seam_passes = np.concatenate([[0], np.cumsum(step < -math.pi)])
    candidates = np.nonzero((az[:-1] < 0) & (az[1:] >= 0) & (step < math.pi))[0] + 1
    starts = []
    last_seam = 0
    for i in candidates:
        if seam_passes[i] > last_seam:
            starts.append(i)
            last_seam = seam_passes[i]
    ring = np.zeros(p.shape[0], np.int64)
    if starts:
        ring[np.asarray(starts)] = 1
        ring = np.cumsum(ring)
    return ring


def cluster_elevations(elevation, n_beams: int, iterations: int = 30) -> np.ndarray:
    """Label elevations (radians) with up to ``n_beams`` clusters, labels
    ordered by increasing elevation.

    Start by cutting the sorted elevations at their ``n_beams - 1`` widest
    gaps (exact when each beam's points share one elevation), then refine
    with 1-D k-means (Lloyd) iterations, which only matter when beams
    overlap. Fewer distinct elevations than beams give fewer clusters.
    """
    e = np.asarray(elevation, np.float64)
    if e.size == 0:
        return np.zeros(0, np.int64)
    es = np.sort(e)
    gaps = np.diff(es)
    k = min(n_beams - 1, int(np.count_nonzero(gaps > 0)))
    cuts = np.sort(np.argpartition(gaps, -k)[-k:]) if k > 0 else np.zeros(0, np.int64)
    bounds = 0.5 * (es[cuts] + es[cuts + 1])
    for _ in range(iterations):
        labels = np.searchsorted(bounds, e)
        counts = np.bincount(labels, minlength=k + 1)
        centres = np.bincount(labels, weights=e, minlength=k + 1) / np.maximum(counts, 1)
        if np.any(counts == 0):
            break  # a cluster emptied: keep the previous boundaries
        new = 0.5 * (centres[1:] + centres[:-1])
        if np.allclose(new, bounds, atol=1e-9):
            break
        bounds = new
    return np.searchsorted(bounds, e)


def assign_beams(points, n_beams: int = 64, method: str = "auto",
                 beam_elevations=None):
    """Beam row (0 = top) of every point and the per-row elevation table.

    ``beam_elevations`` (radians, any order): a known beam table; each point
    then goes to the nearest entry (``method`` is ignored) and the table is
    returned sorted. Otherwise ``method`` is 'auto', 'scan_order' or
    'elevation' (see the module docstring).

    Returns ``(rows (N,) int64, elevations (n_beams,) radians descending,
    method_used)``. If fewer than ``n_beams`` beams are found, the missing
    rows are appended at the bottom, continuing the mean beam spacing.
    """
    elev = _elevation(points)
    if beam_elevations is not None:
        table = np.sort(np.asarray(beam_elevations, np.float64))[::-1]
        mids = 0.5 * (table[1:] + table[:-1])
        # table descends, so search in the ascending negated midpoints
        return np.searchsorted(-mids, -elev), table, "table"
    if method not in ("auto", "scan_order", "elevation"):
        raise ValueError(f"unknown beam assignment method {method!r}")

    labels, used = None, method
    if method in ("auto", "scan_order"):
        rings = scan_order_rings(points)
        n_rings = int(rings.max()) + 1 if rings.size else 0
        if n_rings == n_beams:
            labels, used = rings, "scan_order"
        elif method == "scan_order":
            raise UserError(f"scan-order beam detection found {n_rings} rings, "
                            f"expected {n_beams}; use method='elevation'")
    if labels is None:
        labels, used = cluster_elevations(elev, n_beams), "elevation"

    n_found = int(labels.max()) + 1 if labels.size else 0
    medians = np.array([np.median(elev[labels == k]) for k in range(n_found)])
    order = np.argsort(-medians, kind="stable")      # rows: top to bottom
    row_of_label = np.empty(n_found, np.int64)
    row_of_label[order] = np.arange(n_found)
    table = medians[order]
    if n_found < n_beams:
        step = (table[0] - table[-1]) / (n_found - 1) if n_found > 1 else np.radians(0.4)
        start = table[-1] if n_found else 0.0
        table = np.concatenate([table, start - step * np.arange(1, n_beams - n_found + 1)])
    return row_of_label[labels] if labels.size else labels, table, used


# ----------------------------------------------------------------------------
# Beam layout of a drive
# ----------------------------------------------------------------------------

#: A sensor whose returns leave an azimuth gap wider than this (degrees) is not
#: spinning: its rays form an explicit pattern (solid-state, Livox-style).
SPINNING_MAX_GAP_DEG = 60.0


@dataclass
class BeamLayout:
    """What the sweeps of a drive say about their sensor.

    ``kind`` is ``spinning`` (rows = beams, columns = azimuth steps) or
    ``rays`` (an explicit pattern: ``rays`` holds its unit directions in the
    sensor frame and ``ray_beam`` the beam of each). ``elevations`` is the
    beam table (radians, descending, row 0 = top beam); ``method`` how it was
    found: ``histogram`` (separated elevation clusters), ``scan_order``
    (KITTI's firing order; beams overlap in elevation), ``kmeans`` (neither:
    ``n_beams`` clusters of the elevations, approximate).
    """
    kind: str
    elevations: np.ndarray
    method: str
    uniform: bool
    rays: np.ndarray | None = None
    ray_beam: np.ndarray | None = None

    @property
    def n_beams(self) -> int:
        return int(self.elevations.size)

    def describe(self) -> str:
        e = np.degrees(self.elevations)
        table = ("%s table %+.3f..%+.3f deg" % ("uniform" if self.uniform else "non-uniform",
                                              e[0], e[-1])) if e.size else "no table"
        if self.kind == "rays":
            return ("explicit ray pattern: %d rays in %d beam(s), %s (from the %s of the "
                    "sweeps)" % (len(self.rays), self.n_beams, table,
                                 "elevation histogram" if self.method == "histogram" else self.method))
        how = {"histogram": "elevation histogram of the sweeps",
               "scan_order": "firing order of the points (beams overlap in elevation)",
               "kmeans": "k-means of the elevations (beams overlap; approximate)"}[self.method]
        return "spinning sensor, %d beams, %s (%s)" % (self.n_beams, table, how)


def _azimuth_gap_deg(points) -> float:
    az = np.degrees(np.arctan2(points[:, 1], points[:, 0])) % 360.0
    occ = np.bincount(np.floor(az).astype(np.int64) % 360, minlength=360) > 0
    if not occ.any():
        return 360.0
    # Longest circular run of empty one-degree bins.
    empty = np.concatenate([~occ, ~occ]).astype(np.int64)
    run = best = 0
    for v in empty:
        run = run + 1 if v else 0
        best = max(best, run)
    return float(min(best, 360))


def _pattern_rays(points, clusters):
    """Distinct ray directions of an explicit pattern: per beam, returns
    sorted by azimuth and split where the azimuth jumps (> 1e-4 rad)."""
    d = points / np.maximum(np.linalg.norm(points, axis=1, keepdims=True), 1e-12)
    az = np.arctan2(d[:, 1], d[:, 0])
    beam = clusters.beam
    ok = beam >= 0
    order = np.lexsort((az[ok], beam[ok]))
    b_s, a_s, d_s = beam[ok][order], az[ok][order], d[ok][order]
    new = np.ones(b_s.size, bool)
    new[1:] = (b_s[1:] != b_s[:-1]) | (np.diff(a_s) > 1e-4)
    ray_id = np.cumsum(new) - 1
    n = int(ray_id[-1]) + 1 if ray_id.size else 0
    rays = np.zeros((n, 3))
    for k in range(3):
        rays[:, k] = np.bincount(ray_id, weights=d_s[:, k], minlength=n)
    rays /= np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-12)
    return rays, b_s[new]


def detect_beam_layout(sweeps, n_beams: int | None = None,
                       max_points: int = 4_000_000) -> BeamLayout:
    """The sensor's beam layout from its sweeps (sensor-frame points, any order).

    1. Pattern: a spinning sensor covers the full circle in azimuth; returns
       with a gap wider than :data:`SPINNING_MAX_GAP_DEG` come from an
       explicit ray pattern, whose distinct directions are recovered.
    2. Beams: the elevation histogram of all sweeps
       (:func:`mi_invrgbl.physics.beam_layout.elevation_clusters`), exact for
       beams that share one origin, uniform or not. Where beams overlap in
       elevation (the HDL-64E's lasers sit at different heights), KITTI's
       firing order gives the rings if it is consistent over the sweeps;
       failing that, ``n_beams`` (default 64) k-means clusters.

    ``n_beams`` is only a hint for that last resort: a count found in the data
    wins over it.
    """
    from ..physics.beam_layout import elevation_clusters
    pts = [np.asarray(p, np.float64)[:, :3] for p in sweeps if len(p)]
    if not pts:
        raise UserError("no LiDAR returns in any sweep: cannot find the beam layout")
    allp = np.concatenate(pts)
    if allp.shape[0] > max_points:
        allp = allp[:: int(np.ceil(allp.shape[0] / max_points))]
    rng = np.linalg.norm(allp, axis=1)
    allp = allp[rng > 1e-6]
    elev = _elevation(allp)
    cl = elevation_clusters(elev)
    if _azimuth_gap_deg(allp) > SPINNING_MAX_GAP_DEG:
        from ..physics.beam_layout import ray_beams
        rays, _ = _pattern_rays(allp, cl) if cl.separated else (None, None)
        if rays is None:
            # No rows: every distinct direction (1e-4 rad grid) is its own ray.
            d = allp / np.linalg.norm(allp, axis=1, keepdims=True)
            _, first = np.unique(np.round(d / 1e-4).astype(np.int64), axis=0, return_index=True)
            rays = d[np.sort(first)]
        beam, table = ray_beams(rays)
        uniform = bool(table.size < 3 or np.allclose(np.diff(table), np.diff(table).mean(),
                                                     rtol=0.02))
        return BeamLayout("rays", table, "histogram", uniform, rays, beam)
    if cl.separated and cl.n_beams >= 2:
        return BeamLayout("spinning", cl.elevations, "histogram", cl.uniform)
    rings = [int(scan_order_rings(p).max()) + 1 for p in pts]
    values, counts = np.unique(rings, return_counts=True)
    best = int(values[np.argmax(counts)])
    if best >= 4 and counts.max() >= 0.8 * len(pts):
        tables = [assign_beams(p, best, "scan_order")[1] for p, r in zip(pts, rings) if r == best]
        table = np.median(np.stack(tables), axis=0)
        return BeamLayout("spinning", table, "scan_order", False)
    n = int(n_beams or 64)
    labels = cluster_elevations(elev, n)
    k = int(labels.max()) + 1
    table = np.sort(np.array([np.median(elev[labels == j]) for j in range(k)]))[::-1]
    return BeamLayout("spinning", table, "kmeans", False)


# ----------------------------------------------------------------------------
# Range image
# ----------------------------------------------------------------------------

@dataclass
class RangeImage:
    """A sweep resampled on the beam x azimuth grid (see module docstring)."""
    intensity: np.ndarray   # (H, W) float32, 0 where no hit
    range: np.ndarray       # (H, W) float32 metres, 0 where no hit
    hit: np.ndarray         # (H, W) bool
    index: np.ndarray       # (H, W) int64 source point index, -1 where none
    elevations: np.ndarray  # (H,) radians, descending (row 0 = top beam)
    method: str             # beam assignment: 'scan_order', 'elevation', 'table' or 'rays'
    rays: np.ndarray | None = None   # (W, 3) unit directions of an explicit pattern (H = 1)

    @property
    def shape(self):
        return self.hit.shape

    @property
    def azimuths(self) -> np.ndarray:
        return column_azimuth(self.hit.shape[1])

    def directions(self) -> np.ndarray:
        """(H, W, 3) unit ray directions through the pixel centres (the
        pattern's rays for an explicit pattern)."""
        if self.rays is not None:
            return np.asarray(self.rays, np.float64)[None].copy()
        e = self.elevations[:, None]
        a = self.azimuths[None, :]
        return np.stack(np.broadcast_arrays(np.cos(e) * np.cos(a),
                                            np.cos(e) * np.sin(a),
                                            np.sin(e) + 0 * a), axis=-1)

    def to_points(self):
        """Points (M, 3) and intensities (M,) of the hit pixels, placed along
        the pixel-centre rays (so within half a pixel of the source points
        for a single-origin sensor)."""
        pts = self.directions()[self.hit] * self.range[self.hit][:, None]
        return pts.astype(np.float32), self.intensity[self.hit]


def range_image(points, intensity, width: int = 2048, n_beams: int = 64,
                method: str = "auto", beam_elevations=None) -> RangeImage:
    """Resample a sweep into a ``n_beams x width`` range image.

    ``width=2048`` is just below the HDL-64's ~2080 firings per turn at 10 Hz,
    so nearly every firing gets its own column and few collide.
    ``beam_elevations`` (a known beam table) overrides ``n_beams`` and
    ``method``; see :func:`assign_beams`.
    """
    points = np.asarray(points, np.float32).reshape(-1, 3)
    intensity = np.asarray(intensity, np.float32).reshape(-1)
    if points.shape[0] != intensity.shape[0]:
        raise ValueError("points and intensity differ in length")
    if beam_elevations is not None:
        n_beams = len(beam_elevations)
    H, W = n_beams, width
    rows, elevations, used = assign_beams(points, n_beams, method, beam_elevations)
    cols = azimuth_to_column(np.arctan2(points[:, 1], points[:, 0]), W)
    rng = np.linalg.norm(points.astype(np.float64), axis=1)

    flat = rows * W + cols
    # Nearest point per pixel: sort by pixel, then range; keep first of each.
    order = np.lexsort((rng, flat))
    first = np.ones(order.size, bool)
    first[1:] = flat[order][1:] != flat[order][:-1]
    keep = order[first]

    index = np.full(H * W, -1, np.int64)
    index[flat[keep]] = keep
    index = index.reshape(H, W)
    hit = index >= 0
    img_i = np.zeros((H, W), np.float32)
    img_r = np.zeros((H, W), np.float32)
    img_i[hit] = intensity[index[hit]]
    img_r[hit] = rng[index[hit]]
    return RangeImage(img_i, img_r, hit, index, elevations, used)


#: Largest angle (radians) between a point's direction and the pattern ray it
#: is assigned to in :func:`ray_image`.
RAY_TOLERANCE = 2e-3


def ray_image(points, intensity, rays, elevations, tolerance: float = RAY_TOLERANCE) -> RangeImage:
    """A sweep of an explicit ray pattern as a ``1 x N`` range image: pixel
    ``j`` holds the nearest return along pattern ray ``j`` (``rays``: (N, 3)
    sensor-frame directions, the ``lidar`` sensor's film in ``rays`` mode).

    Points farther than ``tolerance`` radians from every ray are dropped.
    """
    import cv2
    points = np.asarray(points, np.float64).reshape(-1, 3)
    intensity = np.asarray(intensity, np.float32).reshape(-1)
    if points.shape[0] != intensity.shape[0]:
        raise ValueError("points and intensity differ in length")
    dirs = np.asarray(rays, np.float64).reshape(-1, 3)
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    n = dirs.shape[0]
    rng = np.linalg.norm(points, axis=1)
    ok = rng > 1e-6
    ray = np.full(points.shape[0], -1, np.int64)
    if ok.any():
        index = cv2.flann_Index(np.ascontiguousarray(dirs, np.float32),
                                {"algorithm": 4, "leaf_max_size": 10})   # exact k-d tree
        q = np.ascontiguousarray(points[ok] / rng[ok, None], np.float32)
        idx, d2 = index.knnSearch(q, 1, params={"checks": -1})
        # Chord length ~ angle at these scales.
        near = np.sqrt(np.maximum(d2[:, 0], 0.0)) <= tolerance
        ray[np.nonzero(ok)[0][near]] = idx[near, 0]
    sel = np.nonzero(ray >= 0)[0]
    order = sel[np.lexsort((rng[sel], ray[sel]))]
    first = np.ones(order.size, bool)
    first[1:] = ray[order][1:] != ray[order][:-1]
    keep = order[first]
    index = np.full(n, -1, np.int64)
    index[ray[keep]] = keep
    hit = index >= 0
    img_i = np.zeros(n, np.float32)
    img_r = np.zeros(n, np.float32)
    img_i[hit] = intensity[index[hit]]
    img_r[hit] = rng[index[hit]]
    return RangeImage(img_i[None], img_r[None], hit[None], index[None],
                      np.asarray(elevations, np.float64), "rays", dirs)


# ----------------------------------------------------------------------------
# Camera projection
# ----------------------------------------------------------------------------

@dataclass
class CameraProjection:
    """LiDAR points seen by a camera: a sparse image plus per-point data."""
    intensity: np.ndarray   # (H, W) float32, 0 where mask is False
    depth: np.ndarray       # (H, W) float32 camera z, 0 where mask is False
    mask: np.ndarray        # (H, W) bool, True where a point landed
    uv: np.ndarray          # (N, 2) float64 pixel coordinates of every point
    point_depth: np.ndarray  # (N,) float64 camera z of every point
    in_image: np.ndarray    # (N,) bool: in front (z > min_depth) and inside


def _as_transform(T, name):
    T = np.asarray(T, np.float64)
    if T.shape == (3, 4):
        T = np.vstack([T, [0, 0, 0, 1]])
    if T.shape != (4, 4):
        raise ValueError(f"{name} must be 4x4 or 3x4, got {T.shape}")
    return T


def points_to_image(points, intensities, T_velo_to_cam, P, image_size,
                    min_depth: float = 0.1) -> CameraProjection:
    """Project sensor-frame points into an image.

    ``image_size`` is ``(width, height)`` as in KITTI's ``S_rect``. Points
    with camera depth <= ``min_depth`` or outside the image are kept out of
    the sparse maps; where several points share a pixel the nearest wins.
    """
    W, H = int(image_size[0]), int(image_size[1])
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    inten = np.asarray(intensities, np.float32).reshape(-1)
    T = _as_transform(T_velo_to_cam, "T_velo_to_cam")
    P = np.asarray(P, np.float64).reshape(3, 4)

    hom = np.hstack([pts, np.ones((pts.shape[0], 1))])
    proj = hom @ (P @ T).T
    w = proj[:, 2]
    front = w > min_depth
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = proj[:, :2] / np.where(front, w, 1.0)[:, None]
    uv[~front] = np.nan
    px = np.floor(uv + 0.5)
    inside = front & (px[:, 0] >= 0) & (px[:, 0] < W) & (px[:, 1] >= 0) & (px[:, 1] < H)

    sel = np.nonzero(inside)[0]
    flat = px[sel, 1].astype(np.int64) * W + px[sel, 0].astype(np.int64)
    order = np.lexsort((w[sel], flat))
    first = np.ones(order.size, bool)
    first[1:] = flat[order][1:] != flat[order][:-1]
    keep = order[first]

    img_i = np.zeros(H * W, np.float32)
    img_d = np.zeros(H * W, np.float32)
    mask = np.zeros(H * W, bool)
    img_i[flat[keep]] = inten[sel[keep]]
    img_d[flat[keep]] = w[sel[keep]]
    mask[flat[keep]] = True
    return CameraProjection(img_i.reshape(H, W), img_d.reshape(H, W),
                            mask.reshape(H, W), uv, w, inside)


def pixels_to_points(uv, depth, T_velo_to_cam, P) -> np.ndarray:
    """Inverse of the projection: pixel coordinates (N, 2) and camera depth
    (N,) -> points (N, 3) in the sensor frame.

    With ``P = [M | p]``: ``M X + p = w (u, v, 1)``, so
    ``X = M^-1 (w (u, v, 1) - p)`` in the frame ``T_velo_to_cam`` maps to.
    """
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    w = np.asarray(depth, np.float64).reshape(-1)
    P = np.asarray(P, np.float64).reshape(3, 4)
    T = _as_transform(T_velo_to_cam, "T_velo_to_cam")
    rhs = np.hstack([uv * w[:, None], w[:, None]]) - P[:, 3]
    cam = np.linalg.solve(P[:, :3], rhs.T).T
    hom = np.hstack([cam, np.ones((cam.shape[0], 1))])
    return (hom @ np.linalg.inv(T).T)[:, :3]
