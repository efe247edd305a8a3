"""Night: no sun, a dim sky, headlights at the camera and streetlights.

The edit (see ``docs/applications.md``): the sky/sun become a ``shsun`` with
zero sun irradiance and the sky scaled down; stock ``spot`` emitters are added
for the streetlights (pointing down) and the ego car's headlights (at the
camera, moved with it every frame). Spot lights have the ``1/d^2`` falloff of
a point source and a smooth angular cut-off, and both the ``invrgbl``
integrator (Gaussians and meshes) and Mitsuba's ``path`` render them with
traced shadows.

Streetlight positions, in order of preference: ``--streetlight X,Y,Z``
options; the synthetic street's own night lamps (``lights.json`` beside the
scene or in the ground-truth folder named by ``frames.json``); otherwise
lamps along the camera path, every ``spacing`` metres, alternately left and
right of it, ``height`` metres above the road (taken 1.65 m below the camera,
KITTI's camera height).
"""

from __future__ import annotations

import dataclasses
import json
import os

import numpy as np

from ..errors import UserError
from . import lighting_edit
from ..scene import xml
from ..scene.xml import spot_to_world
from .lighting_edit import Lighting
from ..scene.xml import SceneDoc

#: KITTI's camera height above the road (m): where the road is, seen from a camera.
CAMERA_HEIGHT = 1.65


@dataclasses.dataclass
class SpotSpec:
    """One kind of spot light: colour x intensity (W/sr) and the cone."""

    intensity: float
    colour: tuple
    cutoff: float       #: degrees from the axis where the light ends
    beam_width: float   #: degrees from the axis where the fall-off starts

    def rgb(self) -> np.ndarray:
        c = np.asarray(self.colour, np.float64)
        return self.intensity * c / max(float(c.max()), 1e-12)

    def check(self, what: str) -> "SpotSpec":
        c = np.asarray(self.colour, np.float64).ravel()
        if c.size != 3 or np.any(c < 0) or not np.any(c > 0):
            raise UserError("--%s-colour: expected three non-negative numbers, not all 0" % what)
        if not self.intensity >= 0:
            raise UserError("--%s-intensity must be >= 0" % what)
        if not 0 < self.cutoff <= 90:
            raise UserError("--%s-cutoff must lie in (0, 90] degrees" % what)
        self.beam_width = min(self.beam_width, self.cutoff)
        return self


#: Defaults: warm sodium-like streetlights and white headlights (the synthetic street's).
STREETLIGHT = SpotSpec(40.0, (1.0, 0.75, 0.45), 60.0, 40.0)
HEADLIGHT = SpotSpec(25.0, (1.0, 1.0, 0.88), 25.0, 15.0)
#: Metres of road ahead of the last camera where automatic streetlights may stand.
AHEAD = 60

#: Headlight positions in the Mitsuba camera frame (x left, y up, z forward):
#: 0.7 m either side, 0.95 m below the camera (about 0.7 m above the road).
HEADLIGHT_OFFSETS = {1: [(0.0, -0.95, 0.3)],
                     2: [(0.7, -0.95, 0.3), (-0.7, -0.95, 0.3)]}
#: Headlight axis in the camera frame: forward, tilted 4.6 degrees down.
HEADLIGHT_AXIS = (0.0, -0.08, 1.0)


def spot_element(ident: str, spec: SpotSpec, to_world) -> "xml.ET.Element":
    return xml.spot_emitter(ident, spec.rgb(), to_world, spec.cutoff, spec.beam_width)


def night_lighting(base: Lighting | None, sky_scale: float, sky_radiance=None) -> Lighting:
    """The sky without its sun, dimmed (or a constant ``sky_radiance``)."""
    if sky_radiance is not None:
        sky = Lighting.constant_sky(sky_radiance)
    elif base is not None:
        sky = base.replace(sh=np.asarray(base.sh) * sky_scale)
    else:
        sky = Lighting.constant_sky(np.zeros(3))
    return sky.replace(sun_irradiance=np.zeros(3))


# ------------------------------------------------------------ streetlights


