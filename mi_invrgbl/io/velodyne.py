"""Read LiDAR sweeps stored as KITTI ``.bin`` files.

A KITTI sweep is a flat array of little-endian float32 records ``x, y, z,
reflectance`` (16 bytes per point) in the sensor frame: x forward, y left, z up.

API::

    points, intensity = read_velodyne(path)            # (N,3) float32, (N,) float32 in [0,1]
    points, intensity = read_velodyne(path, intensity_scale=1/255)

Checks and their outcome:

* missing file, or a size that is not a multiple of 16 bytes -> ``UserError``
  naming the file (a truncated copy or a different record layout; reading on
  would silently shift every later point's fields);
* points with a NaN/inf coordinate or intensity -> dropped, one ``UserWarning``
  with the count (some converters write them for ray drops);
* an empty sweep -> returned as empty arrays with a ``UserWarning`` (a sensor
  can legitimately return nothing, e.g. when blocked; callers decide);
* points exactly at the sensor's origin are not returns (some converters
  write zeros for ray drops): dropped with a ``UserWarning``; a sweep whose
  points *all* lie there is a zero-filled (corrupt) file -> ``UserError``.

Intensity normalisation: the project works with intensities in [0, 1].
KITTI's HDL-64 reflectance is already in [0, 0.99], so by default values in
[0, 1] are kept unchanged. Sensors that report 8-bit intensities (0..255) are
detected by their maximum and divided by 255. Anything else (raw return
strength, 16-bit counts) has no universal scale: pass ``intensity_scale``
explicitly, otherwise a ``UserError`` says so. Values are finally clipped to
[0, 1]; the physical meaning (range-compensated or not) is the sensor's and is
handled by the LiDAR response model, not here.
"""

from __future__ import annotations

import os
import warnings

import numpy as np

from ..errors import UserError

#: bytes per point record: four float32 values
RECORD_BYTES = 16


def read_velodyne(path, intensity_scale: float | None = None):
    """Read one ``.bin`` sweep.

    Parameters
    ----------
    path : str or path-like
        The ``.bin`` file.
    intensity_scale : float, optional
        Factor applied to the stored intensity before clipping to [0, 1].
        ``None`` (default) keeps values already in [0, 1] and divides 8-bit
        values (max in (1, 255]) by 255.

    Returns
    -------
    points : (N, 3) float32 array, sensor frame, metres
    intensity : (N,) float32 array in [0, 1]
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise UserError(f"{path}: LiDAR sweep not found")
    size = os.path.getsize(path)
    if size % RECORD_BYTES != 0:
        raise UserError(
            f"{path}: size {size} bytes is not a multiple of {RECORD_BYTES} "
            "(expected float32 x, y, z, reflectance per point); the file is "
            "truncated or not a KITTI Velodyne sweep")
    data = np.fromfile(path, dtype="<f4").reshape(-1, 4)

    if data.shape[0] == 0:
        warnings.warn(f"{path}: empty LiDAR sweep (0 points)", UserWarning,
                      stacklevel=2)
        return np.zeros((0, 3), np.float32), np.zeros(0, np.float32)

    finite = np.isfinite(data).all(axis=1)
    n_bad = int(data.shape[0] - finite.sum())
    if n_bad:
        warnings.warn(f"{path}: dropped {n_bad} of {data.shape[0]} points with "
                      "NaN/inf values", UserWarning, stacklevel=2)
        data = data[finite]
        if data.shape[0] == 0:
            warnings.warn(f"{path}: no finite points left (empty sweep)",
                          UserWarning, stacklevel=2)

    at_origin = np.all(data[:, :3] == 0, axis=1)
    if at_origin.any():
        if at_origin.all():
            raise UserError(f"{path}: all {data.shape[0]} points lie at the sensor's origin "
                            "(0, 0, 0); the sweep is zero-filled or corrupt")
        warnings.warn(f"{path}: dropped {int(at_origin.sum())} of {data.shape[0]} points at "
                      "the sensor's origin (not returns)", UserWarning, stacklevel=2)
        data = data[~at_origin]

    points = np.ascontiguousarray(data[:, :3])
    intensity = normalize_intensity(data[:, 3], intensity_scale, path)
    return points, intensity


def normalize_intensity(values, scale: float | None = None, source: str = "intensity"):
    """Map stored intensities to [0, 1] (see the module docstring for the rule)."""
    values = np.asarray(values, np.float32)
    if scale is None:
        vmax = float(values.max()) if values.size else 0.0
        if vmax <= 1.0:
            scale = 1.0
        elif vmax <= 255.0:
            scale = 1.0 / 255.0
        else:
            raise UserError(
                f"{source}: intensities reach {vmax:g}, which is neither KITTI's "
                "[0, 1] nor 8-bit; pass intensity_scale for this sensor")
    return np.clip(values * np.float32(scale), 0.0, 1.0).astype(np.float32)


def write_velodyne(path, points, intensity):
    """Write a sweep in the KITTI ``.bin`` layout (used by tests and the
    synthetic-scene generator so that one reader serves both)."""
    points = np.asarray(points, np.float32).reshape(-1, 3)
    intensity = np.asarray(intensity, np.float32).reshape(-1, 1)
    if points.shape[0] != intensity.shape[0]:
        raise ValueError("points and intensity differ in length")
    np.hstack([points, intensity]).astype("<f4").tofile(os.fspath(path))
