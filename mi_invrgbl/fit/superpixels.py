"""Superpixels of the LiDAR albedo map for the L_lidar->rgb term.

The paper takes its regions Omega from SAM run on the LiDAR albedo map; SAM
is a large network, so mi-invrgbl uses SLIC (opencv-contrib's
``cv2.ximgproc.createSuperpixelSLIC``), which on a piecewise-constant albedo
map also cuts along the material edges. The labels feed
:func:`mi_invrgbl.fit.losses.superpixel_variance` (as ``mi.UInt32`` of the
flattened row-major map).
"""

from __future__ import annotations

import numpy as np

#: SLIC variants by name.
_ALGORITHMS = ("SLIC", "SLICO", "MSLIC")
#: Largest value spread inside one segment (per channel, in the map's units):
#: SLIC alone lets a few segments reach across an edge where no centre of the
#: other side lies within its search window (measured: 6 of ~4000 segments on
#: clean two-region maps), so segments are split afterwards (see
#: :func:`split_by_value`). 0.05 separates materials whose LiDAR albedos
#: differ by more than 0.05 (road 0.16 vs. paint ~0.5 on KITTI).
DEFAULT_SPLIT_TOLERANCE = 0.05


def _to_float_image(image, name="image", valid=None):
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[..., 0]
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (3, 4)):
        raise ValueError("%s: expected an H x W or H x W x 3 image, got shape %s"
                         % (name, img.shape))
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[..., :3]
    img = img.astype(np.float32)
    bad = ~np.isfinite(img)
    if img.ndim == 3:
        bad = bad.any(axis=2)
    if valid is not None:
        bad |= ~np.asarray(valid, bool)
    return img, bad


