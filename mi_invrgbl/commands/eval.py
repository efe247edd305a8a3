"""``mi-invrgbl eval FIT_DIR_OR_SCENE``: score a (fitted) scene on its frames.

For every selected frame (default: the held-out ones, ``index % 5 == 4``)
the dynamic objects are placed (:func:`mi_invrgbl.scene_graph.set_frame`),
the frame's camera is rendered with the scene's integrator and its LiDAR
with ``lidar_return``, and the renders are compared with the observations:

* camera: PSNR and SSIM in sRGB. The observed images are 8-bit sRGB PNGs,
  so the linear render is converted with the sRGB curve, clipped to [0, 1]
  and compared in [0, 1] (peak 1).
* LiDAR: intensity RMSE over the beams that return in the observation,
  range error (mean |dr| where both return), ray-drop accuracy (all beams),
  and the nearest-neighbour baseline's intensity RMSE on the same beams
  (:mod:`mi_invrgbl.fit.baselines`, built from the *training* frames' points).
* synthetic ground truth (``frames.json`` ``ground_truth.dir``, as written by
  ``make-scene street``): albedo RMSE after a per-channel scale fit, roughness
  MAE, normal angular error (degrees), LiDAR-albedo RMSE (absolute and
  scale-fitted), all over the pixels where the true surface exists and the
  render covers (alpha > 0.5; the AOVs are divided by alpha), and relighting
  PSNR / SSIM: the scene's ``shsun`` is set to the ground truth's time-B light
  (constant sky radiance -> SH order-0 coefficient ``L / Y_0``, sun direction
  and irradiance), rendered, and compared with ``gt/time_b/N.exr`` (linear,
  both converted to sRGB and clipped).

Ground-truth files are found by the frame's source number ``N`` (6 digits):
``frames.json`` frame key ``source_index`` when present, else its ``index``.
Directions (normals, the sun) are rotated from the ground truth's world into
the scene's by the rigid transform that maps the first scored frame's true
camera pose (``gt/trajectory.json`` ``world_from_cam``) onto its
``camera_to_world``; identity without a trajectory file.

Writes ``metrics.json`` (per frame and the mean over frames; PSNR of
identical images is reported as :data:`PSNR_CAP` dB, JSON has no infinity)
and prints a table. What ``fit`` wrote into that file before (selection,
response, times) is kept under ``"fit"``.
"""

from __future__ import annotations

import json
import math
import os
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import drjit as dr
import numpy as np

from ..errors import UserError, mitsuba_message
from ..scene_graph import set_frame

#: PSNR reported for identical images (MSE = 0).
PSNR_CAP = 100.0
#: Pixels count as covered by the render where alpha exceeds this.
ALPHA_MIN = 0.5

#: Columns of the printed table: (key, header, format).
TABLE = (("psnr", "PSNR", "%6.2f"), ("ssim", "SSIM", "%6.4f"),
         ("lidar_intensity_rmse", "I-RMSE", "%7.4f"), ("baseline_intensity_rmse", "NN-RMSE", "%7.4f"),
         ("range_error", "range", "%6.3f"), ("ray_drop_accuracy", "drop-acc", "%8.4f"),
         ("albedo_rmse", "albedo", "%6.4f"), ("roughness_mae", "rough", "%6.4f"),
         ("normal_angle_deg", "normal°", "%7.2f"), ("lidar_albedo_rmse", "L-alb", "%6.4f"),
         ("relight_psnr", "relight", "%7.2f"))


