"""Observations of an imported scene, at the resolution the fit works at.

Camera images are read as 8-bit sRGB, linearised and resized (area filter) to
``fit_width``; the rays of a frame are the sensor's rays through the pixel
centres of that grid, so one traced hit list per frame serves every
iteration while geometry is frozen. LiDAR scans are the range images written
by ``import`` (one pixel per beam of the frame's ``lidar`` sensor); columns may
be thinned by ``lidar_stride`` for speed.

Masks (a frame record's ``masks``: ``camera`` over the image, ``lidar`` over
the range image; 8-bit, 255 = exclude, written by ``import`` for moving things
it could not model) mark pixels and beams no loss, validation score or
initialisation may use. A camera mask is resized to the fit's grid with any
coverage kept (a masked pixel stays masked); a LiDAR mask is thinned with the
scan's columns. :meth:`Masked.valid` is the one answer to "which pixels of
this frame count".
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import cv2
import drjit as dr
import mitsuba as mi

from ..errors import UserError
from ..io.images import read_exr, read_mask
from ..io.kitti import srgb_to_linear
from ..scene.frames import Frames
from .render import gather_rays
from ..physics.host_arrays import jit_array


class Masked:
    """Which pixels (camera) or kept beams (LiDAR) of an observation count.

    ``excluded`` is ``None`` (nothing masked) or a bool array over the
    observation's grid, True where a mask leaves the pixel or beam out."""

    excluded: np.ndarray | None

    def _size(self) -> int:
        raise NotImplementedError

    def valid(self) -> np.ndarray:
        """Flat (row-major) bool per pixel or beam: True where it counts."""
        if self.excluded is None:
            return np.ones(self._size(), bool)
        return ~self.excluded.ravel()

    def valid_index(self) -> np.ndarray:
        """Flat indices (uint32) of the pixels or beams that count: what a
        random batch draws from."""
        if getattr(self, "_valid_index", None) is None:
            self._valid_index = np.flatnonzero(self.valid()).astype(np.uint32)
        return self._valid_index

    def valid_mask(self):
        """``mi.Bool`` per pixel or beam for a loss's ``mask``, or ``None``
        when nothing is excluded."""
        if self.excluded is None:
            return None
        if getattr(self, "_valid_mask", None) is None:
            self._valid_mask = mi.Bool(self.valid())
        return self._valid_mask

    def restrict(self, mask):
        """``mask`` (a per-pixel ``mi.Bool``, or ``None`` for all) and the valid ones."""
        valid = self.valid_mask()
        if valid is None:
            return mask
        return valid if mask is None else mask & valid


@dataclass
class CameraObservation(Masked):
    sensor: object
    image: np.ndarray          # (H, W, 3) linear RGB
    width: int
    height: int
    rays: mi.Ray3f = None      # one per pixel, row-major
    priors: dict = field(default_factory=dict)  # kind -> (H, W, C) arrays
    excluded: np.ndarray | None = None          # (H, W) bool, True = left out
    #: Flat bool, True where the image shows the sky (:mod:`.sky_mask`);
    #: set by ``load_state`` on training and validation frames only.
    sky: np.ndarray | None = None

    def _size(self) -> int:
        return self.width * self.height

    def pixel_rays(self, index, offset=None):
        """Rays through the pixels ``index`` (numpy) at ``offset`` ((N, 2)
        numpy in [0, 1) within each pixel; default: the centres, cached)."""
        idx = jit_array(mi.UInt32, index)
        if offset is None:
            return gather_rays(self.rays, idx)
        return pixel_rays(self.sensor, self.width, self.height, idx,
                          (jit_array(mi.Float, offset[:, 0]),
                           jit_array(mi.Float, offset[:, 1])))


@dataclass
class LidarObservation(Masked):
    sensor: object
    intensity: np.ndarray      # (B, W') observed, [0, 1]
    range: np.ndarray          # (B, W')
    hit: np.ndarray            # (B, W') bool
    rays: mi.Ray3f = None      # one per kept pixel, row-major
    row: mi.UInt32 = None
    near: mi.Float = None      # distance from the sensor to each ray origin
    excluded: np.ndarray | None = None          # (B, W') bool, True = left out

    def _size(self) -> int:
        return self.intensity.size


@dataclass
class FrameObservation:
    index: int
    held_out: bool
    poses: dict                # object name -> 4x4 object -> world
    camera: CameraObservation | None
    lidar: LidarObservation | None


def _find_sensor(scene, name):
    for s in scene.sensors():
        if s.id() == name:
            return s
    return None


def camera_rays(sensor, width, height):
    """Rays through the pixel centres of a ``width`` x ``height`` grid over the film."""
    return pixel_rays(sensor, width, height, dr.arange(mi.UInt32, width * height))


def pixel_rays(sensor, width, height, index, offset=None):
    """Rays through the pixels ``index`` (flat, row-major; ``mi.UInt32``) of a
    ``width`` x ``height`` grid, at ``offset`` within each pixel (a pair of
    ``mi.Float`` in [0, 1); default: the centre)."""
    row = index // width
    col = index - row * width
    u, v = (0.5, 0.5) if offset is None else offset
    pos = mi.Point2f((mi.Float(col) + u) / width, (mi.Float(row) + v) / height)
    rays, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5), True)
    return mi.Ray3f(rays)