def slic_labels(image, region_size: int = 16, ruler: float = 10.0, iterations: int = 10,
                valid=None, algorithm: str = "SLIC", min_element_size: int = 25,
                split_tolerance: float | None = DEFAULT_SPLIT_TOLERANCE, value_range=None):
    """SLIC superpixels of a 1-channel (LiDAR albedo) or RGB map.

    Args:
        image: ``(H, W)``, ``(H, W, 1)`` or ``(H, W, 3)`` float or uint8 array.
            Floats are mapped from ``value_range`` to 8 bits for SLIC.
        region_size: average superpixel side in pixels (clamped to the image).
        ruler: SLIC's compactness (ignored by SLICO, which adapts it).
        iterations: SLIC iterations.
        valid: optional ``(H, W)`` bool mask. Invalid pixels (and NaN / inf
            pixels, which are treated as invalid rather than refused) are
            filled with the mean valid value before segmenting and labelled
            ``-1`` afterwards (the loss ignores labels >= ``n_labels``).
        algorithm: ``SLIC`` (default; on flat two-region maps it straddled
            the edge least: 6 of 4224 segments vs. ~1 % for ``SLICO`` and
            ``MSLIC``), ``SLICO`` or ``MSLIC``.
        min_element_size: minimum segment size in percent of the average
            (``enforceLabelConnectivity``; 0 = off).
        split_tolerance: afterwards, split every segment so that no channel
            varies by more than this within it (:func:`split_by_value`;
            ``None`` or 0 = off). With it, no segment straddles a step larger
            than the tolerance.
        value_range: ``(lo, hi)`` of float input. Default: ``(0, 1)`` when all
            valid values lie in [0, 1] (albedo maps), else their 0.5 / 99.5
            percentiles. Not stretched to the data on purpose: stretching a
            low-contrast map turns its noise into SLIC edges.

    Returns:
        ``(labels, n_labels)``: int32 ``(H, W)`` labels numbered ``0..n_labels-1``
        (compacted: every label occurs), ``-1`` on invalid pixels.

    Maps smaller than 2 x 2 pixels, or with no valid pixel, get a single
    segment (or none).
    """
    import cv2

    if algorithm.upper() not in _ALGORITHMS:
        raise ValueError("slic_labels: algorithm must be one of %s" % ", ".join(_ALGORITHMS))
    if not hasattr(cv2, "ximgproc"):
        raise RuntimeError("slic_labels needs opencv-contrib (cv2.ximgproc); "
                           "install opencv-contrib-python-headless")
    raw = np.asarray(image)
    is_uint8 = raw.dtype == np.uint8
    img, bad = _to_float_image(raw, "slic_labels", valid)
    h, w = img.shape[:2]
    labels = np.full((h, w), -1, np.int32)
    good = ~bad
    if not good.any():
        return labels, 0
    if h < 2 or w < 2:
        labels[good] = 0
        return labels, 1

    # Fill invalid pixels so they pull no segment edge, then scale to [0, 1].
    values = img[good]
    fill = values.mean(axis=0)
    img = img.copy()
    img[bad] = fill
    if is_uint8:
        lo, hi = 0.0, 255.0
    elif value_range is not None:
        lo, hi = float(value_range[0]), float(value_range[1])
    elif values.min() >= 0.0 and values.max() <= 1.0:
        lo, hi = 0.0, 1.0
    else:
        lo, hi = float(np.percentile(values, 0.5)), float(np.percentile(values, 99.5))
    scaled = np.clip((img - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    # SLIC's distance mixes colour (0..255 scale for 8-bit) with space scaled by
    # ruler / region_size; 8-bit input keeps its compactness meaning.
    img8 = np.ascontiguousarray((scaled * 255.0 + 0.5).astype(np.uint8))

    size = int(max(2, min(region_size, h, w)))
    algo = getattr(cv2.ximgproc, algorithm.upper())
    slic = cv2.ximgproc.createSuperpixelSLIC(img8, algorithm=algo, region_size=size,
                                             ruler=float(ruler))
    slic.iterate(int(max(1, iterations)))
    if min_element_size > 0:
        slic.enforceLabelConnectivity(int(min_element_size))
    raw_labels = slic.getLabels().astype(np.int64)
    raw_labels[bad] = -1
    # Compact to 0..n-1 over the valid pixels.
    used = np.unique(raw_labels[good])
    lut = np.full(int(raw_labels.max()) + 2, -1, np.int64)
    lut[used] = np.arange(len(used))
    labels = np.where(good, lut[np.maximum(raw_labels, 0)], -1).astype(np.int32)
    n = int(len(used))
    if split_tolerance:
        unit = 255.0 if is_uint8 else 1.0
        labels, n = split_by_value(labels, np.where(bad[..., None] if img.ndim == 3 else bad,
                                                    0.0, img) / unit, n, split_tolerance)
    return labels, n


def split_by_value(labels, image, n_labels: int, tolerance: float):
    """Split segments whose pixels straddle a step larger than ``tolerance``.

    SLIC segments of a piecewise-constant map may still include a few pixels
    across an edge; this clean-up re-labels each segment by quantising each
    channel's values relative to the segment's minimum in steps of
    ``tolerance``, so that within every resulting segment each channel spans
    less than ``tolerance``. Parts may be disconnected (harmless for the
    variance loss: they have the same albedo). Returns ``(labels, n_labels)``
    like :func:`slic_labels` (``-1`` stays ``-1``).
    """
    img, _ = _to_float_image(image, "split_by_value")
    chans = img[..., None] if img.ndim == 2 else img
    labels = np.asarray(labels, np.int64)
    good = labels >= 0
    if not good.any() or not tolerance or tolerance <= 0:
        return labels.astype(np.int32), int(n_labels)
    lab = labels[good]
    key = lab.copy()
    for c in range(chans.shape[2]):
        v = chans[..., c][good].astype(np.float64)
        seg_min = np.full(int(n_labels), np.inf)
        np.minimum.at(seg_min, lab, v)
        bucket = np.floor((v - seg_min[lab]) / tolerance).astype(np.int64)
        _, key = np.unique(np.stack([key, bucket], 1), axis=0, return_inverse=True)
        key = key.ravel()
    out = np.full(labels.shape, -1, np.int64)
    out[good] = key
    return out.astype(np.int32), int(key.max()) + 1


def labels_to_drjit(labels):
    """Flattened labels as ``mi.UInt32`` (``-1`` becomes 0xFFFFFFFF, ignored by the loss)."""
    import mitsuba as mi
    from ..physics.host_arrays import jit_array
    flat = np.asarray(labels, np.int64).ravel()
    return jit_array(mi.UInt32, np.where(flat < 0, 0xFFFFFFFF, flat).astype(np.uint32))
