"""LiDAR simulation: new sweeps of a scene from new poses, with a chosen sensor.

The edit (see ``docs/applications.md``): the scene's integrator becomes
``lidar_return`` (with the fitted sensor response when the scene folder has
the fit's ``scene_lidar.xml``) and one ``lidar`` sensor is added; each pose of
the trajectory moves that sensor (``mi.traverse``) and renders one sweep.

Per pose ``N`` the outputs are

* ``frame_NNNN.bin`` -- KITTI Velodyne layout: float32 ``x y z intensity`` in
  the sensor frame (x forward, y left, z up), one record per returning beam;
* ``frame_NNNN.exr`` -- the range image (rows = beams, top first; columns =
  azimuth steps) with channels intensity, range, hit, lidar_albedo, alpha;
* ``frame_NNNN.png`` / ``frame_NNNN_range.png`` -- previews.

Intensities are the integrator's ``I`` times ``intensity_scale``, clipped to
[0, 1] as KITTI stores reflectance. Ray drop is the integrator's ``hit``
channel (no surface within range, or too little opacity), optionally with
random drops at ``drop_rate`` (real sensors lose a few percent of returns).

The synthetic street's ground truth (``gt/scene_*.xml``) renders with stock
BSDFs whose LiDAR albedo is not their RGB albedo. When the scene folder holds
the generator's ``materials.json``, each mesh's BSDF is swapped for a
``cooktorrance`` carrying its true LiDAR albedo (the road's from its LiDAR
texture), and the intensity scale, range limits and azimuth count come from
its ``trajectory.json`` -- so the simulation reproduces the generator's scans.
"""

from __future__ import annotations

import json
import os
import xml.etree.ElementTree as ET

import numpy as np

from ..errors import UserError
from ..scene import xml
from ..scene.xml import SceneDoc

#: Azimuth steps per sweep of the presets (KITTI's HDL-64E: about 2000 at 10 Hz;
#: Velodyne's VLP models: 0.2 degrees at 10 Hz).
PRESET_STEPS = {"hdl64": 2048, "vlp32": 1800, "vlp16": 1800}
#: Channels of the lidar_return integrator (and of the EXR).
CHANNELS = ("intensity", "range", "hit", "lidar_albedo", "alpha")


class SensorSpec:
    """A LiDAR's scan pattern: ``lidar`` plugin parameters plus its film size."""

    def __init__(self, params: dict, width: int, height: int, name: str):
        self.params = params
        self.width, self.height = int(width), int(height)
        self.name = name

    def element(self, ident: str, pose) -> ET.Element:
        children = []
        for key, value in self.params.items():
            kind = "float" if isinstance(value, float) else "string"
            children.append(xml.param(kind, key, value))
        children += [xml.transform(pose), xml.film(self.width, self.height)]
        return xml.element("sensor", "lidar", ident, children)


def sensor_spec(name: str, azimuth_steps: int | None, recorded: dict | None, out_dir: str,
                near: float | None = None, far: float | None = None) -> SensorSpec:
    """``--sensor`` (``scene``, ``hdl64``, ``vlp32``, ``vlp16`` or a JSON file) as a spec."""
    params = {}
    if name == "scene":
        if recorded is None:
            name = "hdl64"
        else:
            params["elevations"] = ", ".join("%.6g" % e for e in recorded["elevations_deg"])
            width = azimuth_steps or recorded["azimuth_steps"]
            height = len(recorded["elevations_deg"])
            near = recorded.get("near") if near is None else near
            far = recorded.get("far") if far is None else far
            label = "the scene's LiDAR"
    if name in PRESET_STEPS:
        from ..plugins.lidar import PRESETS
        params["preset"] = name
        width, height = azimuth_steps or PRESET_STEPS[name], len(PRESETS[name])
        label = name
    elif name != "scene":
        params, width, height, near, far = _custom_sensor(name, azimuth_steps, out_dir, near, far)
        label = name
    if width < 1:
        raise UserError("--azimuth-steps must be at least 1")
    if near is not None:
        params["near_clip"] = float(near)
    if far is not None:
        params["far_clip"] = float(far)
    return SensorSpec(params, width, height, label)


