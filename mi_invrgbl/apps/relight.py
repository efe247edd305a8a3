"""Relighting: the scene's sky and sun replaced, shadows traced for the new sun.

The edit (see ``docs/applications.md``): the scene's sky/sun emitters
(``shsun``, or stock ``constant`` + ``directional`` ...) become one ``shsun``
holding the new lighting, and an ``invrgbl`` integrator is told to trace the
sun's visibility (``sun_visibility = trace``) so that shadows follow the new
sun rather than the fitted per-Gaussian visibility of the old one. Stock
integrators (``path``) always trace shadows.
"""

from __future__ import annotations

import numpy as np

from ..errors import UserError
from . import lighting_edit, solar
from .lighting_edit import Lighting
from ..scene.xml import SceneDoc


def new_lighting(base: Lighting | None, *, elevation=None, azimuth=None, time=None,
                 date=None, utc_offset=None, latitude=None, longitude=None, north=90.0,
                 light_from=None, sun_irradiance=None, sky_radiance=None, sky_scale=None,
                 log=print) -> Lighting:
    """The lighting a ``relight`` call asks for (see ``mi-invrgbl relight --help``)."""
    modes = [m for m, v in (("--sun-elevation/--sun-azimuth", elevation is not None or azimuth is not None),
                            ("--time", time is not None), ("--light-from", light_from is not None))
             if v]
    if len(modes) > 1:
        raise UserError("give only one of %s" % ", ".join(modes))
    if light_from is not None:
        lighting = lighting_edit.read_lighting(light_from)
    else:
        if base is None:
            if sky_radiance is None:
                raise UserError("the scene has no sky or sun to start from: give --sky-radiance "
                                "(and --sun-irradiance) or --light-from")
            base = Lighting.constant_sky(sky_radiance)
        lighting = base
        if time is not None or elevation is not None or azimuth is not None:
            if time is not None:
                lat, lon, _ = solar.KARLSRUHE
                lat = lat if latitude is None else latitude
                lon = lon if longitude is None else longitude
                when = solar.parse_time(time, date, utc_offset)
                elevation, compass = solar.solar_position(when, lat, lon)
                azimuth = solar.world_azimuth(compass, north)
                log("[relight] sun at %s, %.2f N %.2f E: elevation %.1f deg, compass azimuth "
                    "%.1f deg = world azimuth %.1f deg" % (when.isoformat(), lat, lon, elevation,
                                                           compass, azimuth))
                if elevation <= 0.0:
                    raise UserError("--time %s: the sun is below the horizon (elevation %.1f deg); "
                                    "use 'mi-invrgbl night' for a night scene" % (time, elevation))
            else:
                old_e, old_a = lighting_edit.angles_from_direction(base.sun_direction)
                elevation = old_e if elevation is None else elevation
                azimuth = old_a if azimuth is None else azimuth
                if not -90.0 <= elevation <= 90.0:
                    raise UserError("--sun-elevation must lie in [-90, 90] degrees, got %g" % elevation)
            if not base.has_sun and sun_irradiance is None:
                raise UserError("the scene has no sun (irradiance 0): give --sun-irradiance R,G,B "
                                "for the new one")
            lighting = lighting.with_sun(lighting_edit.direction_from_angles(elevation, azimuth))
    if sun_irradiance is not None:
        lighting = lighting.replace(sun_irradiance=_rgb(sun_irradiance, "--sun-irradiance"))
    if sky_radiance is not None:
        lighting = lighting.replace(sh=Lighting.constant_sky(_rgb(sky_radiance, "--sky-radiance")).sh)
    if sky_scale is not None:
        if sky_scale < 0:
            raise UserError("--sky-scale must be >= 0, got %g" % sky_scale)
        lighting = lighting.replace(sh=np.asarray(lighting.sh) * sky_scale)
    return lighting


def _rgb(value, what):
    v = np.asarray(value, np.float64).ravel()
    if v.size == 1:
        v = np.repeat(v, 3)
    if v.size != 3 or not np.all(np.isfinite(v)) or np.any(v < 0):
        raise UserError("%s: expected one or three non-negative numbers" % what)
    return v


def relight_doc(doc: SceneDoc, lighting: Lighting) -> SceneDoc:
    """A copy of ``doc`` lit by ``lighting`` (see the module docstring)."""
    out = doc.copy()
    lighting_edit.replace_lighting(out, lighting, "relit: %s" % lighting.describe())
    lighting_edit.trace_sun_visibility(out)
    return out
