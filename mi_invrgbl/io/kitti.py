"""Readers for the KITTI layouts used as the project's interchange formats.

Frames and conventions used by everything returned here
-------------------------------------------------------
* Sensor frame ("velo"): x forward, y left, z up (the LiDAR's own frame).
* ``T_velo_to_cam`` (4x4): sensor frame -> *rectified* camera-0 frame
  (KITTI raw: ``R_rect_00 @ [R|T]``; odometry: ``Tr``, which already includes
  the rectification). Camera frames: x right, y down, z forward.
* ``P_rect_02`` (3x4): rectified camera-0 frame -> pixels of the left colour
  camera ``image_2``/``image_02``, integer pixel coordinates at pixel centres.
  ``K`` is its left 3x3 block; its last column holds camera 2's offset from
  camera 0 (``T_cam0_to_cam2``).
* ``poses`` (N, 4, 4): ``world_from_velo`` per frame, with the world frame =
  the first frame's sensor frame (so ``poses[0]`` is the identity, and x is
  the initial driving direction). This is also the frame of LiDAR odometry
  (:mod:`mi_invrgbl.io.odometry`), so all sources agree.
* ``image_size``: ``(width, height)``.

API
---
``read_kitti_raw(path, drive=None, check=True) -> Drive``
    KITTI raw: ``DATE/calib_cam_to_cam.txt``, ``DATE/calib_velo_to_cam.txt``,
    ``DATE/DRIVE_sync/image_02/data/*.png``,
    ``DATE/DRIVE_sync/velodyne_points/data/*.bin`` and, when present,
    ``oxts/data/*.txt`` (GPS/IMU -> poses, needs ``DATE/calib_imu_to_velo.txt``)
    and ``velodyne_points/timestamps.txt``. ``path`` may be the drive folder,
    the date folder or a folder holding one date folder.
``read_kitti_odometry(path, sequence=None, check=True) -> Drive``
    KITTI odometry: ``sequences/XX/{image_2/*.png, velodyne/*.bin, calib.txt,
    times.txt}`` and optional ``poses/XX.txt`` (camera-0 poses, 12 numbers per
    line). ``path`` is the dataset root or the sequence folder.
``write_kitti_odometry(root, sequence, ...)``
    Writes that layout; its pieces ``write_odometry_calib``,
    ``write_poses_file`` and ``write_times_file`` are what the synthetic
    street generator writes with, so one format definition serves both.
``read_tracking_labels(path, world_from_cam=None) -> dict[int, Track]``
    KITTI tracking ``label_02/XXXX.txt`` -> per-object, per-frame poses.
``oxts_to_poses(oxts) -> (N, 4, 4)``
    The standard KITTI GPS/IMU -> pose conversion (Mercator projection).
``check_calibration(drive)``
    Projects one sweep; raises if no point lands in the image.
``read_image(path, linear=False)``, ``srgb_to_linear(x)``
    Images as float32 RGB in [0, 1], optionally decoded to linear.

``Drive`` loads nothing heavy up front: ``drive.load_image(i)`` and
``drive.load_scan(i)`` read one frame on request.

Bad input raises :class:`mi_invrgbl.errors.UserError` naming the file and the
problem: missing folders/files/keys, malformed numbers, a calibration that
puts no LiDAR point into the image (``check=True`` projects the first sweep).
Images and scans whose frame numbers disagree are reduced to the frames both
have, with a ``UserWarning`` saying how many were dropped (safe: frames are
matched by their number, never by position); no common frame is an error.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
from pathlib import Path
import warnings

import numpy as np

from ..physics import colour
from ..errors import UserError
from .velodyne import read_velodyne, write_velodyne
from .range_image import points_to_image, CameraProjection

IMAGE_EXTS = (".png", ".jpg", ".jpeg")


# ----------------------------------------------------------------------------
# Small helpers
# ----------------------------------------------------------------------------

def _read_key_values(path: Path) -> dict:
    """``key: numbers`` lines -> dict of raw strings (parsed on demand, since
    KITTI calibration files also hold non-numeric entries like calib_time)."""
    if not path.is_file():
        raise UserError(f"{path}: calibration file not found")
    out = {}
    for line in path.read_text().splitlines():
        if ":" in line:
            key, value = line.split(":", 1)
            out[key.strip()] = value.strip()
    return out


def _numbers(calib: dict, key, path: Path, count: int) -> np.ndarray:
    keys = (key,) if isinstance(key, str) else tuple(key)
    for k in keys:
        if k in calib:
            try:
                values = np.array([float(v) for v in calib[k].split()], np.float64)
            except ValueError:
                raise UserError(f"{path}: entry {k!r} is not a list of numbers") from None
            if values.size != count:
                raise UserError(f"{path}: entry {k!r} has {values.size} numbers, "
                                f"expected {count}")
            if not np.all(np.isfinite(values)):
                raise UserError(f"{path}: entry {k!r} holds a NaN or infinite number")
            return values
    raise UserError(f"{path}: missing entry {keys[0]!r}")


def _check_rotation(R, where: str, tol: float = 1e-3) -> None:
    """A rigid transform's rotation: orthonormal with determinant +1."""
    R = np.asarray(R, np.float64)
    det = float(np.linalg.det(R))
    if abs(det - 1) > 10 * tol or np.abs(R.T @ R - np.eye(3)).max() > tol:
        raise UserError(f"{where} is not a rotation (determinant {det:.3g}"
                        f"{', singular' if abs(det) < 1e-9 else ''}); a rigid "
                        "transform has an orthonormal 3x3 block")


