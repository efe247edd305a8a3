"""A scene's sky and sun as one value, read from any scene and written as ``shsun``.

Relighting swaps a scene's sky + sun for another: a new sun direction, the
lighting of another scene (``--light-from``) or of the synthetic street's
``lights.json``. :class:`Lighting` holds what our ``shsun`` emitter holds (SH
sky coefficients, sun direction, irradiance and angular radius), so every
lighting becomes one ``<emitter type="shsun">`` element that renders in our
``invrgbl`` integrator and in Mitsuba's stock ``path`` alike.

Reading a scene's lighting accepts what street scenes use:

* ``shsun`` -- taken as is;
* ``constant`` -- an order-0 SH sky (exact);
* ``directional`` -- the sun (a delta light becomes a 0.265 degree disk of the
  same irradiance; shadows soften by that half-degree, as real ones do);
* any other environment (``envmap``, ``sunsky``) -- projected onto SH order 3
  (a smooth approximation: a sun baked into such a map is blurred).

Only the scene's emitters are loaded to read them, never its shapes, so
reading the lighting of a large fitted scene is quick.

World convention (the project's): z up; a direction's azimuth is measured
from +x towards +y, its elevation from the horizontal plane upwards.
``sun_direction`` points *towards* the sun.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import xml.etree.ElementTree as ET

import numpy as np

from ..errors import UserError
from ..scene import xml
from ..scene.xml import SKY_TYPES, SceneDoc

#: Angular radius (degrees) of the real sun, used for directional lights.
SUN_RADIUS_DEG = 0.265
#: SH order used to approximate environment maps other than ``constant``/``shsun``.
PROJECTION_ORDER = 3


def direction_from_angles(elevation_deg: float, azimuth_deg: float) -> np.ndarray:
    """Unit vector towards elevation/azimuth (azimuth from +x towards +y)."""
    e, a = math.radians(elevation_deg), math.radians(azimuth_deg)
    return np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])


def angles_from_direction(d) -> tuple[float, float]:
    """(elevation, azimuth) in degrees of a direction (see :func:`direction_from_angles`)."""
    d = np.asarray(d, np.float64) / np.linalg.norm(d)
    return (math.degrees(math.asin(max(-1.0, min(1.0, d[2])))),
            math.degrees(math.atan2(d[1], d[0])))


@dataclasses.dataclass
class Lighting:
    """Sky (real SH, (K,3) coefficients) plus a sun; see the module docstring."""

    sh: np.ndarray
    sun_direction: np.ndarray = dataclasses.field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    sun_irradiance: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    sun_radius: float = SUN_RADIUS_DEG
    source: str = ""

    @staticmethod
    def constant_sky(radiance, **kw) -> "Lighting":
        from ..physics.sh import Y0
        return Lighting(sh=np.asarray(radiance, np.float64).reshape(1, 3) / Y0, **kw)

    @property
    def has_sun(self) -> bool:
        return bool(np.any(np.asarray(self.sun_irradiance) > 0))

    @property
    def has_sky(self) -> bool:
        return bool(np.any(np.asarray(self.sh) != 0))

    def replace(self, **kw) -> "Lighting":
        return dataclasses.replace(self, **kw)

    def with_sun(self, direction, irradiance=None) -> "Lighting":
        d = np.asarray(direction, np.float64)
        d = d / np.linalg.norm(d)
        irr = self.sun_irradiance if irradiance is None else np.asarray(irradiance, np.float64)
        return self.replace(sun_direction=d, sun_irradiance=np.broadcast_to(irr, (3,)).copy())

    def sky_radiance_mean(self) -> np.ndarray:
        """Mean sky radiance over the sphere (RGB): ``c0 Y0``."""
        from ..physics.sh import Y0
        return np.asarray(self.sh, np.float64)[0] * Y0

    def emitter_element(self, ident: str = "sky") -> ET.Element:
        """This lighting as an ``<emitter type="shsun">`` element."""
        from ..physics.sh import order_from_count
        sh = np.asarray(self.sh, np.float64).reshape(-1, 3)
        return xml.shsun_emitter(ident, sh, order_from_count(sh.shape[0]), self.sun_direction,
                                 self.sun_irradiance, self.sun_radius)

    def describe(self) -> str:
        sky = self.sky_radiance_mean()
        text = "sky mean radiance (%.3g, %.3g, %.3g)" % tuple(sky)
        if self.has_sun:
            e, a = angles_from_direction(self.sun_direction)
            text += ", sun at elevation %.1f deg, azimuth %.1f deg, irradiance (%.3g, %.3g, %.3g)" \
                % ((e, a) + tuple(self.sun_irradiance))
        else:
            text += ", no sun"
        return text


# ------------------------------------------------------------------ reading


def lights_only_scene(doc: SceneDoc):
    """Load only the emitters (and top-level textures, defaults) of ``doc``."""
    return xml.load_parts(doc, ("texture", "emitter"), "its emitters")


def lighting_of_scene(scene, source: str = "") -> Lighting | None:
    """The sky + sun of a loaded scene (None if it has neither); see module docstring."""
    import drjit as dr
    import mitsuba as mi
    from ..physics.sh import num_coeffs, project_sh
    sh = None
    suns = []   # (direction, irradiance, radius)

    def add_sky(coeffs):
        nonlocal sh
        coeffs = np.asarray(coeffs, np.float64).reshape(-1, 3)
        if sh is None:
            sh = coeffs
        else:  # sum of two skies: pad the lower order with zeros
            k = max(len(sh), len(coeffs))
            out = np.zeros((k, 3))
            out[:len(sh)] += sh
            out[:len(coeffs)] += coeffs
            sh = out

    for emitter in scene.emitters():
        name = emitter.class_name()
        if hasattr(emitter, "sh_coefficients"):            # our shsun
            if np.allclose(emitter._local_from_world, np.eye(3)):
                add_sky(emitter.sh_coefficients())
            else:   # a rotated sky: re-express it in the world frame
                add_sky(project_sh(lambda d: _eval_sky(emitter, d), emitter.order, 64))
            if emitter.has_sun():
                suns.append((np.array(dr.detach(emitter.sun_direction_world()), np.float64).ravel(),
                             np.array(dr.detach(emitter.sun_irradiance_value()), np.float64).ravel(),
                             emitter.sun_radius()))
        elif name == "DirectionalEmitter":
            m = np.array(emitter.world_transform().matrix, np.float64).reshape(4, 4)
            travel = m[:3, 2]
            params = mi.traverse(emitter)
            irr = np.array(params["irradiance.value"], np.float64).ravel() \
                if "irradiance.value" in params else np.ones(3)
            suns.append((-travel / np.linalg.norm(travel), np.broadcast_to(irr, (3,)).copy(),
                         SUN_RADIUS_DEG))
        elif name == "ConstantBackgroundEmitter":
            add_sky(project_sh(lambda d: _eval_env(emitter, d), 0, 8)[:num_coeffs(0)])
        elif mi.has_flag(emitter.flags(), mi.EmitterFlags.Infinite):
            add_sky(project_sh(lambda d: _eval_env(emitter, d), PROJECTION_ORDER, 64))
    if sh is None and not suns:
        return None
    if sh is None:
        sh = np.zeros((1, 3))
    lighting = Lighting(sh=sh, source=source)
    if suns:
        # shsun holds one sun: keep the brightest (street scenes have one).
        d, irr, radius = max(suns, key=lambda s: float(np.mean(s[1])))
        lighting = lighting.replace(sun_direction=d / np.linalg.norm(d), sun_irradiance=irr,
                                    sun_radius=float(radius))
    return lighting


def _eval_env(emitter, dirs):
    import drjit as dr
    import mitsuba as mi
    d = np.asarray(dirs, np.float32)
    si = dr.zeros(mi.SurfaceInteraction3f, d.shape[0])
    si.wi = -mi.Vector3f(d[:, 0], d[:, 1], d[:, 2])
    value = np.array(emitter.eval(si), np.float64).reshape(3, -1).T
    # A constant emitter returns one value, not one per direction.
    return np.broadcast_to(value, (d.shape[0], 3)).copy()


def _eval_sky(emitter, dirs):
    import mitsuba as mi
    d = np.asarray(dirs, np.float32)
    value = emitter.sky_radiance(mi.Vector3f(d[:, 0], d[:, 1], d[:, 2]))
    return np.array(value, np.float64).reshape(3, -1).T


def lighting_of_doc(doc: SceneDoc) -> Lighting | None:
    """The sky + sun of a scene file (only its emitters are loaded)."""
    return lighting_of_scene(lights_only_scene(doc), source=doc.path)


def lighting_from_lights_json(path: str, key: str) -> Lighting:
    """A day lighting (``time_a``/``time_b``) or ``night`` sky of the street generator's lights.json."""
    try:
        with open(path) as f:
            info = json.load(f)
    except (OSError, ValueError) as exc:
        raise UserError("%s: cannot read lights (%s)" % (path, exc)) from None
    if key not in info or not isinstance(info[key], dict) or "sky_radiance" not in info[key]:
        keys = [k for k, v in info.items() if isinstance(v, dict) and "sky_radiance" in v]
        raise UserError("%s: no lighting '%s' (has: %s)" % (path, key, ", ".join(keys)))
    spec = info[key]
    lighting = Lighting.constant_sky(spec["sky_radiance"], source="%s:%s" % (path, key))
    if "sun_direction" in spec:
        lighting = lighting.with_sun(spec["sun_direction"], spec["sun_irradiance"])
    return lighting


