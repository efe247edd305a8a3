"""A LiDAR's beams from the elevations of its rays or returns.

A spinning LiDAR fires a fixed set of beams, each at its own elevation; a
solid-state sensor's ray pattern often has rows too. Which beam a ray belongs
to matters because every beam has its own gain (and its own ray-drop
behaviour). This module finds the beams from elevations alone, with no
assumption about point order or beam count:

* :func:`elevation_clusters` builds a fine histogram of the elevations
  (``bin_deg`` wide) and takes every run of occupied bins as one beam. For a
  sensor whose beams share one origin (modern sensors, simulated sweeps) each
  beam is a single elevation, so the runs are exact, uniform or not.
* :class:`ElevationClusters` says whether the result is trustworthy
  (``separated``: every beam's spread is well below the gap to its
  neighbours). Heads whose lasers sit at different heights (the HDL-64E)
  smear each beam over 1-2 degrees at short range, neighbouring beams
  overlap, and the histogram cannot separate them: callers then need another
  cue (KITTI's firing order; see :mod:`mi_invrgbl.io.range_image`).

Beams are numbered top first (row 0 = highest elevation), the ``lidar``
sensor's row convention.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Histogram bin of the elevation search (degrees): far below the closest
#: beam spacing of common sensors (VLP-32C: 0.33 deg, OS1-128: 0.35 deg).
BIN_DEG = 0.02
#: A run of bins holding fewer than this share of the median beam's points
#: is noise (a stray return), not a beam.
MIN_SHARE = 0.002
#: Above this many beams (or fewer than MIN_PER_BEAM rays per beam) a ray
#: pattern has no rows (e.g. a rosette): all rays are treated as one beam.
MAX_BEAMS = 512
#: A lone run of elevations wider than this (degrees) is several smeared beams.
SINGLE_BEAM_MAX_SPREAD_DEG = 0.25
MIN_PER_BEAM = 4


@dataclass
class ElevationClusters:
    """Beams found in a set of elevations (radians)."""
    elevations: np.ndarray   # (B,) beam elevations, descending (row 0 = top)
    beam: np.ndarray         # (N,) beam of each input elevation (-1: stray)
    counts: np.ndarray       # (B,) inputs per beam
    spread: np.ndarray       # (B,) width of each beam's elevations (radians)
    separated: bool          # every beam's spread is below half the gap to its neighbours
                             # (a lone beam: below SINGLE_BEAM_MAX_SPREAD_DEG)

    @property
    def n_beams(self) -> int:
        return int(self.elevations.size)

    @property
    def uniform(self) -> bool:
        """Whether the beams are evenly spaced (within 2 % of the mean step)."""
        if self.n_beams < 3:
            return True
        step = -np.diff(self.elevations)
        return bool(np.all(np.abs(step - step.mean()) <= 0.02 * step.mean()))

    def describe(self) -> str:
        e = np.degrees(self.elevations)
        if self.n_beams == 0:
            return "no beam"
        if self.n_beams == 1:
            return "1 beam at %.3f deg" % e[0]
        step = -np.diff(e)
        kind = "uniform" if self.uniform else "non-uniform"
        return ("%d beams, %s table %+.3f..%+.3f deg (spacing %.3f-%.3f deg)"
                % (self.n_beams, kind, e[0], e[-1], step.min(), step.max()))


def elevation_clusters(elevation, bin_deg: float = BIN_DEG,
                       min_share: float = MIN_SHARE) -> ElevationClusters:
    """Beams of ``elevation`` (radians, any order) by the histogram rule above.

    Each beam's elevation is the median of its members. Inputs in runs that
    hold fewer than ``min_share`` of the median run's count get beam -1.
    """
    e = np.asarray(elevation, np.float64).ravel()
    ok = np.isfinite(e)
    beam = np.full(e.size, -1, np.int64)
    empty = ElevationClusters(np.zeros(0), beam, np.zeros(0, np.int64), np.zeros(0), False)
    if not ok.any():
        return empty
    deg = np.degrees(e[ok])
    lo = float(deg.min())
    b = np.floor((deg - lo) / bin_deg).astype(np.int64)
    hist = np.bincount(b)
    occ = hist > 0
    # Runs of occupied bins: a new run starts at an occupied bin after an empty one.
    start = occ & np.concatenate([[True], ~occ[:-1]])
    run_of_bin = np.cumsum(start) - 1
    run = run_of_bin[b]
    n_runs = int(run.max()) + 1
    counts = np.bincount(run, minlength=n_runs)
    keep = counts >= max(1.0, min_share * float(np.median(counts)))
    # Renumber kept runs top first (runs are numbered by increasing elevation).
    kept = np.nonzero(keep)[0]
    new = np.full(n_runs, -1, np.int64)
    new[kept[::-1]] = np.arange(kept.size)
    lab = new[run]
    beam[np.nonzero(ok)[0]] = lab
    B = kept.size
    order = np.argsort(lab, kind="stable")
    lab_s = lab[order]
    e_s = e[ok][order]
    bounds = np.searchsorted(lab_s, np.arange(B + 1))
    elev = np.empty(B)
    spread = np.empty(B)
    for k in range(B):
        v = e_s[bounds[k]:bounds[k + 1]]
        elev[k] = np.median(v)
        spread[k] = float(v.max() - v.min())
    cnt = np.diff(bounds)
    if B > 1:
        gap = -np.diff(elev)
        near = np.minimum(np.concatenate([gap, [np.inf]]), np.concatenate([[np.inf], gap]))
        separated = bool(np.all(spread < 0.5 * near))
    else:
        # One run: a beam only if it is sharp (not several smeared beams).
        separated = B == 1 and float(np.degrees(spread[0])) < SINGLE_BEAM_MAX_SPREAD_DEG
    return ElevationClusters(elev, beam, cnt, spread, separated)


def ray_beams(directions) -> tuple[np.ndarray, np.ndarray]:
    """Beam of each ray of an explicit ray list, from its elevation.

    ``directions``: (N, 3) in the sensor frame (z up). Returns ``(beam (N,),
    elevations (B,) radians descending)``. A pattern without rows (more than
    :data:`MAX_BEAMS` beams, or fewer than :data:`MIN_PER_BEAM` rays per beam
    on average, e.g. a rosette) is one beam: every ray shares one gain.
    """
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    elev = np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1]))
    cl = elevation_clusters(elev, min_share=0.0)
    if cl.n_beams == 0 or cl.n_beams > MAX_BEAMS or d.shape[0] < MIN_PER_BEAM * cl.n_beams:
        return np.zeros(d.shape[0], np.int64), np.array([float(np.median(elev))])
    return cl.beam, cl.elevations