def add_parser(sub):
    p = sub.add_parser("eval", help="score a fitted scene on held-out frames (and ground truth)")
    p.add_argument("scene", metavar="FIT_DIR_OR_SCENE",
                   help="a fit folder (with scene.xml) or a scene XML file")
    p.add_argument("--frames", default="held-out",
                   help="held-out (default), all, A:B (frame indices, B excluded) or a list 3,8")
    p.add_argument("-o", "--output", default=None,
                   help="metrics file (default: metrics.json next to the scene)")
    p.add_argument("--spp", type=int, default=0, help="camera samples per pixel (default: the sensor's)")
    p.add_argument("--samples", type=int, default=None,
                   help="sky samples M of the invrgbl integrator (default: the scene's)")
    p.add_argument("--lidar-model", choices=("pbr", "lambertian"), default=None,
                   help="LiDAR model when the fit has no scene_lidar.xml (default: pbr)")
    p.add_argument("--no-baseline", action="store_true", help="skip the nearest-neighbour baseline")
    p.add_argument("--baseline-max-points", type=int, default=2_000_000,
                   help="subsample the baseline's training points to this many (default: 2e6)")
    p.add_argument("--no-relight", action="store_true", help="skip the relighting score")
    p.add_argument("--save-renders", default=None, metavar="DIR",
                   help="also write each frame's renders (EXR) into DIR")
    p.set_defaults(run=run)


# ----------------------------------------------------------------------------
# Inputs
# ----------------------------------------------------------------------------
def resolve_inputs(path):
    """``(scene.xml, scene_lidar.xml or None)`` for a fit folder or a scene file."""
    p = Path(path)
    if not p.exists():
        raise UserError("%s: no such fit folder or scene file" % p)
    if p.is_dir():
        scene = p / "scene.xml"
        if not scene.is_file():
            raise UserError("%s: not a fit folder (no scene.xml in it)" % p)
    else:
        if p.suffix.lower() != ".xml":
            raise UserError("%s: expected a fit folder or a scene .xml file" % p)
        scene = p
    lidar = scene.parent / "scene_lidar.xml"
    return scene, (lidar if lidar.is_file() and lidar != scene else None)


def select_frames(frames, spec: str) -> list:
    """Positions in ``frames`` (not indices) chosen by ``--frames``."""
    spec = (spec or "held-out").strip()
    by_index = {f.index: k for k, f in enumerate(frames.frames)}
    if spec in ("held-out", "held_out", "heldout", "test"):
        pos = [k for k, f in enumerate(frames.frames) if f.held_out]
        if not pos:
            raise UserError("%s: no held-out frame (use --frames all or A:B)" % frames.path)
        return pos
    if spec == "all":
        return list(range(len(frames.frames)))
    try:
        if ":" in spec:
            a, b = spec.split(":", 1)
            lo = int(a) if a.strip() else min(by_index)
            hi = int(b) if b.strip() else max(by_index) + 1
            wanted = [i for i in sorted(by_index) if lo <= i < hi]
        else:
            wanted = [int(v) for v in spec.split(",") if v.strip()]
    except ValueError:
        raise UserError("--frames: expected held-out, all, A:B or a list of indices, got '%s'"
                        % spec) from None
    missing = [i for i in wanted if i not in by_index]
    if missing:
        raise UserError("--frames: frame(s) %s not in %s" % (missing, frames.path))
    if not wanted:
        raise UserError("--frames %s selects no frame" % spec)
    return [by_index[i] for i in wanted]


def load_lidar_integrator(scene_lidar, model=None):
    """The ``lidar_return`` integrator of ``scene_lidar.xml`` (only its
    ``<integrator>`` and ``<default>`` elements are loaded), or a default one."""
    import mitsuba as mi
    if scene_lidar is None:
        return mi.load_dict({"type": "lidar_return", "model": model or "pbr"})
    try:
        root = ET.parse(scene_lidar).getroot()
    except (ET.ParseError, OSError) as exc:
        raise UserError("%s: cannot read: %s" % (scene_lidar, exc)) from None
    integ = [e for e in root if e.tag == "integrator"]
    if not integ:
        raise UserError("%s: no <integrator> element" % scene_lidar)
    if integ[0].get("type") != "lidar_return":
        raise UserError("%s: the integrator is '%s', expected lidar_return"
                        % (scene_lidar, integ[0].get("type")))
    if model is not None:
        for e in integ[0]:
            if e.get("name") == "model":
                e.set("value", model)
    parts = [ET.tostring(e, encoding="unicode") for e in root if e.tag == "default"]
    parts.append(ET.tostring(integ[0], encoding="unicode"))
    text = '<scene version="%s">%s</scene>' % (root.get("version", "3.0.0"), "".join(parts))
    try:
        return mi.load_string(text).integrator()
    except Exception as exc:
        raise UserError("%s: cannot load the lidar_return integrator: %s"
                        % (scene_lidar, mitsuba_message(exc))) from None


