"""The Mitsuba scene files of the street: one per lighting (time A, time B, night).

The renders load these very files (``mi.load_file``), so the XML on disk is
exactly what produced the images. Each file holds frame 0: the sensor and the
moving car (and its headlights) at their frame-0 poses; :mod:`.rgb_frames` moves
them per frame with :func:`mi_invrgbl.scene.posing.place`. Meshes and
textures live next to the XML in ``meshes/`` and ``textures/``. The files are
built with the package's one scene-XML builder, :mod:`mi_invrgbl.scene.xml`.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np

from ..scene import xml
from ..scene.xml import spot_to_world

__all__ = ["headlight_to_world", "scene_xml", "spot_to_world"]


def headlight_to_world(car_pose: np.ndarray, light: dict) -> np.ndarray:
    local = spot_to_world(light["position_car_frame"], light["direction_car_frame"])
    return car_pose @ local


def scene_xml(kind: str, config, layout, mesh_files: dict, sensor_to_world: np.ndarray,
              car_pose0: np.ndarray, light_info: dict) -> str:
    """XML text of the scene for ``kind`` in (``time_a``, ``time_b``, ``night``)."""
    doc = xml.SceneDoc.new("scene.xml")
    doc.add(xml.integrator("path", max_depth=int(config.max_depth)))
    doc.add(xml.perspective_sensor("sensor", config.fov, sensor_to_world, config.width,
                                   config.height, config.spp, near_clip=0.05, far_clip=1000,
                                   pixel_format="rgb"))
    for mat in layout.materials.values():
        doc.add(ET.fromstring(mat.bsdf_xml(getattr(config, "bsdf", "roughplastic"))))
    for part in layout.parts:
        children = [xml.param("string", "filename", mesh_files[part.name]),
                    xml.param("boolean", "face_normals", True)]
        if part.dynamic:
            children.append(xml.transform(car_pose0))
        children.append(ET.Element("ref", {"id": "mat_%s" % part.material}))
        doc.add(xml.element("shape", "ply", part.name, children))
    info = light_info[kind]
    if kind == "night":
        doc.add(xml.element("emitter", "constant", "sky", [xml.rgb("radiance", info["sky_radiance"])]))
        for i, lamp in enumerate(info["streetlights"]):
            doc.add(xml.spot_emitter("streetlight_%d" % i, lamp["intensity"],
                                     spot_to_world(lamp["position"], lamp["direction"]),
                                     lamp["cutoff_angle"], lamp["beam_width"]))
        for i, light in enumerate(info["headlights"]):
            doc.add(xml.spot_emitter("headlight_%d" % i, light["intensity"],
                                     headlight_to_world(car_pose0, light),
                                     light["cutoff_angle"], light["beam_width"]))
    else:
        travel = -np.asarray(info["sun_direction"], np.float64)   # directional: direction of travel
        doc.add(xml.element("emitter", "directional", "sun", [
            xml.vector("direction", travel), xml.rgb("irradiance", info["sun_irradiance"])]))
        doc.add(xml.element("emitter", "constant", "sky", [xml.rgb("radiance", info["sky_radiance"])]))
    return doc.to_string()
