"""The animation of a rendered sequence: an MP4 and a GIF.

Both come from OpenCV, which the project already depends on: MP4 through
``cv2.VideoWriter`` with the ``mp4v`` codec (the one the pip wheel's bundled
FFmpeg can always encode; H.264 needs a hardware or GPL encoder the wheel
lacks), GIF through ``cv2.imwriteanimation`` (OpenCV >= 4.11). The GIF is
what a browser or a README shows; the MP4 is what a video player shows.
Either can fail on an unusual OpenCV build: the PNG frames stay the result,
and the caller prints why the animation is missing.
"""

from __future__ import annotations

import os

import numpy as np

from ..physics.colour import linear_to_srgb

#: Frames per second of the animations (KITTI records at 10 Hz).
DEFAULT_FPS = 10.0
#: Longest side of GIF frames: GIFs of wide street images grow large fast.
GIF_MAX_SIDE = 640


def to_srgb8(linear_rgb: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """Linear RGB (H, W, 3) to 8-bit sRGB, as :func:`mi_invrgbl.io.images.write_png` does."""
    img = np.clip(np.nan_to_num(np.asarray(linear_rgb, np.float32) * exposure), 0.0, 1.0)
    srgb = linear_to_srgb(img)
    return (srgb * 255 + 0.5).astype(np.uint8)


def _even(frames):
    """Crop to even sizes (MPEG-4 encoders need them) and make every frame RGB."""
    out = []
    for f in frames:
        f = np.asarray(f, np.uint8)
        if f.ndim == 2:
            f = np.repeat(f[..., None], 3, axis=2)
        h, w = f.shape[:2]
        out.append(np.ascontiguousarray(f[:h - h % 2, :w - w % 2, :3]))
    return out


def write_mp4(path: str, frames, fps: float = DEFAULT_FPS) -> str | None:
    """Write RGB uint8 frames as MP4; returns the path, or None if OpenCV cannot."""
    import cv2
    frames = _even(frames)
    if not frames:
        return None
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (w, h))
    if not writer.isOpened():
        return None
    for f in frames:
        if f.shape[:2] != (h, w):
            f = cv2.resize(f, (w, h))
        writer.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    writer.release()
    return path if os.path.isfile(path) and os.path.getsize(path) > 0 else None


def write_gif(path: str, frames, fps: float = DEFAULT_FPS) -> str | None:
    """Write RGB uint8 frames as a looping GIF; returns the path, or None if OpenCV cannot."""
    import cv2
    if not hasattr(cv2, "imwriteanimation") or not frames:
        return None
    scaled = []
    for f in _even(frames):
        h, w = f.shape[:2]
        k = GIF_MAX_SIDE / max(h, w)
        if k < 1:
            f = cv2.resize(f, (int(w * k) // 2 * 2, int(h * k) // 2 * 2), interpolation=cv2.INTER_AREA)
        scaled.append(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    animation = cv2.Animation()
    animation.frames = scaled
    animation.durations = [int(round(1000.0 / fps))] * len(scaled)
    animation.loop_count = 0
    try:
        ok = cv2.imwriteanimation(path, animation)
    except cv2.error:
        return None
    return path if ok else None


def write_animation(out_dir: str, frames, stem: str = "sequence", fps: float = DEFAULT_FPS) -> list[str]:
    """MP4 + GIF of ``frames`` in ``out_dir``; returns the files written (maybe none)."""
    written = []
    for writer, ext in ((write_mp4, ".mp4"), (write_gif, ".gif")):
        path = writer(os.path.join(out_dir, stem + ext), frames, fps)
        if path:
            written.append(path)
    return written