def read_png(path):
    """An 8-bit (sRGB) image as float (H, W, 3) in [0, 1]."""
    import mitsuba as mi
    if not os.path.isfile(path):
        raise UserError("%s: observation image not found" % path)
    try:
        bmp = mi.Bitmap(str(path))
    except Exception as exc:
        raise UserError("%s: cannot read image: %s" % (path, exc)) from None
    arr = np.array(bmp)
    if arr.ndim == 2:
        arr = arr[..., None]
    scale = 255.0 if arr.dtype == np.uint8 else (65535.0 if arr.dtype == np.uint16 else 1.0)
    arr = arr.astype(np.float64) / scale
    if arr.shape[2] == 1:
        arr = np.repeat(arr, 3, axis=2)
    return arr[..., :3]


def read_channels(path, names, what="file"):
    """Named channels of an EXR as a dict of (H, W) arrays (EXR may reorder channels)."""
    from ..io.images import read_exr
    if not os.path.isfile(path):
        raise UserError("%s: %s not found" % (path, what))
    try:
        arr, chans = read_exr(str(path))
    except Exception as exc:
        raise UserError("%s: cannot read EXR: %s" % (path, exc)) from None
    out = {}
    lower = [c.lower() for c in chans]
    for n in names:
        if n in lower:
            out[n] = arr[..., lower.index(n)]
        elif len(chans) == len(names):
            out[n] = arr[..., names.index(n)]
        else:
            raise UserError("%s: no channel '%s' (has %s)" % (path, n, ", ".join(chans)))
    return out


def read_map(path):
    """A ground-truth map as (H, W) or (H, W, 3) float array (None if absent)."""
    from ..io.images import read_exr
    if not os.path.isfile(path):
        return None
    arr, _ = read_exr(str(path))
    return arr[..., 0] if arr.shape[2] == 1 else arr[..., :3]


# ----------------------------------------------------------------------------
# Rendering
# ----------------------------------------------------------------------------
def _channel_index(names, prefix):
    return [i for i, n in enumerate(names) if n == prefix or n.startswith(prefix + ".")]


def render_camera(scene, sensor, spp=0, integrator=None):
    """Linear RGB (H, W, 3) and AOVs {albedo, normal, roughness, lidar_albedo, alpha}."""
    import mitsuba as mi
    img = np.array(mi.render(scene, sensor=sensor, spp=spp, integrator=integrator), np.float64)
    names = [f.name for f in sensor.film().bitmap().struct_()] if img.shape[2] > 3 else []
    out = {"rgb": img[..., :3]}
    if len(names) == img.shape[2]:
        for key in ("albedo", "normal", "roughness", "lidar_albedo", "alpha", "depth"):
            idx = _channel_index(names, key)
            if idx:
                out[key] = img[..., idx] if len(idx) > 1 else img[..., idx[0]]
    return out


def render_lidar(scene, sensor, integrator):
    import mitsuba as mi
    arr = np.array(mi.render(scene, sensor=sensor, integrator=integrator), np.float64)
    keys = ("intensity", "range", "hit", "lidar_albedo", "alpha")
    return {k: arr[..., i] for i, k in enumerate(keys) if i < arr.shape[2]}