def _custom_sensor(path, azimuth_steps, out_dir, near, far):
    if not path.endswith(".json"):
        raise UserError("--sensor %s: expected hdl64, vlp32, vlp16, scene or a .json file" % path)
    try:
        with open(path) as f:
            spec = json.load(f)
    except OSError as exc:
        raise UserError("--sensor %s: cannot read (%s)" % (path, exc.strerror)) from None
    except ValueError as exc:
        raise UserError("--sensor %s: not valid JSON (%s)" % (path, exc)) from None
    if not isinstance(spec, dict):
        raise UserError("--sensor %s: expected a JSON object" % path)
    near = spec.get("near_clip", near)
    far = spec.get("far_clip", far)
    width = int(azimuth_steps or spec.get("azimuth_steps", 1024))
    if "elevations_deg" in spec:
        elev = np.asarray(spec["elevations_deg"], np.float64).ravel()
        if elev.size == 0 or not np.all(np.abs(elev) <= 90):
            raise UserError("--sensor %s: 'elevations_deg' must list angles in [-90, 90]" % path)
        return {"elevations": ", ".join("%.6g" % e for e in elev)}, width, elev.size, near, far
    if "beams" in spec:
        return ({"fov_up": float(spec.get("fov_up", 2.0)), "fov_down": float(spec.get("fov_down", -24.9))},
                width, int(spec["beams"]), near, far)
    if "rays" in spec:
        rays = np.asarray(spec["rays"], np.float64)
        if rays.ndim != 2 or rays.shape[1] != 6 or rays.shape[0] == 0:
            raise UserError("--sensor %s: 'rays' must be a list of [ox, oy, oz, dx, dy, dz]" % path)
        os.makedirs(out_dir, exist_ok=True)
        npy = os.path.join(out_dir, "sensor_rays.npy")
        np.save(npy, rays)
        return {"rays": os.path.abspath(npy)}, rays.shape[0], 1, near, far
    raise UserError("--sensor %s: give 'elevations_deg', 'beams' (+ 'fov_up', 'fov_down') or 'rays'"
                    % path)


def recorded_sensor(scene_path: str) -> dict | None:
    """The LiDAR an imported/fitted or synthetic scene was recorded with (or None)."""
    from .frames import find_frames_json
    frames = find_frames_json(scene_path)
    if frames is not None:
        with open(frames) as f:
            lidar = json.load(f).get("lidar", {})
        if lidar.get("elevations_deg") and lidar.get("azimuth_steps"):
            return {"elevations_deg": [float(e) for e in lidar["elevations_deg"]],
                    "azimuth_steps": int(lidar["azimuth_steps"])}
    info = synthetic_info(scene_path)
    if info is not None:
        lidar = info["lidar"]
        top, bottom = lidar["elevation_deg"]
        return {"elevations_deg": list(np.linspace(top, bottom, int(lidar["beams"]))),
                "azimuth_steps": int(lidar["azimuth_steps"]),
                "near": float(lidar.get("min_range", 0.5)), "far": float(lidar.get("far_range", 120.0))}
    return None


def synthetic_info(scene_path: str) -> dict | None:
    """The generator's trajectory.json beside a synthetic ground-truth scene (or None)."""
    from .frames import origin_scene
    path = os.path.join(os.path.dirname(origin_scene(scene_path)), "trajectory.json")
    if not os.path.isfile(path):
        return None
    with open(path) as f:
        info = json.load(f)
    return info if "lidar" in info else None


def default_intensity_scale(scene_path: str) -> float:
    info = synthetic_info(scene_path)
    return float(info["lidar"].get("intensity_scale", 1.0)) if info else 1.0


# ---------------------------------------------------------------- the edit


def lidar_integrator(doc: SceneDoc, model: str | None) -> tuple[ET.Element, str]:
    """The ``lidar_return`` integrator to use, and where its parameters come from."""
    import copy
    from .frames import origin_scene
    own = doc.integrator()
    fitted = os.path.join(os.path.dirname(origin_scene(doc.path)), "scene_lidar.xml")
    if own is not None and own.get("type") == "lidar_return":
        elem, source = copy.deepcopy(own), doc.path
    elif os.path.isfile(fitted) and os.path.abspath(fitted) != doc.path:
        fit_doc = SceneDoc.load(fitted)
        found = fit_doc.integrator()
        if found is None or found.get("type") != "lidar_return":
            raise UserError("%s: expected a lidar_return integrator (the fitted LiDAR response)"
                            % fitted)
        elem, source = copy.deepcopy(found), fitted
    else:
        elem, source = xml.element("integrator", "lidar_return"), "defaults (paper's cos/d^2)"
    if model is not None:
        xml.set_child_param(elem, "string", "model", model)
    return elem, source


def fit_beam_gains(integrator: ET.Element, beams: int, log=print) -> None:
    """Fitted per-beam gains only apply to the same beam count: else use their mean."""
    gains = xml.child_param(integrator, "beam_gains")
    if gains is None or "$" in gains:
        return
    values = [float(v) for v in gains.replace(",", " ").split()]
    if len(values) > 1 and len(values) != beams:
        mean = float(np.mean(values))
        xml.set_child_param(integrator, "string", "beam_gains", "%.6g" % mean)
        log("[lidar] the fitted response has %d beam gains but the sensor %d beams: "
            "using their mean %.4g" % (len(values), beams, mean))