def _check_projection(P, path: Path, key: str) -> None:
    K = P[:, :3]
    if not (K[0, 0] > 0 and K[1, 1] > 0 and abs(np.linalg.det(K)) > 1e-12):
        raise UserError(f"{path}: entry {key!r} is not a camera projection (focal lengths "
                        f"{K[0, 0]:g}, {K[1, 1]:g}); expected fx, fy > 0")


def _homogeneous(R, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _frame_files(folder: Path, exts) -> dict:
    """Frame number -> file for every file with one of ``exts`` in ``folder``."""
    if not folder.is_dir():
        raise UserError(f"{folder}: folder not found")
    files = {}
    for f in folder.iterdir():
        if f.suffix.lower() in exts and f.stem.isdigit():
            files[int(f.stem)] = f
    if not files:
        raise UserError(f"{folder}: no {'/'.join(exts)} frames found")
    return files


def _match_frames(images: dict, scans: dict, image_dir: Path, scan_dir: Path):
    common = sorted(set(images) & set(scans))
    if not common:
        raise UserError(f"{image_dir} and {scan_dir} share no frame number")
    n_img, n_scan = len(images), len(scans)
    if len(common) != n_img or len(common) != n_scan:
        warnings.warn(
            f"{image_dir.parent}: {n_img} images but {n_scan} LiDAR sweeps; "
            f"using the {len(common)} frames that have both", UserWarning,
            stacklevel=3)
    return common


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] -> linear (IEC 61966-2-1)."""
    return colour.srgb_to_linear(x).astype(np.float32)


def read_image(path, linear: bool = False) -> np.ndarray:
    """Read an 8- or 16-bit image as (H, W, 3) float32 RGB in [0, 1];
    ``linear=True`` decodes sRGB to linear radiance units."""
    import cv2  # imported here: only image loading needs OpenCV

    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: image not found")
    img = cv2.imread(str(path), cv2.IMREAD_COLOR | cv2.IMREAD_ANYDEPTH)
    if img is None:
        raise UserError(f"{path}: not a readable image")
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    rgb = img[:, :, ::-1].astype(np.float32) / np.float32(scale)
    return srgb_to_linear(rgb) if linear else np.ascontiguousarray(rgb)


# ----------------------------------------------------------------------------
# The drive
# ----------------------------------------------------------------------------

@dataclass
class Drive:
    """One recording: calibration, per-frame files and (optional) poses.

    See the module docstring for frames and conventions.
    """
    root: Path
    layout: str                     # 'raw' or 'odometry'
    frames: list                    # frame numbers (int), ascending
    image_paths: list               # Path per frame
    scan_paths: list                # Path per frame
    K: np.ndarray                   # (3, 3)
    P_rect_02: np.ndarray           # (3, 4)
    T_velo_to_cam: np.ndarray       # (4, 4) sensor -> rectified camera 0
    image_size: tuple               # (width, height)
    poses: np.ndarray | None = None  # (N, 4, 4) world_from_velo
    pose_source: str | None = None  # 'oxts', 'poses file', 'odometry', None
    timestamps: np.ndarray | None = None  # (N,) seconds from the first frame
    calib_files: list = field(default_factory=list)

    def __len__(self):
        return len(self.frames)

    @property
    def T_cam0_to_cam2(self) -> np.ndarray:
        """Rectified camera 0 -> camera 2 (a pure translation K^-1 p)."""
        T = np.eye(4)
        T[:3, 3] = np.linalg.solve(self.K, self.P_rect_02[:, 3])
        return T

    @property
    def T_velo_to_cam2(self) -> np.ndarray:
        return self.T_cam0_to_cam2 @ self.T_velo_to_cam

    def camera_poses(self) -> np.ndarray | None:
        """world_from_cam2 per frame (the colour camera's poses), or None."""
        if self.poses is None:
            return None
        return self.poses @ np.linalg.inv(self.T_velo_to_cam2)

    def world_from_cam0(self) -> np.ndarray | None:
        """world_from_(rectified camera 0) per frame: the frame of KITTI
        tracking labels; pass it to :func:`read_tracking_labels`."""
        if self.poses is None:
            return None
        return self.poses @ np.linalg.inv(self.T_velo_to_cam)

    def load_image(self, i: int, linear: bool = False) -> np.ndarray:
        """Frame ``i`` (position, not number) as (H, W, 3) float32 RGB."""
        return read_image(self.image_paths[i], linear=linear)

    def load_scan(self, i: int, intensity_scale: float | None = None):
        """Frame ``i``'s sweep: (points (N, 3), intensity (N,))."""
        return read_velodyne(self.scan_paths[i], intensity_scale)

    def project_scan(self, i: int) -> CameraProjection:
        """Frame ``i``'s sweep projected into its image."""
        pts, inten = self.load_scan(i)
        return points_to_image(pts, inten, self.T_velo_to_cam, self.P_rect_02,
                               self.image_size)


def check_calibration(drive: Drive, frame: int = 0, min_fraction: float = 0.01):
    """Project one sweep; no point in the image means the calibration (or the
    sweep's frame) is wrong. Returns the fraction of points in the image."""
    pts, inten = drive.load_scan(frame)
    if pts.shape[0] == 0:
        return 0.0
    proj = points_to_image(pts, inten, drive.T_velo_to_cam, drive.P_rect_02,
                           drive.image_size)
    n_in = int(proj.in_image.sum())
    files = ", ".join(str(f) for f in drive.calib_files)
    if n_in == 0:
        raise UserError(
            f"{files}: this calibration puts none of the {pts.shape[0]} LiDAR "
            f"points of {drive.scan_paths[frame]} into the "
            f"{drive.image_size[0]}x{drive.image_size[1]} image; check the "
            "velodyne-to-camera transform and the projection matrix")
    fraction = n_in / pts.shape[0]
    if fraction < min_fraction:
        warnings.warn(f"{files}: only {100 * fraction:.2f}% of the LiDAR points "
                      "land in the image; the calibration may be wrong",
                      UserWarning, stacklevel=2)
    return fraction


# ----------------------------------------------------------------------------
# KITTI raw
# ----------------------------------------------------------------------------

def _locate_raw_drive(path: Path, drive: str | None) -> Path:
    if (path / "image_02").is_dir() or (path / "velodyne_points").is_dir():
        return path
    candidates = sorted({p.parent for p in path.glob("*/image_02")}
                        | {p.parent for p in path.glob("*/*/image_02")})
    if drive is not None:
        candidates = [c for c in candidates if c.name == drive or c.name.startswith(drive)]
    if not candidates:
        raise UserError(f"{path}: no KITTI raw drive found (expected "
                        "DATE/DRIVE_sync/image_02 and velodyne_points)")
    if len(candidates) > 1:
        names = ", ".join(c.name for c in candidates)
        raise UserError(f"{path}: several drives ({names}); choose one with drive=")
    return candidates[0]


def _parse_kitti_time(line: str) -> float:
    """'2011-09-26 13:02:25.964389445' -> seconds since midnight."""
    clock = line.strip().split(" ")[-1]
    h, m, s = clock.split(":")
    return int(h) * 3600 + int(m) * 60 + float(s)


def _read_timestamps(path: Path, frames) -> np.ndarray | None:
    if not path.is_file():
        return None
    lines = [l for l in path.read_text().splitlines() if l.strip()]
    if max(frames) >= len(lines):
        warnings.warn(f"{path}: {len(lines)} timestamps for frame numbers up to "
                      f"{max(frames)}; timestamps ignored", UserWarning, stacklevel=3)
        return None
    try:
        t = np.array([_parse_kitti_time(lines[f]) for f in frames])
    except ValueError:
        raise UserError(f"{path}: unreadable timestamp line") from None
    return t - t[0]


def oxts_to_poses(oxts: np.ndarray) -> np.ndarray:
    """KITTI OXTS records (N, >=6: lat, lon, alt, roll, pitch, yaw) -> IMU
    poses (N, 4, 4) relative to the first record.

    The standard conversion: a Mercator projection whose scale is fixed by
    the first latitude (x east, y north, z altitude) and the rotation
    Rz(yaw) Ry(pitch) Rx(roll).
    """
    oxts = np.asarray(oxts, np.float64)
    earth_radius = 6378137.0
    scale = math.cos(math.radians(oxts[0, 0]))
    poses = np.empty((oxts.shape[0], 4, 4))
    for k, (lat, lon, alt, roll, pitch, yaw) in enumerate(oxts[:, :6]):
        tx = scale * math.radians(lon) * earth_radius
        ty = scale * earth_radius * math.log(math.tan(math.radians(90.0 + lat) / 2.0))
        cr, sr = math.cos(roll), math.sin(roll)
        cp, sp = math.cos(pitch), math.sin(pitch)
        cy, sy = math.cos(yaw), math.sin(yaw)
        Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
        Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
        Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
        poses[k] = _homogeneous(Rz @ Ry @ Rx, [tx, ty, alt])
    return np.linalg.inv(poses[0]) @ poses


def _read_oxts(folder: Path, frames) -> np.ndarray:
    rows = []
    for f in frames:
        path = folder / f"{f:010d}.txt"
        if not path.is_file():
            raise UserError(f"{path}: GPS/IMU record missing for frame {f} "
                            "(remove the oxts folder to estimate poses by LiDAR odometry)")
        try:
            values = [float(v) for v in path.read_text().split()]
        except ValueError:
            raise UserError(f"{path}: not a list of numbers") from None
        if len(values) < 6:
            raise UserError(f"{path}: {len(values)} values, expected 30")
        if not np.all(np.isfinite(values[:6])):
            raise UserError(f"{path}: position or orientation holds a NaN or infinite value")
        rows.append(values[:6])
    return np.array(rows)


def read_kitti_raw(path, drive: str | None = None, check: bool = True) -> Drive:
    """Read a KITTI raw drive (see the module docstring)."""
    drive_dir = _locate_raw_drive(Path(path), drive)
    date_dir = drive_dir.parent

    cam_file = date_dir / "calib_cam_to_cam.txt"
    velo_file = date_dir / "calib_velo_to_cam.txt"
    cam = _read_key_values(cam_file)
    velo = _read_key_values(velo_file)
    R_rect = np.eye(4)
    R_rect[:3, :3] = _numbers(cam, "R_rect_00", cam_file, 9).reshape(3, 3)
    _check_rotation(R_rect[:3, :3], f"{cam_file}: entry 'R_rect_00'")
    P2 = _numbers(cam, "P_rect_02", cam_file, 12).reshape(3, 4)
    _check_projection(P2, cam_file, "P_rect_02")
    R = _numbers(velo, "R", velo_file, 9).reshape(3, 3)
    _check_rotation(R, f"{velo_file}: entry 'R'")
    t = _numbers(velo, "T", velo_file, 3)
    T_velo_to_cam = R_rect @ _homogeneous(R, t)

    image_dir = drive_dir / "image_02" / "data"
    scan_dir = drive_dir / "velodyne_points" / "data"
    images = _frame_files(image_dir, IMAGE_EXTS)
    scans = _frame_files(scan_dir, (".bin",))
    frames = _match_frames(images, scans, image_dir, scan_dir)

    if "S_rect_02" in cam:
        w, h = _numbers(cam, "S_rect_02", cam_file, 2)
        size = (int(round(w)), int(round(h)))
    else:
        size = _image_size(images[frames[0]])

    poses, source, calib_files = None, None, [cam_file, velo_file]
    oxts_dir = drive_dir / "oxts" / "data"
    if oxts_dir.is_dir():
        imu_file = date_dir / "calib_imu_to_velo.txt"
        imu = _read_key_values(imu_file)
        R_imu = _numbers(imu, "R", imu_file, 9).reshape(3, 3)
        _check_rotation(R_imu, f"{imu_file}: entry 'R'")
        T_imu_to_velo = _homogeneous(R_imu, _numbers(imu, "T", imu_file, 3))
        imu_poses = oxts_to_poses(_read_oxts(oxts_dir, frames))
        # world(first velo) <- velo_i = velo<-imu . imu0<-imu_i . imu<-velo
        poses = T_imu_to_velo @ imu_poses @ np.linalg.inv(T_imu_to_velo)
        source = "oxts"
        calib_files.append(imu_file)

    timestamps = _read_timestamps(drive_dir / "velodyne_points" / "timestamps.txt", frames)

    result = Drive(root=drive_dir, layout="raw", frames=frames,
                   image_paths=[images[f] for f in frames],
                   scan_paths=[scans[f] for f in frames],
                   K=P2[:, :3].copy(), P_rect_02=P2, T_velo_to_cam=T_velo_to_cam,
                   image_size=size, poses=poses, pose_source=source,
                   timestamps=timestamps, calib_files=calib_files)
    if check:
        check_calibration(result)
    return result


def _image_size(path: Path):
    img = read_image(path)
    return (img.shape[1], img.shape[0])


# ----------------------------------------------------------------------------
# KITTI odometry
# ----------------------------------------------------------------------------

def _locate_sequence(path: Path, sequence: str | None):
    if (path / "calib.txt").is_file() or (path / "velodyne").is_dir():
        seq_dir = path
        root = path.parent.parent
    else:
        seqs = path / "sequences"
        if not seqs.is_dir():
            raise UserError(f"{path}: no 'sequences' folder (KITTI odometry layout)")
        if sequence is None:
            found = sorted(p.name for p in seqs.iterdir() if p.is_dir())
            if len(found) != 1:
                raise UserError(f"{seqs}: {len(found)} sequences ({', '.join(found)}); "
                                "choose one with sequence=")
            sequence = found[0]
        seq_dir = seqs / sequence
        root = path
        if not seq_dir.is_dir():
            raise UserError(f"{seq_dir}: sequence not found")
    return root, seq_dir


def read_kitti_odometry(path, sequence: str | None = None, check: bool = True) -> Drive:
    """Read one KITTI odometry sequence (see the module docstring)."""
    root, seq_dir = _locate_sequence(Path(path), sequence)
    calib_file = seq_dir / "calib.txt"
    calib = _read_key_values(calib_file)
    P2 = _numbers(calib, "P2", calib_file, 12).reshape(3, 4)
    _check_projection(P2, calib_file, "P2")
    Tr = np.vstack([_numbers(calib, ("Tr", "Tr_velo_to_cam"), calib_file, 12).reshape(3, 4),
                    [0, 0, 0, 1]])
    _check_rotation(Tr[:3, :3], f"{calib_file}: entry 'Tr'")

    image_dir, scan_dir = seq_dir / "image_2", seq_dir / "velodyne"
    images = _frame_files(image_dir, IMAGE_EXTS)
    scans = _frame_files(scan_dir, (".bin",))
    frames = _match_frames(images, scans, image_dir, scan_dir)

    timestamps = None
    times_file = seq_dir / "times.txt"
    if times_file.is_file():
        try:
            times = np.loadtxt(times_file, ndmin=1)
        except ValueError:
            raise UserError(f"{times_file}: not one number per line") from None
        if times.size <= frames[-1]:
            raise UserError(f"{times_file}: {times.size} times for frame numbers up "
                            f"to {frames[-1]}")
        bad = np.flatnonzero(~np.isfinite(times))
        if bad.size:
            raise UserError(f"{times_file}: line {bad[0] + 1} is not a finite number "
                            f"({times[bad[0]]})")
        timestamps = times[frames] - times[frames[0]]

    poses, source = None, None
    pose_file = root / "poses" / f"{seq_dir.name}.txt"
    if pose_file.is_file():
        try:
            cam_poses = np.loadtxt(pose_file, ndmin=2)
        except ValueError:
            raise UserError(f"{pose_file}: not 12 numbers per line") from None
        if cam_poses.shape[1] != 12:
            raise UserError(f"{pose_file}: {cam_poses.shape[1]} numbers per line, expected 12")
        if cam_poses.shape[0] <= frames[-1]:
            raise UserError(f"{pose_file}: {cam_poses.shape[0]} poses for frame "
                            f"numbers up to {frames[-1]}")
        bad = np.flatnonzero(~np.all(np.isfinite(cam_poses), axis=1))
        if bad.size:
            raise UserError(f"{pose_file}: line {bad[0] + 1} holds a NaN or infinite number")
        for f in frames:
            _check_rotation(cam_poses[f].reshape(3, 4)[:, :3], f"{pose_file}: line {f + 1}")
        C = np.tile(np.eye(4), (len(frames), 1, 1))
        C[:, :3, :] = cam_poses[frames].reshape(-1, 3, 4)
        # Camera-0 poses -> sensor poses with the first sensor frame as world.
        poses = np.linalg.inv(Tr) @ np.linalg.inv(C[0]) @ C @ Tr
        source = "poses file"

    size = _image_size(images[frames[0]])
    result = Drive(root=seq_dir, layout="odometry", frames=frames,
                   image_paths=[images[f] for f in frames],
                   scan_paths=[scans[f] for f in frames],
                   K=P2[:, :3].copy(), P_rect_02=P2, T_velo_to_cam=Tr,
                   image_size=size, poses=poses, pose_source=source,
                   timestamps=timestamps, calib_files=[calib_file])
    if check:
        check_calibration(result)
    return result


def _fmt_numbers(a) -> str:
    return " ".join(f"{v:.12e}" for v in np.ravel(a))


def write_odometry_calib(path, P2, T_velo_to_cam, P0=None) -> None:
    """KITTI odometry ``calib.txt``: ``P0..P3`` (3x4; P1 = P0, P3 = P2) and
    ``Tr`` (velodyne -> camera 0, 3x4). ``P0`` defaults to ``P2`` without its
    camera offset."""
    P2 = np.asarray(P2, np.float64).reshape(3, 4)
    Tr = np.asarray(T_velo_to_cam, np.float64).reshape(-1)[:12].reshape(3, 4)
    if P0 is None:
        P0 = np.hstack([P2[:, :3], np.zeros((3, 1))])
    lines = [f"P0: {_fmt_numbers(P0)}", f"P1: {_fmt_numbers(P0)}", f"P2: {_fmt_numbers(P2)}",
             f"P3: {_fmt_numbers(P2)}", f"Tr: {_fmt_numbers(Tr)}"]
    Path(path).write_text("\n".join(lines) + "\n")


def write_poses_file(path, cam_poses) -> None:
    """KITTI ``poses/XX.txt``: one row of 12 numbers (3x4, row-major) per
    camera-0 pose."""
    cam = np.asarray(cam_poses, np.float64).reshape(-1, 4, 4)
    np.savetxt(path, cam[:, :3, :].reshape(len(cam), 12), fmt="%.12e")


def write_times_file(path, times) -> None:
    """KITTI ``times.txt``: one time in seconds per line."""
    np.savetxt(path, np.asarray(times, np.float64).reshape(-1), fmt="%.6e")


def write_kitti_odometry(root, sequence: str, P2, T_velo_to_cam, images, scans,
                         poses=None, times=None, P0=None):
    """Write a sequence in the KITTI odometry layout under ``root``.

    ``images``: (H, W, 3) float RGB in [0, 1] (sRGB-encoded, written as 8-bit
    PNG); ``scans``: (points (N, 3), intensity (N,)) pairs; ``poses``:
    world_from_velo (N, 4, 4), written as camera-0 poses as KITTI does;
    ``times`` in seconds (default 0.1 s apart). ``P0`` defaults to ``P2``
    without its camera offset. Returns the sequence folder.
    """
    import cv2

    root = Path(root)
    seq_dir = root / "sequences" / sequence
    (seq_dir / "image_2").mkdir(parents=True, exist_ok=True)
    (seq_dir / "velodyne").mkdir(parents=True, exist_ok=True)
    Tr = np.asarray(T_velo_to_cam, np.float64).reshape(4, 4)
    write_odometry_calib(seq_dir / "calib.txt", P2, Tr, P0)

    n = len(scans)
    if len(images) != n:
        raise ValueError("images and scans differ in number")
    for k in range(n):
        rgb = np.clip(np.asarray(images[k], np.float32), 0, 1)
        bgr = (rgb[:, :, ::-1] * 255.0 + 0.5).astype(np.uint8)
        cv2.imwrite(str(seq_dir / "image_2" / f"{k:06d}.png"), bgr)
        write_velodyne(seq_dir / "velodyne" / f"{k:06d}.bin", *scans[k])
    times = np.arange(n) * 0.1 if times is None else np.asarray(times, np.float64)
    write_times_file(seq_dir / "times.txt", times)
    if poses is not None:
        poses = np.asarray(poses, np.float64)
        # world(cam0 of frame 0) <- cam0_i = Tr . world_from_velo_i . Tr^-1
        cam = Tr @ np.linalg.inv(poses[0]) @ poses @ np.linalg.inv(Tr)
        (root / "poses").mkdir(parents=True, exist_ok=True)
        write_poses_file(root / "poses" / f"{sequence}.txt", cam)
    return seq_dir


# ----------------------------------------------------------------------------
# KITTI tracking labels
# ----------------------------------------------------------------------------

@dataclass
class Track:
    """One labelled object over the frames it appears in.

    Object frame (KITTI's box convention): origin at the bottom centre of the
    3D box, x along the object's length (its heading), y down (the box spans
    y in [-h, 0]), z along its width. ``poses_cam`` maps it to the rectified
    camera-0 frame of each frame; ``poses_world`` to the world frame when
    camera poses were given.
    """
    track_id: int
    type: str
    frames: np.ndarray        # (M,) int frame numbers
    dimensions: np.ndarray    # (M, 3) height, width, length in metres
    poses_cam: np.ndarray     # (M, 4, 4)
    poses_world: np.ndarray | None
    bbox: np.ndarray          # (M, 4) left, top, right, bottom in pixels
    truncated: np.ndarray     # (M,)
    occluded: np.ndarray      # (M,) int
    alpha: np.ndarray         # (M,)

    @property
    def size(self) -> np.ndarray:
        """Median (height, width, length) over the track."""
        return np.median(self.dimensions, axis=0)


def object_pose(location, rotation_y) -> np.ndarray:
    """KITTI box location (bottom centre, camera coords) and rotation about
    the camera's y axis -> camera_from_object (4x4)."""
    c, s = math.cos(rotation_y), math.sin(rotation_y)
    R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return _homogeneous(R, location)


def read_tracking_labels(path, world_from_cam=None, skip_dontcare: bool = True) -> dict:
    """Read a KITTI tracking label file -> {track_id: Track}.

    Each line: frame, track_id, type, truncated, occluded, alpha, bbox (4),
    dimensions (h, w, l), location (x, y, z), rotation_y [, score].
    ``world_from_cam``: poses of the rectified camera 0 per frame, either a
    dict {frame number: 4x4} or an (N, 4, 4) array indexed by frame number
    (e.g. ``dict(zip(drive.frames, drive.world_from_cam0()))``).
    ``DontCare`` regions (track id -1) carry no object and are skipped.
    """
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: label file not found")
    rows = {}
    for n, line in enumerate(path.read_text().splitlines(), start=1):
        fields = line.split()
        if not fields:
            continue
        if len(fields) not in (17, 18):
            raise UserError(f"{path}, line {n}: {len(fields)} fields, expected 17 "
                            "(frame, id, type, truncated, occluded, alpha, bbox, "
                            "h w l, x y z, rotation_y)")
        try:
            frame, tid = int(fields[0]), int(fields[1])
            nums = [float(v) for v in fields[3:17]]
        except ValueError:
            raise UserError(f"{path}, line {n}: malformed number") from None
        kind = fields[2]
        if skip_dontcare and (kind == "DontCare" or tid < 0):
            continue
        rows.setdefault(tid, []).append((frame, kind, nums))

    if world_from_cam is not None and not isinstance(world_from_cam, dict):
        world_from_cam = dict(enumerate(np.asarray(world_from_cam, np.float64)))

    tracks = {}
    for tid, entries in sorted(rows.items()):
        entries.sort(key=lambda e: e[0])
        frames = np.array([e[0] for e in entries])
        nums = np.array([e[2] for e in entries])
        poses_cam = np.stack([object_pose(v[10:13], v[13]) for v in nums])
        poses_world = None
        if world_from_cam is not None:
            missing = [f for f in frames if f not in world_from_cam]
            if missing:
                raise UserError(f"{path}: object {tid} is labelled in frame "
                                f"{missing[0]}, which has no camera pose")
            poses_world = np.stack([world_from_cam[f] for f in frames]) @ poses_cam
        # nums: truncated, occluded, alpha, bbox(4), h w l, x y z, rotation_y
        tracks[tid] = Track(
            track_id=tid, type=entries[0][1], frames=frames,
            dimensions=nums[:, 7:10], poses_cam=poses_cam, poses_world=poses_world,
            bbox=nums[:, 3:7], truncated=nums[:, 0], occluded=nums[:, 1].astype(int),
            alpha=nums[:, 2])
    return tracks