def integrator_like(scene, samples=None, sun_visibility=None):
    """The scene's ``invrgbl`` integrator with ``samples`` / ``sun_visibility``
    replaced (None: no change needed, or not an ``invrgbl`` scene)."""
    import mitsuba as mi
    integ = scene.integrator()
    if type(integ).__name__ != "InvRGBLIntegrator":
        return None
    if (samples is None or samples == integ.samples) and \
            (sun_visibility is None or sun_visibility == integ.sun_visibility):
        return None
    return mi.load_dict({"type": "invrgbl", "samples": int(samples or integ.samples),
                         "max_hits": integ.max_hits,
                         "min_transmittance": integ.min_transmittance,
                         "sun_visibility": sun_visibility or integ.sun_visibility,
                         "f0": integ.f0, "hide_emitters": integ.hide_emitters})


def place_frame(scene, frames, k):
    """:func:`~mi_invrgbl.scene_graph.set_frame`, then make the scene see the move.

    ``set_frame`` edits each object's parameters through ``mi.traverse(shape)``;
    with Mitsuba 3.9.1 that leaves the *scene's* ray-tracing acceleration
    structure at the old bounds, so a moved object is partly missed.
    Re-assigning the objects' ``data`` through the scene's own parameters
    rebuilds it (measured: max pixel error 0.73 -> 0.001 against the object
    loaded at that pose). Harmless once ``set_frame`` does this itself.
    """
    import mitsuba as mi
    cam, lidar = set_frame(scene, frames, k)
    if frames.objects:
        params = mi.traverse(scene)
        changed = False
        for name in frames.objects:
            key = name + ".data"
            if key in params.keys():
                params[key] = type(params[key])(np.array(params[key]))
                changed = True
        if changed:
            params.update()
    return cam, lidar


def _find_sky(scene):
    for e in scene.emitters():
        if hasattr(e, "sh_coefficients") and hasattr(e, "sun_direction"):
            return e
    return None


class SkySwap:
    """Set a ``shsun`` emitter to a constant sky + sun, and put it back."""

    def __init__(self, emitter):
        import mitsuba as mi
        self.params = mi.traverse(emitter)
        self.saved = {k: type(self.params[k])(self.params[k]) for k in
                      ("sh", "sun_direction", "sun_irradiance")}

    def set(self, sky_radiance, sun_direction, sun_irradiance):
        from ..physics.sh import Y0
        n = dr.width(self.params["sh"])
        sh = np.zeros(n, np.float32)
        sh[:3] = np.asarray(sky_radiance, np.float64) / Y0
        self.params["sh"] = type(self.params["sh"])(sh)
        self.params["sun_direction"] = type(self.params["sun_direction"])(
            *[float(v) for v in sun_direction])
        self.params["sun_irradiance"] = type(self.params["sun_irradiance"])(
            *[float(v) for v in sun_irradiance])
        self.params.update()

    def restore(self):
        for k, v in self.saved.items():
            self.params[k] = v
        self.params.update()


# ----------------------------------------------------------------------------
# Ground truth
# ----------------------------------------------------------------------------
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
    cos = np.dot(fitted, truth) / max(np.linalg.norm(fitted) * np.linalg.norm(truth), 1e-12)
    return {"sun_used": bool(np.max(irr) > 0), "sun_direction": fitted.tolist(),
            "true_sun_direction": truth.tolist(),
            "sun_direction_error_deg": float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))}


def ground_truth_metrics(cam, gt_dir, number, R):
    """Material metrics of one frame against gt/maps (empty dict if absent)."""
    from .. import metrics as M
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


# ----------------------------------------------------------------------------
# Scoring
# ----------------------------------------------------------------------------
def _cap(v):
    if v is None:
        return None
    v = float(v)
    if math.isnan(v):
        return None
    return min(v, PSNR_CAP) if v > 0 and math.isinf(v) else v


