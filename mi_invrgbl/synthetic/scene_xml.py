"""The Mitsuba scene files of the street: one per lighting (time A, time B, night).

The renders load these very files (``mi.load_file``), so the XML on disk is
exactly what produced the images. Each file holds frame 0: the sensor and the
moving car (and its headlights) at their frame-0 poses; :mod:`.render` moves
them per frame through ``mi.traverse``. Meshes and textures live next to the
XML in ``meshes/`` and ``textures/``.
"""

from __future__ import annotations

import numpy as np

HEADER = '<?xml version="1.0" encoding="utf-8"?>\n<scene version="3.0.0">\n'


def matrix_xml(m: np.ndarray, name: str = "to_world") -> str:
    values = " ".join("%.9g" % v for v in np.asarray(m, dtype=np.float64).reshape(-1))
    return '<transform name="%s"><matrix value="%s"/></transform>' % (name, values)


def rgb(name: str, value) -> str:
    return '<rgb name="%s" value="%.6g %.6g %.6g"/>' % ((name,) + tuple(value))


def spot_to_world(position, direction) -> np.ndarray:
    """A frame whose +z (the spot's axis) points along ``direction``, placed at ``position``."""
    z = np.asarray(direction, dtype=np.float64)
    z = z / np.linalg.norm(z)
    helper = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, position
    return m


def headlight_to_world(car_pose: np.ndarray, light: dict) -> np.ndarray:
    local = spot_to_world(light["position_car_frame"], light["direction_car_frame"])
    return car_pose @ local


def scene_xml(kind: str, config, layout, mesh_files: dict, sensor_to_world: np.ndarray,
              car_pose0: np.ndarray, light_info: dict) -> str:
    """XML text of the scene for ``kind`` in (``time_a``, ``time_b``, ``night``)."""
    out = [HEADER,
           '<integrator type="path"><integer name="max_depth" value="%d"/></integrator>\n'
           % config.max_depth,
           '<sensor type="perspective" id="sensor">'
           '<float name="fov" value="%.9g"/><string name="fov_axis" value="x"/>'
           '<float name="near_clip" value="0.05"/><float name="far_clip" value="1000"/>%s'
           '<sampler type="independent"><integer name="sample_count" value="%d"/></sampler>'
           '<film type="hdrfilm"><integer name="width" value="%d"/>'
           '<integer name="height" value="%d"/><rfilter type="box"/>'
           '<string name="pixel_format" value="rgb"/></film></sensor>\n'
           % (config.fov, matrix_xml(sensor_to_world), config.spp, config.width, config.height)]
    for mat in layout.materials.values():
        out.append(mat.bsdf_xml(getattr(config, "bsdf", "roughplastic")) + "\n")
    for part in layout.parts:
        transform = matrix_xml(car_pose0) if part.dynamic else ""
        out.append('<shape type="ply" id="%s"><string name="filename" value="%s"/>'
                   '<boolean name="face_normals" value="true"/>%s<ref id="mat_%s"/></shape>\n'
                   % (part.name, mesh_files[part.name], transform, part.material))
    info = light_info[kind]
    if kind == "night":
        out.append('<emitter type="constant" id="sky">%s</emitter>\n'
                   % rgb("radiance", info["sky_radiance"]))
        for i, lamp in enumerate(info["streetlights"]):
            out.append('<emitter type="spot" id="streetlight_%d">%s%s'
                       '<float name="cutoff_angle" value="%g"/><float name="beam_width" value="%g"/>'
                       '</emitter>\n' % (i, rgb("intensity", lamp["intensity"]),
                                         matrix_xml(spot_to_world(lamp["position"], lamp["direction"])),
                                         lamp["cutoff_angle"], lamp["beam_width"]))
        for i, light in enumerate(info["headlights"]):
            out.append('<emitter type="spot" id="headlight_%d">%s%s'
                       '<float name="cutoff_angle" value="%g"/><float name="beam_width" value="%g"/>'
                       '</emitter>\n' % (i, rgb("intensity", light["intensity"]),
                                         matrix_xml(headlight_to_world(car_pose0, light)),
                                         light["cutoff_angle"], light["beam_width"]))
    else:
        travel = -np.asarray(info["sun_direction"])   # directional: direction of travel
        out.append('<emitter type="directional" id="sun"><vector name="direction" '
                   'value="%.9g %.9g %.9g"/>%s</emitter>\n'
                   % (tuple(travel) + (rgb("irradiance", info["sun_irradiance"]),)))
        out.append('<emitter type="constant" id="sky">%s</emitter>\n'
                   % rgb("radiance", info["sky_radiance"]))
    out.append("</scene>\n")
    return "".join(out)

