"""Rendering for evaluation: a frame's camera and LiDAR, and a swapped sky.

:func:`render_camera` returns linear RGB and the ``invrgbl`` AOVs by channel
name; :func:`render_lidar` the ``lidar_return`` channels by name;
:func:`load_lidar_integrator` reads the fitted LiDAR integrator from
``scene_lidar.xml``; :func:`integrator_like` changes the sample count or the
sun-visibility mode of a scene's ``invrgbl`` integrator; :class:`SkySwap`
sets a ``shsun`` emitter to another light and back.
"""

from __future__ import annotations

import drjit as dr
import numpy as np

from ..errors import UserError
from ..scene.xml import SceneDoc, load_parts, set_child_param


def load_lidar_integrator(scene_lidar, model=None):
    """The ``lidar_return`` integrator of ``scene_lidar.xml`` (only its
    ``<integrator>`` and ``<default>`` elements are loaded), or a default one."""
    import mitsuba as mi
    if scene_lidar is None:
        return mi.load_dict({"type": "lidar_return", "model": model or "pbr"})
    doc = SceneDoc.load(str(scene_lidar))
    integ = doc.integrator()
    if integ is None:
        raise UserError("%s: no <integrator> element" % scene_lidar)
    if integ.get("type") != "lidar_return":
        raise UserError("%s: the integrator is '%s', expected lidar_return"
                        % (scene_lidar, integ.get("type")))
    if model is not None:
        set_child_param(integ, "string", "model", model)
    return load_parts(doc, ("integrator",), "the lidar_return integrator").integrator()


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
    """A ``lidar_return`` render as {channel name: (beams, azimuth) array}."""
    import mitsuba as mi
    from ..plugins.lidar_return import CHANNELS
    arr = np.array(mi.render(scene, sensor=sensor, integrator=integrator), np.float64)
    return {k: arr[..., i] for i, k in enumerate(CHANNELS) if i < arr.shape[2]}


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
    return mi.load_dict(dict(integ.settings(), samples=int(samples or integ.samples),
                             sun_visibility=sun_visibility or integ.sun_visibility))


def find_sky(scene):
    """The scene's ``shsun`` emitter (None if it has none)."""
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

    def put(self, light, R):
        """A ground-truth light (a ``lights.json`` entry: constant
        ``sky_radiance``, ``sun_direction`` in the truth's world,
        ``sun_irradiance``; missing parts off), the direction turned into
        the scene's world by ``R``."""
        self.set(light.get("sky_radiance", [0, 0, 0]),
                 R @ np.asarray(light.get("sun_direction", [0, 0, 1]), np.float64),
                 light.get("sun_irradiance", [0, 0, 0]))

    def edit(self, sky_ratio, sun_direction, sun_ratio):
        """The saved (fitted) light edited as ``mi-invrgbl relight`` edits it:
        the sun turned to ``sun_direction``, every SH coefficient of the sky
        scaled by ``sky_ratio`` (per channel) and the sun's irradiance by
        ``sun_ratio``. The fitted light keeps its own level and shape; only
        the change is the caller's."""
        sh = np.array(self.saved["sh"], np.float64).reshape(-1, 3) * np.asarray(sky_ratio, np.float64)
        irr = np.array(self.saved["sun_irradiance"], np.float64).ravel() * np.asarray(sun_ratio, np.float64)
        self.params["sh"] = type(self.params["sh"])(sh.ravel().astype(np.float32))
        self.params["sun_direction"] = type(self.params["sun_direction"])(
            *[float(v) for v in sun_direction])
        self.params["sun_irradiance"] = type(self.params["sun_irradiance"])(*[float(v) for v in irr])
        self.params.update()

    def restore(self):
        for k, v in self.saved.items():
            self.params[k] = v
        self.params.update()