def image_metrics(render_lin, observed_srgb):
    from .. import metrics as M
    pred = np.clip(M.linear_to_srgb(render_lin), 0.0, 1.0)
    if pred.shape != observed_srgb.shape:
        raise UserError("the camera renders %dx%d but the observation is %dx%d"
                        % (pred.shape[1], pred.shape[0], observed_srgb.shape[1],
                           observed_srgb.shape[0]))
    return {"psnr": min(M.psnr(pred, observed_srgb, 1.0), PSNR_CAP),
            "ssim": M.ssim(pred, observed_srgb, 1.0)}


def lidar_metrics(pred, obs, baseline=None, sensor=None):
    from .. import metrics as M
    shape = obs["intensity"].shape
    if pred["intensity"].shape != shape:
        raise UserError("the LiDAR renders %dx%d but the observed scan is %dx%d"
                        % (pred["intensity"].shape[1], pred["intensity"].shape[0],
                           shape[1], shape[0]))
    obs_hit = obs["hit"] > 0.5
    out = {"lidar_intensity_rmse": M.rmse(pred["intensity"], obs["intensity"], obs_hit),
           "range_error": M.range_error(pred["range"], obs["range"], pred["hit"], obs["hit"]),
           "ray_drop_accuracy": M.ray_drop_accuracy(pred["hit"], obs["hit"]),
           "lidar_returns": float(obs_hit.mean())}
    if baseline is not None and sensor is not None:
        dirs = np.asarray(sensor.ray_directions_local(), np.float64)
        if dirs.shape[:2] == shape:
            to_world = np.array(sensor.world_transform().matrix, np.float64).reshape(4, 4)
            dirs_w = dirs @ to_world[:3, :3].T
            dirs_w /= np.maximum(np.linalg.norm(dirs_w, axis=-1, keepdims=True), 1e-12)
            nn = baseline.predict_scan(obs["range"], dirs_w, to_world[:3, 3], obs_hit)
            out["baseline_intensity_rmse"] = M.rmse(nn, obs["intensity"], obs_hit)
    return out


def _mean(rows):
    keys = []
    for r in rows:
        keys += [k for k, v in r.items() if k not in keys and isinstance(v, (int, float))
                 and not isinstance(v, bool) and k not in ("index", "position")]
    out = {}
    for k in keys:
        vals = [r[k] for r in rows if isinstance(r.get(k), (int, float)) and r[k] is not None
                and math.isfinite(r[k])]
        if vals:
            out[k] = float(np.mean(vals))
    return out


def format_table(rows, mean) -> str:
    cols = [c for c in TABLE if any(c[0] in r for r in rows)]
    head = "frame " + " ".join("%8s" % c[1] for c in cols)
    lines = [head, "-" * len(head)]

    def fmt(row, label):
        cells = []
        for key, _, f in cols:
            v = row.get(key)
            cells.append("%8s" % ("-" if v is None else (f % v).strip()))
        return "%-5s " % label + " ".join(cells)

    for r in rows:
        lines.append(fmt(r, "%d" % r["index"]))
    lines.append(fmt(mean, "mean"))
    return "\n".join(lines)