def recorded_streetlights(scene_path: str):
    """Night lamps of the synthetic street, if this scene is (or was fitted from) one."""
    from .frames import origin_scene
    folder = os.path.dirname(origin_scene(scene_path))
    candidates = [os.path.join(folder, "lights.json")]
    from .frames import find_frames_json
    frames_json = find_frames_json(scene_path)
    if frames_json is not None:
        try:
            with open(frames_json) as f:
                gt = json.load(f).get("ground_truth", {}).get("dir")
            if gt:
                candidates.append(os.path.join(gt, "lights.json"))
        except (OSError, ValueError):
            pass
    for path in candidates:
        if os.path.isfile(path):
            with open(path) as f:
                lamps = json.load(f).get("night", {}).get("streetlights", [])
            if lamps:
                return [(np.asarray(l["position"]), np.asarray(l["direction"])) for l in lamps], path
    return None, None


def path_streetlights(cameras, count: int, spacing: float, height: float, offset: float):
    """``count`` lamps along the camera path (see the module docstring)."""
    cams = [np.asarray(c, np.float64) for c in cameras]
    pos = np.array([c[:3, 3] for c in cams])
    forward = cams[-1][:3, 2].copy()
    forward[2] = 0.0   # level: a camera tilted down must not lead the lamps into the road
    forward /= max(np.linalg.norm(forward), 1e-9)
    # Extend the path ahead of the last camera: the camera sees the lamps in front.
    ahead = pos[-1] + forward[None] * np.arange(1, AHEAD + 1)[:, None]
    path = np.concatenate([pos, ahead])
    seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    lamps = []
    for k in range(count):
        target = spacing * (k + 0.5)
        if target > s[-1]:
            break
        j = min(int(np.searchsorted(s, target)), len(path) - 1)
        cam = cams[min(j, len(cams) - 1)]
        left = cam[:3, 0] / np.linalg.norm(cam[:3, 0])   # Mitsuba cameras: +x is left
        side = 1.0 if k % 2 == 0 else -1.0
        p = path[j] + side * offset * left
        p[2] = path[j][2] - CAMERA_HEIGHT + height
        lamps.append((p, np.array([0.0, 0.0, -1.0])))
    return lamps


# -------------------------------------------------------------- headlights


def headlight_poses(camera_to_world, count: int):
    """World ``to_world`` of each headlight spot for a camera pose."""
    cam = np.asarray(camera_to_world, np.float64)
    out = []
    for offset in HEADLIGHT_OFFSETS.get(count, []):
        local = spot_to_world(offset, HEADLIGHT_AXIS)
        m = cam @ local
        # Keep the spot frame orthonormal even if the camera matrix is scaled.
        m[:3, :3] /= np.linalg.norm(m[:3, :3], axis=0, keepdims=True)
        out.append(m)
    return out


class HeadlightHook:
    """Moves the headlight emitters with each frame's camera (a render hook)."""

    def __init__(self, ids, frames):
        self.ids = list(ids)
        self.frames = frames
        self.params = None

    def __call__(self, scene, frame, sensor):
        import mitsuba as mi
        if not self.ids:
            return
        if self.params is None:
            self.params = mi.traverse(scene)
        cam = self.frames.camera_to_world(scene, frame)
        for ident, m in zip(self.ids, headlight_poses(cam, len(self.ids))):
            self.params[ident + ".to_world"] = mi.Transform4f(mi.ScalarMatrix4f(m))
        self.params.update()


def night_doc(doc: SceneDoc, lighting: Lighting, streetlights, street_spec: SpotSpec,
              headlights: int, head_spec: SpotSpec, camera0) -> tuple[SceneDoc, list]:
    """The edited scene and the ids of its headlight emitters."""
    if headlights not in HEADLIGHT_OFFSETS and headlights != 0:
        raise UserError("--headlights must be 0, 1 or 2, got %d" % headlights)
    out = doc.copy()
    lighting_edit.replace_lighting(out, lighting, "night sky: %s" % lighting.describe())
    for k, (p, d) in enumerate(streetlights):
        ident = out.unique_id("streetlight_%d" % k)
        out.add(spot_element(ident, street_spec, spot_to_world(p, d)),
                "streetlight at (%.2f, %.2f, %.2f)" % tuple(p) if k == 0 else None)
    ids = []
    for k, m in enumerate(headlight_poses(camera0, headlights)):
        ident = out.unique_id("headlight_%d" % k)
        out.add(spot_element(ident, head_spec, m),
                "headlights at the camera, moved with it every frame" if k == 0 else None)
        ids.append(ident)
    lighting_edit.trace_sun_visibility(out)
    return out, ids
