"""Lighting of the three renders: time A (training), time B (relighting truth), night.

Days use Mitsuba's stock ``directional`` sun plus a ``constant`` sky. A constant
sky (rather than ``sunsky``, which 3.9.1 also has) keeps the ground truth exact
and small: it is the order-0 term of the fit's spherical-harmonics sky, and
the sun is a delta light whose direction and irradiance ``lights.json`` gives
in full. Night switches the sun off, dims the sky, and lights stock ``spot``
emitters at streetlight heads and on the moving car's front.
"""

from __future__ import annotations

import math

import numpy as np


def sun_direction(elevation_deg: float, azimuth_deg: float) -> tuple:
    """Unit vector *towards* the sun; azimuth from +x (along the street) towards +y."""
    e, a = math.radians(elevation_deg), math.radians(azimuth_deg)
    return (math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e))


#: Time A: high sun over the left side of the street, lighting the right facades.
TIME_A = {"name": "time_a", "elevation_deg": 55.0, "azimuth_deg": 60.0,
          "sun_irradiance": (4.0, 3.85, 3.6), "sky_radiance": (0.32, 0.38, 0.50)}
#: Time B: low, warm sun from behind on the right; long shadows across the road.
TIME_B = {"name": "time_b", "elevation_deg": 25.0, "azimuth_deg": -125.0,
          "sun_irradiance": (2.6, 1.9, 1.2), "sky_radiance": (0.22, 0.24, 0.32)}

NIGHT_SKY = (0.004, 0.005, 0.009)
STREETLIGHT_INTENSITY = (40.0, 30.0, 18.0)   #: W/sr, warm sodium-like
HEADLIGHT_INTENSITY = (25.0, 25.0, 22.0)
#: Streetlights lit at night: the nearest ones to the start of the sequence.
NIGHT_LAMPS = 3


def day(spec: dict) -> dict:
    """A day lighting as recorded in lights.json (directions in world coordinates)."""
    d = sun_direction(spec["elevation_deg"], spec["azimuth_deg"])
    return {"sun_direction": [float(c) for c in d],
            "sun_elevation_deg": spec["elevation_deg"],
            "sun_azimuth_deg": spec["azimuth_deg"],
            "sun_irradiance": list(spec["sun_irradiance"]),
            "sky_radiance": list(spec["sky_radiance"]),
            "emitters": "directional (sun) + constant (sky)"}


def night(lamps, headlights) -> dict:
    """Night lighting: dim sky, the first streetlights, the moving car's headlights."""
    return {"sky_radiance": list(NIGHT_SKY),
            "streetlights": [{"position": list(map(float, p)), "direction": list(map(float, d)),
                              "intensity": list(STREETLIGHT_INTENSITY),
                              "cutoff_angle": 60.0, "beam_width": 40.0}
                             for p, d in lamps[:NIGHT_LAMPS]],
            "headlights": [{"position_car_frame": list(map(float, p)),
                            "direction_car_frame": list(map(float, d)),
                            "intensity": list(HEADLIGHT_INTENSITY),
                            "cutoff_angle": 25.0, "beam_width": 15.0}
                           for p, d in headlights],
            "emitters": "constant (sky) + spot (streetlights, headlights)"}


def all_lights(lamps, headlights) -> dict:
    return {"time_a": day(TIME_A), "time_b": day(TIME_B), "night": night(lamps, headlights),
            "frame": "world: z up, x along the street, y left; sun_direction points towards the sun"}


def sun_a_direction() -> np.ndarray:
    return np.array(sun_direction(TIME_A["elevation_deg"], TIME_A["azimuth_deg"]))
