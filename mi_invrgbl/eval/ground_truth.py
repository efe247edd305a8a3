"""Scoring against a synthetic street's ground truth (``gt/`` of ``make-scene``).

Ground-truth files are found by the frame's source number ``N`` (6 digits):
``frames.json`` frame key ``source_index`` when present, else its ``index``.
Directions (normals, the sun) are rotated from the ground truth's world into
the scene's by the rigid transform that maps the first scored frame's true
camera pose (``gt/trajectory.json`` ``world_from_cam``) onto its
``camera_to_world``; identity without a trajectory file.

Material metrics (:func:`ground_truth_metrics`): albedo RMSE after a
per-channel scale fit, roughness MAE, normal angular error (degrees),
LiDAR-albedo RMSE (absolute and scale-fitted), all over the pixels where the
true surface exists and the render covers (alpha > :data:`ALPHA_MIN`; the
AOVs are divided by alpha), with two albedo references scored alike (a
flat map and the photo's own chromaticity,
:func:`~mi_invrgbl.eval.baselines.albedo_references`). :func:`sun_metrics`
compares the fitted sun with the true time-A sun.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import UserError
from ..physics.directions import angle_deg
from . import metrics as M
from .baselines import albedo_references
from .inputs import read_map

#: Pixels count as covered by the render where alpha exceeds this.
ALPHA_MIN = 0.5


def source_number(record) -> int:
    for key in ("source_index", "source_frame"):
        if key in record.extra:
            return int(record.extra[key])
    return int(record.index)


def gt_alignment(frames, positions, gt_dir):
    """Rotation (3x3) from the ground truth's world to the scene's (see module doc)."""
    traj = Path(gt_dir) / "trajectory.json"
    if not traj.is_file():
        return np.eye(3)
    try:
        cams = json.loads(traj.read_text())["world_from_cam"]
    except (KeyError, ValueError):
        return np.eye(3)
    for k in positions:
        rec = frames[k]
        n = source_number(rec)
        if 0 <= n < len(cams):
            T = rec.camera_to_world @ np.linalg.inv(np.asarray(cams[n], np.float64))
            u, _, vt = np.linalg.svd(T[:3, :3])
            return u @ vt
    return np.eye(3)


def load_lights(gt_dir):
    p = Path(gt_dir) / "lights.json"
    if not p.is_file():
        return None
    try:
        return json.loads(p.read_text())
    except ValueError:
        raise UserError("%s: not valid JSON" % p) from None


def sun_metrics(sky, lights, R):
    """The fitted sun against the ground truth's time-A sun (the fitted light)."""
    import mitsuba as mi
    la = (lights or {}).get("time_a")
    if not la or "sun_direction" not in la:
        return None
    params = mi.traverse(sky)
    irr = np.array(params["sun_irradiance"], np.float64).ravel()
    fitted = np.array(params["sun_direction"], np.float64).ravel()
    truth = R @ np.asarray(la["sun_direction"], np.float64)
    return {"sun_used": bool(np.max(irr) > 0), "sun_direction": fitted.tolist(),
            "true_sun_direction": truth.tolist(),
            "sun_direction_error_deg": angle_deg(fitted, truth)}


def ground_truth_metrics(cam, gt_dir, number, R, observed=None):
    """Material metrics of one frame against gt/maps (empty dict if absent).

    With the frame's ``observed`` sRGB image, the albedo references of
    :func:`~mi_invrgbl.eval.baselines.albedo_references` are scored on the
    same pixels as the fitted albedo (``albedo_rmse_flat``,
    ``albedo_rmse_chromaticity``)."""
    base = Path(gt_dir) / "maps" / ("%06d" % number)
    maps = {k: read_map(str(base) + "_%s.exr" % k)
            for k in ("albedo", "roughness", "normal", "lidar_albedo", "mesh_id")}
    if all(v is None for v in maps.values()):
        return {}
    ref = next(v for v in maps.values() if v is not None)
    h, w = ref.shape[:2]
    if cam["rgb"].shape[:2] != (h, w):
        raise UserError("%s_*.exr: ground truth is %dx%d but the camera renders %dx%d"
                        % (base, w, h, cam["rgb"].shape[1], cam["rgb"].shape[0]))
    if maps["mesh_id"] is not None:
        gt_hit = maps["mesh_id"] >= 0
    elif maps["normal"] is not None:
        gt_hit = np.linalg.norm(maps["normal"], axis=-1) > 0.5
    else:
        gt_hit = np.ones((h, w), bool)
    alpha = cam.get("alpha")
    covered = alpha > ALPHA_MIN if alpha is not None else np.ones((h, w), bool)
    mask = gt_hit & covered
    inv_a = 1.0 / np.maximum(alpha, 1e-6) if alpha is not None else 1.0
    out = {"gt_coverage": float(mask.sum() / max(gt_hit.sum(), 1))}

    def aov(name):
        v = cam.get(name)
        if v is None:
            return None
        return v * (inv_a[..., None] if v.ndim == 3 and np.ndim(inv_a) else inv_a)

    if maps["albedo"] is not None and cam.get("albedo") is not None:
        out["albedo_rmse"] = M.albedo_rmse_scaled(aov("albedo"), maps["albedo"], mask)
        if observed is not None and np.shape(observed)[:2] == (h, w):
            for name, ref in albedo_references(observed).items():
                out["albedo_rmse_" + name] = M.albedo_rmse_scaled(ref, maps["albedo"], mask)
    if maps["roughness"] is not None and cam.get("roughness") is not None:
        out["roughness_mae"] = M.mae(aov("roughness"), maps["roughness"], mask)
    if maps["normal"] is not None and cam.get("normal") is not None:
        gt_n = maps["normal"] @ R.T
        out["normal_angle_deg"] = M.angular_error_deg(cam["normal"], gt_n, mask)
    if maps["lidar_albedo"] is not None and cam.get("lidar_albedo") is not None:
        la = aov("lidar_albedo")
        out["lidar_albedo_rmse"] = M.rmse(la, maps["lidar_albedo"], mask)
        out["lidar_albedo_rmse_scaled"] = M.albedo_rmse_scaled(la, maps["lidar_albedo"], mask)
    return out