def lidar_rays(sensor, stride):
    """Beam rays of every ``stride``-th column, the row of each, and the origin offset."""
    from ..plugins.lidar_return import LidarReturnIntegrator
    rays, row, (h, w), near = LidarReturnIntegrator.beam_rays(sensor)
    cols = np.arange(0, w, stride)
    keep = (np.arange(h)[:, None] * w + cols[None, :]).ravel().astype(np.uint32)
    k = jit_array(mi.UInt32, keep)
    out = mi.Ray3f(dr.gather(mi.Point3f, rays.o, k), dr.gather(mi.Vector3f, rays.d, k))
    out.maxt = dr.gather(mi.Float, rays.maxt, k)
    return out, dr.gather(mi.UInt32, row, k), dr.gather(mi.Float, near, k), cols, (h, w)


def _read_image(path, width, height):
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise UserError("%s: cannot read the camera image" % path)
    img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0
    if img.shape[1] != width or img.shape[0] != height:
        img = cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)
    return srgb_to_linear(img).astype(np.float32)


def _read_scan(path):
    try:
        data, names = read_exr(str(path))
    except Exception as exc:  # noqa: BLE001  (any reader failure is a bad file)
        raise UserError("%s: cannot read the LiDAR scan (%s)" % (path, exc)) from None
    ch = {n: data[..., i] for i, n in enumerate(names)}
    for need in ("intensity", "range", "hit"):
        if need not in ch:
            raise UserError("%s: LiDAR scan lacks channel '%s' (has %s)" % (path, need, names))
    intensity = np.nan_to_num(ch["intensity"])
    rng = np.nan_to_num(ch["range"])
    hit = (ch["hit"] > 0.5) & np.isfinite(ch["range"]) & (rng > 0)
    return intensity, rng, hit


def _frame_mask(rec, kind, shape, what, log):
    """The frame's ``kind`` mask at its file's resolution, or None (not listed,
    or listed but missing: nothing excluded, with a note)."""
    path = rec.masks.get(kind)
    if path is None:
        return None
    if not path.is_file():
        log("[fit] %s: %s mask of frame %d not found; nothing excluded there"
            % (path, kind, rec.index))
        return None
    return read_mask(path, shape, what)


def camera_exclusion(rec, frames: Frames, width, height, log=print):
    """(height, width) bool, True where the frame's camera mask excludes any
    part of the pixel (area-resized, so a masked pixel stays masked); None
    when nothing is excluded."""
    full = _frame_mask(rec, "camera", (frames.camera.height, frames.camera.width),
                       "image (frames.json camera)", log)
    if full is None or not full.any():
        return None
    if full.shape != (height, width):
        cover = cv2.resize(full.astype(np.float32), (width, height), interpolation=cv2.INTER_AREA)
        full = cover > 1e-6
    return full


def lidar_exclusion(rec, shape, log=print):
    """Bool over the whole range image (``shape``), True where the frame's
    LiDAR mask excludes the beam; None when nothing is excluded."""
    full = _frame_mask(rec, "lidar", tuple(shape), "range image %s" % rec.lidar_scan.name, log)
    if full is None or not full.any():
        return None
    return full


def fit_size(frames: Frames, fit_width: int):
    w, h = frames.camera.width, frames.camera.height
    if fit_width and fit_width < w:
        return int(fit_width), max(1, int(round(h * fit_width / w)))
    return w, h


def load_observations(scene, frames: Frames, fit_width=320, lidar_columns=512,
                      use_camera=True, use_lidar=True, log=print):
    """Every frame's observations (training and held out)."""
    width, height = fit_size(frames, fit_width)
    out = []
    for pos, rec in enumerate(frames):
        cam = lid = None
        if use_camera and rec.image is not None:
            sensor = _find_sensor(scene, rec.camera)
            if sensor is None:
                raise UserError("%s: the scene has no sensor '%s' for frame %d"
                                % (frames.path, rec.camera, rec.index))
            if not rec.image.is_file():
                raise UserError("%s: image of frame %d not found" % (rec.image, rec.index))
            cam = CameraObservation(sensor, _read_image(rec.image, width, height), width, height,
                                    excluded=camera_exclusion(rec, frames, width, height, log))
            cam.rays = camera_rays(sensor, width, height)
            for kind, path in rec.priors.items():
                if path is not None and path.is_file():
                    data, _ = read_exr(str(path))
                    cam.priors[kind] = cv2.resize(data, (width, height),
                                                  interpolation=cv2.INTER_AREA).reshape(height, width, -1)
        if use_lidar and rec.lidar_scan is not None and not rec.lidar_scan.is_file():
            # frames.json lists it: training without it would fit the frame without LiDAR.
            raise UserError("%s: LiDAR scan of frame %d not found (listed in %s)"
                            % (rec.lidar_scan, rec.index, frames.path))
        if use_lidar and rec.lidar_scan is not None:
            sensor = _find_sensor(scene, rec.lidar)
            if sensor is not None:
                intensity, rng, hit = _read_scan(rec.lidar_scan)
                stride = max(1, int(np.ceil(intensity.shape[1] / max(lidar_columns, 1))))
                rays, row, near, cols, size = lidar_rays(sensor, stride)
                if tuple(intensity.shape) != tuple(size):
                    raise UserError("%s: scan is %dx%d but sensor '%s' has another size"
                                    % (rec.lidar_scan, intensity.shape[0], intensity.shape[1],
                                       rec.lidar))
                excluded = lidar_exclusion(rec, intensity.shape, log)
                lid = LidarObservation(sensor, intensity[:, cols], rng[:, cols], hit[:, cols],
                                       rays, row, near,
                                       excluded=None if excluded is None else excluded[:, cols])
        out.append(FrameObservation(rec.index, rec.held_out, dict(rec.objects), cam, lid))
    if not any(o.camera is not None or o.lidar is not None for o in out if not o.held_out):
        raise UserError("%s: no training frame has an image or a LiDAR scan" % frames.path)
    return out