def _json_clean(value):
    if isinstance(value, dict):
        return {k: _json_clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_clean(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return _cap(value)
    if isinstance(value, np.integer):
        return int(value)
    return value


def evaluate(scene_path, frames_spec="held-out", spp=0, samples=None, lidar_model=None,
             baseline=True, relight=True, baseline_max_points=2_000_000, save_renders=None,
             log=print):
    """Score a scene; returns the metrics dictionary (see the module docstring)."""
    from .. import metrics as M
    from ..scene_graph import Frames
    from .render import load_scene

    scene_xml, scene_lidar = resolve_inputs(scene_path)
    frames = Frames.load(scene_xml)
    positions = select_frames(frames, frames_spec)
    t0 = time.time()
    scene = load_scene(str(scene_xml))
    lidar_integ = load_lidar_integrator(scene_lidar, lidar_model)
    cam_integ = integrator_like(scene, samples)
    log("[eval] %s: %d frame(s) to score, loaded in %.1f s%s"
        % (scene_xml, len(positions), time.time() - t0,
           "" if scene_lidar is None else "; LiDAR response from %s" % scene_lidar.name))

    nn = None
    if baseline:
        from ..fit.baselines import NearestNeighbourIntensity, load_points
        held = {k for k in range(len(frames)) if frames[k].held_out} | set(positions)
        paths = [frames[k].points for k in range(len(frames))
                 if k not in held and frames[k].points is not None
                 and os.path.isfile(frames[k].points)]
        if paths:
            t = time.time()
            pts = load_points(paths, baseline_max_points)
            if len(pts):
                nn = NearestNeighbourIntensity(pts)
                log("[eval] nearest-neighbour baseline: %d points from %d training frame(s), "
                    "%.1f s" % (len(nn), len(paths), time.time() - t))
        else:
            log("[eval] no training points: nearest-neighbour baseline skipped")

    gt_dir = frames.ground_truth if frames.ground_truth is not None \
        and Path(frames.ground_truth).is_dir() else None
    if frames.ground_truth is not None and gt_dir is None:
        log("[eval] ground truth %s not found: material metrics skipped" % frames.ground_truth)
    R = gt_alignment(frames, positions, gt_dir) if gt_dir else np.eye(3)
    lights = load_lights(gt_dir) if gt_dir and relight else None
    sky = _find_sky(scene) if lights and "time_b" in lights else None
    if lights and "time_b" in lights and sky is None:
        log("[eval] the scene has no shsun emitter: relighting score skipped")
    # A moved sun needs traced sun visibility, not the fitted per-Gaussian field.
    relight_integ = integrator_like(scene, samples, "trace") if sky is not None else None

    rows = []
    for k in positions:
        rec = frames[k]
        t = time.time()
        cam_sensor, lidar_sensor = place_frame(scene, frames, k)
        row = {"index": rec.index}
        if cam_sensor is None:
            raise UserError("%s: no camera sensor '%s' for frame %d" % (scene_xml, rec.camera, rec.index))
        cam = render_camera(scene, cam_sensor, spp, cam_integ)
        if rec.image is not None:
            row.update(image_metrics(cam["rgb"], read_png(rec.image)))
        if lidar_sensor is not None and rec.lidar_scan is not None:
            obs = read_channels(rec.lidar_scan, ["intensity", "range", "hit"], "LiDAR scan")
            pred = render_lidar(scene, lidar_sensor, lidar_integ)
            row.update(lidar_metrics(pred, obs, nn, lidar_sensor))
        elif rec.lidar_scan is not None:
            log("[eval] frame %d: no LiDAR sensor '%s' in the scene" % (rec.index, rec.lidar))
        if gt_dir is not None:
            row.update(ground_truth_metrics(cam, gt_dir, source_number(rec), R))
        if save_renders:
            from ..io.images import write_exr
            os.makedirs(save_renders, exist_ok=True)
            write_exr(os.path.join(save_renders, "camera_%04d.exr" % rec.index),
                      cam["rgb"], ["R", "G", "B"])
        row["time_s"] = time.time() - t
        rows.append(row)
        log("[eval] frame %d scored in %.1f s" % (rec.index, row["time_s"]))

    # Relighting in a second pass with the time-B light set once: the
    # integrator's lighting precompute (minutes at 1e5-1e6 Gaussians) is
    # redone whenever the sun or the geometry changes, so interleaving the two
    # lights would pay it twice per frame even in a static scene.
    if sky is not None:
        todo = [(k, row, Path(gt_dir) / "time_b" / ("%06d.exr" % source_number(frames[k])))
                for k, row in zip(positions, rows)]
        todo = [item for item in todo if item[2].is_file()]
        if todo:
            lb = lights["time_b"]
            swap = SkySwap(sky)
            try:
                swap.set(lb.get("sky_radiance", [0, 0, 0]),
                         R @ np.asarray(lb.get("sun_direction", [0, 0, 1]), np.float64),
                         lb.get("sun_irradiance", [0, 0, 0]))
                for k, row, gt_b in todo:
                    t = time.time()
                    cam_sensor, _ = place_frame(scene, frames, k)
                    relit = render_camera(scene, cam_sensor, spp, relight_integ)
                    truth = read_channels(gt_b, ["r", "g", "b"], "relighting ground truth")
                    truth = np.stack([truth["r"], truth["g"], truth["b"]], -1)
                    m = image_metrics(relit["rgb"], np.clip(M.linear_to_srgb(truth), 0.0, 1.0))
                    row["relight_psnr"], row["relight_ssim"] = m["psnr"], m["ssim"]
                    row["relight_time_s"] = time.time() - t
                    log("[eval] frame %d relit (time B) in %.1f s" % (frames[k].index,
                                                                     row["relight_time_s"]))
            finally:
                swap.restore()

    mean = _mean(rows)
    lighting = sun_metrics(sky, lights, R) if sky is not None else None
    if lighting:
        log("[eval] sun: %s" % ("not used" if not lighting["sun_used"] else
                                 "%.1f deg from the true time-A direction"
                                 % lighting["sun_direction_error_deg"]))
    result = {"format": "mi-invrgbl-metrics/1", "scene": str(Path(scene_xml).absolute()),
              "frames_json": str(frames.path), "selection": frames_spec,
              "lidar_response": str(scene_lidar) if scene_lidar else "default",
              "ground_truth": str(gt_dir) if gt_dir else None,
              "notes": {"psnr": "sRGB in [0, 1], peak 1; identical images = %g dB" % PSNR_CAP,
                        "albedo_rmse": "per-channel least-squares scale fit, then RMSE",
                        "lidar_intensity_rmse": "over beams that return in the observation"},
              "frames": rows, "mean": mean, "lighting": lighting}
    return result


def _read_json(path):
    try:
        with open(path) as f:
            data = json.load(f)
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def _is_metrics_file(path) -> bool:
    """Whether ``path`` is a metrics.json that ``fit`` or ``eval`` wrote (folders
    written before output markers existed)."""
    data = _read_json(path)
    return data is not None and (data.get("format") == "mi-invrgbl-metrics/1"
                                 or {"heldout_psnr", "selection", "config"} <= set(data))


def run(args):
    from .. import outdir
    scene_xml, _ = resolve_inputs(args.scene)
    out = args.output or str(Path(scene_xml).parent / "metrics.json")
    # Checked before the renders, not after them.
    outdir.check_file(out, "eval", inputs=[scene_xml], recognise=_is_metrics_file,
                      what="metrics file")
    renders = None
    if args.save_renders:
        renders = outdir.prepare(args.save_renders, "eval", inputs=[scene_xml],
                                 replace_own=True, what="--save-renders folder")
    try:
        result = evaluate(args.scene, args.frames, spp=args.spp, samples=args.samples,
                          lidar_model=args.lidar_model, baseline=not args.no_baseline,
                          relight=not args.no_relight, baseline_max_points=args.baseline_max_points,
                          save_renders=str(renders.path) if renders else None)
    except BaseException:
        if renders:
            renders.discard()
        raise
    if renders:
        renders.commit()
    # DIR/fit/metrics.json first holds what ``fit`` reported (selection,
    # response, times); keep it under "fit" instead of overwriting it.
    previous = _read_json(out)
    if previous is not None:
        if previous.get("format") != result["format"]:
            result["fit"] = previous
        elif "fit" in previous:
            result["fit"] = previous["fit"]
    outdir.write_file(out, json.dumps(_json_clean(result), indent=1), "eval",
                      inputs=[scene_xml], recognise=_is_metrics_file, what="metrics file")
    print(format_table(result["frames"], result["mean"]))
    print("[eval] wrote %s" % out)
    return 0