def read_lighting(spec: str) -> Lighting:
    """``--light-from`` value: a scene XML, or ``lights.json:KEY``."""
    path, key = spec, None
    if not os.path.isfile(spec) and ":" in spec:
        path, key = spec.rsplit(":", 1)
    if path.endswith(".json"):
        return lighting_from_lights_json(path, key or "time_a")
    doc = SceneDoc.load(path)
    lighting = lighting_of_doc(doc)
    if lighting is None or not (lighting.has_sky or lighting.has_sun):
        raise UserError("%s: the scene has no sky or sun to copy (no shsun, constant, envmap "
                        "or directional emitter)" % path)
    return lighting


# ------------------------------------------------------------------ writing


def sky_emitters(doc: SceneDoc) -> list[ET.Element]:
    return doc.children("emitter", SKY_TYPES)


def replace_lighting(doc: SceneDoc, lighting: Lighting, comment: str = "") -> None:
    """Swap ``doc``'s sky and sun emitters for one ``shsun`` holding ``lighting``.

    Other emitters (spot, point, area lights, the LiDAR's laser) stay.
    """
    for e in sky_emitters(doc):
        doc.remove(e)
    ident = doc.unique_id("sky")
    doc.add(lighting.emitter_element(ident), comment or "sky + sun: %s" % lighting.describe())


def trace_sun_visibility(doc: SceneDoc) -> bool:
    """Make an ``invrgbl`` integrator trace sun shadows (a fit may store them instead).

    Returns whether the scene's integrator is ``invrgbl``.
    """
    integrator = doc.integrator()
    if integrator is None or integrator.get("type") != "invrgbl":
        return False
    xml.set_child_param(integrator, "string", "sun_visibility", "trace")
    return True
