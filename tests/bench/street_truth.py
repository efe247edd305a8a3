"""What the synthetic-street benches share: the ground truth behind a scene
folder, its per-frame maps, the observed images and the fitted maps.

    meta, gt = ground_truth(root)          # frames.json and the truth folder
    truth_map(gt, "sun_visibility", n)     # (H, W) or (H, W, 3) float32
"""

import sys as _sys, pathlib as _pathlib
_sys.path.insert(0, str(_pathlib.Path(__file__).resolve().parents[1]))
import variant_choice  # noqa: E402  (--variant NAME, default $MI_INVRGBL_VARIANT or llvm_ad_rgb)
variant_choice.from_argv()

import json
import os
import sys

import numpy as np
import cv2
import mitsuba as mi

from mi_invrgbl.eval.metrics import srgb_to_linear  # noqa: E402

from mi_invrgbl.physics.colour import LUMINANCE as LUM  # noqa: E402


def read_exr(path):
    """An EXR's pixels: (H, W) for one channel, (H, W, C) for more."""
    return np.array(mi.Bitmap(path), np.float32)


def ground_truth(root):
    """``(frames.json as a dict, truth folder)``; exits with a message without one."""
    meta = json.load(open(os.path.join(root, "frames.json")))
    gt = meta.get("ground_truth")
    gt = gt.get("dir") if isinstance(gt, dict) else gt
    if not gt:
        sys.exit("%s: frames.json names no ground truth" % root)
    if not os.path.isabs(gt):
        gt = os.path.normpath(os.path.join(root, gt))
    return meta, gt


def source_number(frame):
    """The generator's frame number of a frames.json record."""
    return int(frame.get("source_index", frame.get("source_frame", frame["index"])))


def scene_from_truth(rec, cams):
    """4x4 rigid map from the truth's world into the scene's: the motion
    between frame record ``rec``'s camera pose in the scene and the same
    frame's in the truth (``cams``: trajectory.json's ``world_from_cam``)."""
    from mi_invrgbl.eval.ground_truth import source_number as number
    return np.asarray(rec.camera_to_world, np.float64) @ np.linalg.inv(np.asarray(cams[number(rec)], np.float64))


def truth_to_scene(gt, rec):
    """:func:`scene_from_truth` for frame record ``rec``, with the truth's
    camera poses read from ``gt``'s ``trajectory.json``."""
    cams = json.load(open(os.path.join(gt, "trajectory.json")))["world_from_cam"]
    return scene_from_truth(rec, cams)


def nearest_points(points, queries):
    """Index of (int64) and distance to each query's nearest point among
    ``points`` (approximate: a FLANN forest, 64 checks)."""
    index = cv2.flann_Index(np.ascontiguousarray(points, np.float32), dict(algorithm=1, trees=4))
    pick, d2 = index.knnSearch(np.ascontiguousarray(queries, np.float32), 1, params=dict(checks=64))
    return pick[:, 0].astype(np.int64), np.sqrt(np.maximum(d2[:, 0], 0.0))


def truth_map(gt, kind, number):
    """Ground-truth map ``kind`` (albedo, normal, sun_visibility, mesh_id, ...) of a frame."""
    return read_exr(os.path.join(gt, "maps", "%06d_%s.exr" % (number, kind)))


def fitted_map(root, variant, index, kind):
    """Map ``kind`` that ``fit`` wrote for training frame ``index``, or None."""
    path = os.path.join(root, variant, "maps", "%04d_%s.exr" % (index, kind))
    return read_exr(path) if os.path.isfile(path) else None


def observed_linear(root, index):
    """The observed image of frame ``index`` as linear RGB."""
    img = cv2.imread(os.path.join(root, "observations", "image_%04d.png" % index))[..., ::-1] / 255.0
    return srgb_to_linear(img)


def open_fit(fit, frames_spec="held-out"):
    """A fitted scene folder as ``eval`` opens it: ``(frames, truth folder,
    selected frame positions, loaded scene)``; exits with a message when the
    frames have no ground truth (only ``make-scene street`` imports do)."""
    from pathlib import Path
    from mi_invrgbl.eval.inputs import resolve_inputs, select_frames
    from mi_invrgbl.scene.frames import Frames
    from mi_invrgbl.scene.loading import load_scene
    scene_xml, _ = resolve_inputs(fit)
    frames = Frames.load(scene_xml)
    if frames.ground_truth is None or not Path(frames.ground_truth).is_dir():
        sys.exit("%s: no ground truth next to the frames (a make-scene street import)" % fit)
    return frames, Path(frames.ground_truth), select_frames(frames, frames_spec), \
        load_scene(str(scene_xml))


def refuse_existing(*paths):
    """Exit with one line if an output file a bench was asked for exists:
    a bench writes only new files, never over one it did not write."""
    for path in paths:
        if path and os.path.exists(path):
            sys.exit("%s: exists; not overwritten" % path)


def write_json(path, record):
    """``record`` as JSON at ``path`` (written to a temporary file, then renamed)."""
    import json
    from mi_invrgbl.outdir import atomic_write_text
    atomic_write_text(path, json.dumps(record, indent=1))
