"""Loading a scene file: ``mi.load_file`` with one clear error line.

``load_scene(path, defines)`` is how every command and library loads a
Mitsuba scene; ``parse_defines`` reads ``-D KEY=VALUE`` options into the
``defines`` (``<default>`` parameters of the XML); ``is_lidar`` tells the
package's ``lidar`` sensors from cameras.
"""

from __future__ import annotations

import os

from ..errors import UserError, mitsuba_message


def parse_defines(defines) -> dict:
    """``["spp=4", "samples=16"]`` -> ``{"spp": "4", "samples": "16"}``."""
    out = {}
    for item in defines or []:
        if "=" not in item:
            raise UserError("-D expects KEY=VALUE, got '%s'" % item)
        key, value = item.split("=", 1)
        out[key.strip()] = value.strip()
    return out


def load_scene(path, defines=None):
    """``mi.load_file`` with one clear error for a missing or broken file."""
    import mitsuba as mi
    path = str(path)
    if not os.path.isfile(path):
        raise UserError("%s: scene file not found" % path)
    try:
        return mi.load_file(path, **(defines or {}))
    except Exception as exc:  # Mitsuba reports parse and plugin errors as RuntimeError
        raise UserError("%s: cannot load scene: %s" % (path, mitsuba_message(exc))) from None


def is_lidar(sensor) -> bool:
    """Whether a loaded sensor is the package's ``lidar`` sensor."""
    return type(sensor).__name__ == "LidarSensor" or sensor.class_name() == "LidarSensor"
