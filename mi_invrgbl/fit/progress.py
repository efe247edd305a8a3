"""Progress bar with ETA, speed-versus-error log, peak memory."""

from __future__ import annotations

import csv
import resource
import sys
import time

from ..outdir import atomic_write


def peak_rss_mb() -> float:
    """Peak resident memory of this process in MiB (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


class ProgressBar:
    """One-line progress: ``[stage] 120/300 |####    | loss 1.2e-2  ETA 31 s``."""

    def __init__(self, label, total, stream=None, start_at=0):
        self.label, self.total = label, max(int(total), 1)
        self.stream = stream or sys.stdout
        self.t0 = time.perf_counter()
        self.start_at = start_at
        self.tty = getattr(self.stream, "isatty", lambda: False)()
        self._last = 0.0

    def update(self, it, text=""):
        now = time.perf_counter()
        done = it - self.start_at
        elapsed = now - self.t0
        eta = elapsed / done * (self.total - it) if done > 0 else float("nan")
        # Print every update on a terminal, at most every 5 s into a log file.
        if not self.tty and now - self._last < 5.0 and it < self.total:
            return
        self._last = now
        width = 24
        filled = int(width * it / self.total)
        line = "[%s] %5d/%d |%s%s| %s  %.0f s, ETA %s" % (
            self.label, it, self.total, "#" * filled, " " * (width - filled), text, elapsed,
            "%.0f s" % eta if eta == eta else "?")
        end = "\r" if self.tty and it < self.total else "\n"
        self.stream.write(line + end)
        self.stream.flush()

    def close(self):
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()


class SpeedErrorLog:
    """Rows of (wall time, stage, iteration, losses, held-out errors) in a CSV."""

    FIELDS = ["wall_s", "stage", "iteration", "loss", "loss_rgb", "loss_lidar", "loss_range",
              "loss_drop", "loss_sky", "loss_rgb2lidar", "loss_lidar2rgb", "loss_prior", "loss_anchor",
              "heldout_psnr", "heldout_intensity_rmse", "peak_rss_mb"]

    def __init__(self, path, rows=None):
        self.path = path
        self.rows = list(rows or [])

    def add(self, **row):
        row = {k: row.get(k, "") for k in self.FIELDS}
        self.rows.append(row)
        self.write()

    def write(self):
        def write(tmp):
            with open(tmp, "w", newline="") as f:
                w = csv.DictWriter(f, fieldnames=self.FIELDS)
                w.writeheader()
                for r in self.rows:
                    w.writerow(r)
        atomic_write(self.path, write)


def plot_error_vs_time(rows, path, key="heldout_psnr", key2="heldout_intensity_rmse"):
    """A small PNG plot (OpenCV drawing) of held-out error against wall time."""
    import numpy as np
    import cv2
    def number(v):
        try:
            v = float(v)
        except (TypeError, ValueError):
            return None
        return v if np.isfinite(v) else None
    # Rows without a finite value (NaN: no held-out frame, all weights 0) are not drawn.
    pts = [(float(r["wall_s"]), number(r.get(key)), number(r.get(key2))) for r in rows
           if number(r.get(key)) is not None and number(r.get("wall_s")) is not None]
    W, H, m = 640, 360, 50
    img = np.full((H, W, 3), 255, np.uint8)
    if len(pts) >= 1:
        t = np.array([p[0] for p in pts])
        series = [(key, np.array([float(p[1]) for p in pts]), (200, 60, 30))]
        if all(p[2] is not None for p in pts):
            series.append((key2, np.array([float(p[2]) for p in pts]), (30, 120, 220)))
        tmax = max(t.max(), 1e-6)
        cv2.line(img, (m, H - m), (W - m, H - m), (0, 0, 0), 1)
        cv2.line(img, (m, m), (m, H - m), (0, 0, 0), 1)
        cv2.putText(img, "wall time [s] (0 .. %.0f)" % tmax, (W // 2 - 90, H - 15),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1)
        for k, (name, v, colour) in enumerate(series):
            lo, hi = float(np.min(v)), float(np.max(v))
            if hi - lo < 1e-9:
                lo, hi = lo - 1, hi + 1
            xy = [(int(m + (W - 2 * m) * ti / tmax), int(H - m - (H - 2 * m) * (vi - lo) / (hi - lo)))
                  for ti, vi in zip(t, v)]
            for a, b in zip(xy[:-1], xy[1:]):
                cv2.line(img, a, b, colour, 2)
            for p in xy:
                cv2.circle(img, p, 3, colour, -1)
            cv2.putText(img, "%s (%.3g .. %.3g)" % (name, lo, hi), (m + 5, 20 + 18 * k),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1)
    cv2.imwrite(path, img)