def true_lidar_materials(doc: SceneDoc, materials_json: str) -> int:
    """Swap the synthetic street's BSDFs for ``cooktorrance`` with the true LiDAR albedo.

    Returns the number of BSDFs replaced (see the module docstring).
    """
    with open(materials_json) as f:
        table = json.load(f)
    folder = os.path.dirname(os.path.abspath(materials_json))   # texture paths are relative to it
    replaced = 0
    for name, mat in table.get("materials", {}).items():
        elem = doc.by_id("mat_%s" % name)
        if elem is None or elem.tag != "bsdf":
            continue
        children = []
        if mat.get("albedo_texture"):
            children.append(_bitmap("albedo", os.path.join(folder, mat["albedo_texture"]), False))
        else:
            children.append(xml.rgb("albedo", mat["albedo"]))
        children.append(xml.param("float", "roughness", max(float(mat["roughness"]), 1e-3)))
        if mat.get("lidar_texture"):
            children.append(_bitmap("lidar_albedo", os.path.join(folder, mat["lidar_texture"]), True))
        else:
            children.append(xml.param("float", "lidar_albedo", mat["lidar_albedo"]))
        children.append(xml.param("float", "f0", mat.get("f0", 0.04)))
        new = xml.element("bsdf", "cooktorrance", elem.get("id"), children)
        parent = next(p for p in doc.root.iter() if elem in list(p))
        index = list(parent).index(elem)
        parent.remove(elem)
        parent.insert(index, new)
        replaced += 1
    return replaced


def _bitmap(name, path, raw):
    children = [xml.param("string", "filename", path),
                xml.param("string", "filter_type", "bilinear")]
    if raw:
        children.append(xml.param("boolean", "raw", True))
    e = xml.element("texture", "bitmap", None, children)
    e.set("name", name)
    return e


def lidar_doc(doc: SceneDoc, spec: SensorSpec, first_pose, model=None, log=print):
    """The edited scene: ``lidar_return`` integrator plus one ``lidar`` sensor ``lidar_sim``."""
    out = doc.copy()
    integrator, source = lidar_integrator(doc, model)
    fit_beam_gains(integrator, spec.height, log)
    out.set_integrator(integrator)
    log("[lidar] LiDAR response from %s" % source)
    from .frames import origin_scene
    materials = os.path.join(os.path.dirname(origin_scene(doc.path)), "materials.json")
    if os.path.isfile(materials):
        n = true_lidar_materials(out, materials)
        if n:
            log("[lidar] synthetic street: %d BSDFs carry their true LiDAR albedo (%s)" % (n, materials))
    ident = out.unique_id("lidar_sim")
    out.add(spec.element(ident, first_pose),
            "simulated %s; moved to each pose of the trajectory" % spec.name)
    return out, ident


# ------------------------------------------------------------------ output


def sweep_outputs(image: np.ndarray, directions: np.ndarray, intensity_scale: float,
                  drop_rate: float, rng) -> dict:
    """Range-image channels and KITTI points of one rendered sweep.

    ``image`` is the integrator's (H, W, 5) output; ``directions`` the sensor's
    (H, W, 3) unit beam directions in its own frame.
    """
    image = np.array(image, np.float32)
    hit = image[..., 2] > 0.5
    if drop_rate > 0:
        hit &= rng.random(hit.shape) >= drop_rate
    image[..., 0] = np.where(hit, np.clip(image[..., 0] * intensity_scale, 0.0, 1.0), 0.0)
    image[..., 1] = np.where(hit, image[..., 1], 0.0)
    image[..., 2] = hit
    image[..., 3] = np.where(hit, image[..., 3], 0.0)
    points = directions[hit] * image[..., 1][hit][:, None]
    return {"image": image, "points": points.astype(np.float32), "intensity": image[..., 0][hit],
            "hit": hit}


def preview(image: np.ndarray, rows: int = 3) -> np.ndarray:
    """Grey intensity over range, each row repeated ``rows`` times: an 8-bit RGB frame."""
    out = []
    hit = image[..., 2] > 0
    for ch in (0, 1):
        v = np.where(hit, image[..., ch], 0.0)
        top = np.percentile(v[hit], 99) if hit.any() else 1.0
        grey = (np.clip(v / max(top, 1e-12), 0, 1) ** (1 / 2.2) * 255 + 0.5).astype(np.uint8)
        out.append(np.repeat(grey, rows, axis=0))
    both = np.concatenate(out, axis=0)
    return np.repeat(both[..., None], 3, axis=2)
