"""File writers (and the matching readers the tests use): EXR, PNG, KITTI text and binary.

EXR and PNG go through ``mi.Bitmap``. Multi-channel EXRs carry named
channels; note that OpenEXR stores channels sorted by name, so read them by
name (:func:`read_exr`), never by position.
"""

from __future__ import annotations

import numpy as np
import mitsuba as mi


def write_exr(path: str, array: np.ndarray, channels=None) -> None:
    """Write float32 data (H, W) or (H, W, C) to an EXR, with channel names if given."""
    data = np.ascontiguousarray(np.asarray(array, dtype=np.float32))
    if data.ndim == 2:
        data = data[..., None]
    if channels is None:
        fmt = {1: mi.Bitmap.PixelFormat.Y, 3: mi.Bitmap.PixelFormat.RGB}[data.shape[2]]
        bitmap = mi.Bitmap(data, pixel_format=fmt)
    else:
        bitmap = mi.Bitmap(data, pixel_format=mi.Bitmap.PixelFormat.MultiChannel,
                           channel_names=list(channels))
    bitmap.write(path)


def read_exr(path: str) -> dict:
    """Channels of an EXR by name: ``{'R': (H, W), ...}``, ``{'Y': ...}`` or the given names."""
    bitmap = mi.Bitmap(path)
    data = np.array(bitmap, dtype=np.float32)
    if data.ndim == 2:
        data = data[..., None]
    names = [bitmap.struct_()[i].name for i in range(data.shape[2])]
    return {name: data[..., i] for i, name in enumerate(names)}


def read_exr_rgb(path: str) -> np.ndarray:
    ch = read_exr(path)
    return np.stack([ch["R"], ch["G"], ch["B"]], axis=-1)


def write_png_srgb(path: str, linear_rgb: np.ndarray) -> None:
    """Linear RGB -> 8-bit sRGB PNG (values clipped to [0, 1])."""
    data = np.clip(np.asarray(linear_rgb, dtype=np.float32), 0.0, 1.0)
    bitmap = mi.Bitmap(np.ascontiguousarray(data), pixel_format=mi.Bitmap.PixelFormat.RGB)
    bitmap.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, srgb_gamma=True).write(path)


def write_png_linear_grey(path: str, grey: np.ndarray) -> None:
    """Data texture in [0, 1] as an 8-bit grey PNG without gamma (load with ``raw=True``)."""
    data = np.round(np.clip(grey, 0.0, 1.0) * 255.0).astype(np.uint8)
    bitmap = mi.Bitmap(np.ascontiguousarray(data[..., None]), pixel_format=mi.Bitmap.PixelFormat.Y)
    bitmap.set_srgb_gamma(False)
    bitmap.write(path)


def write_calib(path: str, K: np.ndarray, cam_from_velo: np.ndarray) -> None:
    """KITTI odometry calib.txt: P0..P3 (3x4) and Tr (velodyne -> camera 0, 3x4).

    There is a single rendered camera, so P0..P3 are all ``K [I | 0]``:
    image_2 is camera 0's image and no baseline offset applies. Written by
    the reader's own writer (:func:`mi_invrgbl.io.kitti.write_odometry_calib`).
    """
    from ..io.kitti import write_odometry_calib
    P = np.hstack([np.asarray(K, np.float64), np.zeros((3, 1))])
    Tr = np.eye(4)
    Tr[:3, :4] = np.asarray(cam_from_velo, np.float64)[:3, :4]
    write_odometry_calib(path, P, Tr, P0=P)


def write_poses(path: str, poses: np.ndarray) -> None:
    """KITTI poses file: one row of 12 numbers (3x4, row-major) per frame
    (:func:`mi_invrgbl.io.kitti.write_poses_file`)."""
    from ..io.kitti import write_poses_file
    poses = np.asarray(poses, np.float64)
    full = np.tile(np.eye(4), (len(poses), 1, 1))
    full[:, :3, :4] = poses[:, :3, :4]
    write_poses_file(path, full)


def read_poses(path: str) -> np.ndarray:
    rows = np.loadtxt(path, ndmin=2).reshape(-1, 3, 4)
    out = np.tile(np.eye(4), (len(rows), 1, 1))
    out[:, :3, :4] = rows
    return out


def read_calib(path: str) -> dict:
    out = {}
    with open(path) as f:
        for line in f:
            if ":" in line:
                key, values = line.split(":", 1)
                out[key.strip()] = np.array([float(v) for v in values.split()]).reshape(3, 4)
    return out


def write_times(path: str, times) -> None:
    """KITTI times.txt (:func:`mi_invrgbl.io.kitti.write_times_file`)."""
    from ..io.kitti import write_times_file
    write_times_file(path, times)


def write_velodyne(path: str, points: np.ndarray) -> None:
    """KITTI .bin: float32 (x, y, z, intensity) per point, sensor frame.

    Delegates to the reader's own writer so that one format definition serves both.
    """
    from ..io.velodyne import write_velodyne as write_bin
    points = np.asarray(points, np.float32).reshape(-1, 4)
    write_bin(path, points[:, :3], points[:, 3])


def read_velodyne(path: str) -> np.ndarray:
    return np.fromfile(path, dtype=np.float32).reshape(-1, 4)


def write_tracking_labels(path: str, rows) -> None:
    """KITTI tracking labels, one object per line, frames in order.

    Each row is a dict with frame, track_id, type, truncated, occluded, alpha,
    bbox (left, top, right, bottom), dimensions (h, w, l), location (x, y, z of
    the bottom centre, camera coordinates) and rotation_y.
    """
    with open(path, "w") as f:
        for r in rows:
            f.write("%d %d %s %d %d %.6f %.2f %.2f %.2f %.2f %.6f %.6f %.6f %.6f %.6f %.6f %.6f\n"
                    % ((r["frame"], r["track_id"], r["type"], r["truncated"], r["occluded"],
                        r["alpha"]) + tuple(r["bbox"]) + tuple(r["dimensions"])
                       + tuple(r["location"]) + (r["rotation_y"],)))


def read_tracking_labels(path: str) -> list:
    rows = []
    with open(path) as f:
        for line in f:
            v = line.split()
            if not v:
                continue
            rows.append({"frame": int(v[0]), "track_id": int(v[1]), "type": v[2],
                         "truncated": int(v[3]), "occluded": int(v[4]), "alpha": float(v[5]),
                         "bbox": [float(x) for x in v[6:10]],
                         "dimensions": [float(x) for x in v[10:13]],
                         "location": [float(x) for x in v[13:16]],
                         "rotation_y": float(v[16])})
    return rows
