"""Image writers: multi-channel EXR and tone-mapped PNG, written atomically."""

from __future__ import annotations

import numpy as np
import mitsuba as mi

from ..outdir import atomic_write
from ..physics.colour import linear_to_srgb


def write_exr(path: str, image: np.ndarray, channels: list[str]) -> None:
    """Write an H x W x C float image with named channels as an OpenEXR file."""
    image = np.ascontiguousarray(np.asarray(image, np.float32))
    if image.ndim == 2:
        image = image[..., None]
    if image.shape[2] != len(channels):
        raise ValueError("%s: %d channels but %d names" % (path, image.shape[2], len(channels)))
    bitmap = mi.Bitmap(image, mi.Bitmap.PixelFormat.MultiChannel, list(channels))
    atomic_write(path, lambda p: bitmap.write(p, mi.Bitmap.FileFormat.OpenEXR))


def read_exr(path: str) -> tuple[np.ndarray, list[str]]:
    """Read an EXR into (H x W x C array, channel names)."""
    bitmap = mi.Bitmap(path)
    names = [f.name for f in bitmap.struct_()]
    return np.array(bitmap, np.float32).reshape(bitmap.height(), bitmap.width(), -1), names


def write_png(path: str, linear_rgb: np.ndarray, exposure: float = 1.0) -> None:
    """Write linear RGB (or a single channel) as an 8-bit sRGB PNG."""
    img = np.clip(np.nan_to_num(np.asarray(linear_rgb, np.float32) * exposure), 0.0, 1.0)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[..., 0]
    srgb = linear_to_srgb(img)
    data = np.ascontiguousarray((srgb * 255 + 0.5).astype(np.uint8))
    fmt = mi.Bitmap.PixelFormat.Y if data.ndim == 2 else mi.Bitmap.PixelFormat.RGB
    bitmap = mi.Bitmap(data, fmt)
    atomic_write(path, lambda p: bitmap.write(p, mi.Bitmap.FileFormat.PNG))


def write_false_colour_png(path: str, values: np.ndarray, mask: np.ndarray | None = None,
                           vmax: float | None = None) -> None:
    """Write a single channel (range, intensity) as a viewable grey PNG (gamma 2.2)."""
    v = np.nan_to_num(np.asarray(values, np.float32))
    if mask is not None:
        v = np.where(mask, v, 0.0)
    top = vmax if vmax else (np.percentile(v[v > 0], 99) if np.any(v > 0) else 1.0)
    grey = np.clip(v / max(top, 1e-12), 0, 1) ** (1 / 2.2)
    data = np.ascontiguousarray((grey * 255 + 0.5).astype(np.uint8))
    bitmap = mi.Bitmap(data, mi.Bitmap.PixelFormat.Y)
    atomic_write(path, lambda p: bitmap.write(p, mi.Bitmap.FileFormat.PNG))


def read_image_uint8(path, size, crop=None, expected=None) -> np.ndarray:
    """An 8-bit image as (H, W, 3) RGB uint8 at ``size`` (W, H): cropped from
    the top left to ``crop`` (W, H) first if given, then resized (area
    averaging). One error naming the file if it cannot be read, or if its
    size is not ``expected`` (W, H; the calibration's), which would
    otherwise be stretched silently."""
    import cv2
    from ..errors import UserError

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise UserError(f"{path}: not a readable image")
    if expected is not None and (img.shape[1], img.shape[0]) != tuple(expected):
        raise UserError(f"{path}: image is {img.shape[1]}x{img.shape[0]}, the calibration's "
                        f"(and the drive's) is {expected[0]}x{expected[1]}")
    if crop is not None:
        img = img[:crop[1], :crop[0]]
    if (img.shape[1], img.shape[0]) != tuple(size):
        img = cv2.resize(img, tuple(size), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(img[:, :, ::-1])     # RGB uint8


def read_mask(path, shape, what) -> np.ndarray:
    """An 8-bit mask file (e.g. ``import``'s motion masks, 255 = exclude) as
    a bool array, True where the value is above 127, of ``shape`` (rows,
    columns); a one-line ``UserError`` when it is unreadable or of another
    size. ``what`` names the grid it must cover, for the message."""
    import cv2
    from ..errors import UserError
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise UserError("%s: cannot read the mask" % path)
    if img.ndim == 3:
        img = img.max(axis=2)
    if tuple(img.shape) != tuple(shape):
        raise UserError("%s: mask is %dx%d (width x height) but the %s is %dx%d"
                        % (path, img.shape[1], img.shape[0], what, shape[1], shape[0]))
    return img > 127
