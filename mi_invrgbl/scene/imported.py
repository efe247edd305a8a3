"""The imported scene's ``scene.xml`` (see ``docs/scene_format.md``).

``imported_scene(frames, path, ...)`` builds it with :mod:`.xml`'s builder
and returns the :class:`~mi_invrgbl.scene.xml.SceneDoc`:

* ``<default name="spp" value="4"/>``, ``<default name="samples" value="16"/>``;
* integrator ``invrgbl`` (``samples`` = ``$samples``);
* emitter ``shsun`` id ``sky``: a plain grey SH sky and a sun (direction up-ish,
  irradiance 0 unless given: ``fit`` estimates both);
* shape ``gaussians`` id ``background`` (``background.ply``) and one
  ``gaussians`` id ``object_<track>`` per dynamic object, ``to_world`` = its
  pose at frame 0;
* per frame ``NNNN``: ``perspective`` sensor ``camera_NNNN`` and ``lidar``
  sensor ``lidar_NNNN``.

Camera conversion (dataset camera x right, y down, z forward; pixel centres
at integer coordinates, as KITTI's K): ``fov`` = 2 atan(W / (2 fx)) along x,
``principal_point_offset_x = (W/2 - 0.5 - cx) / W`` and
``principal_point_offset_y = (H/2 - 0.5 - cy) / H`` (Mitsuba measures the
offset in film sizes, in its own flipped image axes), ``to_world =
camera_to_world @ diag(-1, -1, 1, 1)``. Mitsuba assumes square pixels: fy
is not used (the importer warns when it differs from fx).

Every sensor's sampler carries its own ``seed`` (the frame index). Besides
decorrelating frames, this keeps sensors distinct: Mitsuba 3.9.1 merges
XML nodes with identical properties, so two frames with the same pose (a
car waiting at a light) would otherwise become one sensor object with one id.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import numpy as np

from . import xml
from .frames import CAMERA_FLIP, Frames

#: Radiance of the initial uniform sky (a white Lambertian under it has
#: radiance 1, i.e. pixel value ~1 before tone mapping).
SKY_RADIANCE = 1.0
#: Initial direction towards the sun (world frame: z up), normalised on use.
SUN_DIRECTION = (0.3, 0.2, 0.93)
Y0 = 0.28209479177387814


def camera_fov_and_offsets(width, height, fx, cx, cy):
    """Mitsuba ``fov`` (degrees, x axis) and principal point offsets for a
    pinhole with KITTI/OpenCV intrinsics (pixel centres at integers)."""
    fov = math.degrees(2.0 * math.atan(width / (2.0 * fx)))
    ppx = (width / 2.0 - 0.5 - cx) / width
    ppy = (height / 2.0 - 0.5 - cy) / height
    return fov, ppx, ppy


def camera_sensor(name, index, camera, camera_to_world) -> ET.Element:
    fov, ppx, ppy = camera_fov_and_offsets(camera.width, camera.height, camera.fx,
                                           camera.cx, camera.cy)
    return xml.perspective_sensor(name, fov, np.asarray(camera_to_world) @ CAMERA_FLIP,
                                  camera.width, camera.height, "$spp", seed=index,
                                  principal_point=(ppx, ppy))


def lidar_sensor(name, index, lidar, lidar_to_world, far_clip=120.0) -> ET.Element:
    if lidar.extra.get("rays"):      # an explicit ray pattern (file next to the scene)
        return xml.lidar_rays_sensor(name, lidar.extra["rays"], lidar.azimuth_steps,
                                     lidar_to_world, far_clip, seed=index)
    return xml.lidar_sensor(name, lidar.elevations_deg, lidar.azimuth_steps, lidar_to_world,
                            far_clip, seed=index)


def sky_emitter(order=2, radiance=SKY_RADIANCE, sun_direction=SUN_DIRECTION,
                sun_irradiance=0.0) -> ET.Element:
    """A plain grey SH sky (only the order-0 term) and a sun."""
    coeffs = np.zeros(((order + 1) ** 2, 3))
    coeffs[0] = radiance / Y0
    d = np.asarray(sun_direction, np.float64)
    return xml.shsun_emitter("sky", coeffs, order, d / np.linalg.norm(d),
                             np.full(3, float(sun_irradiance)))


def imported_scene(frames: Frames, path, background="background.ply", sky_order=2,
                   sun_irradiance=0.0, lidar_far_clip=120.0, comment="") -> xml.SceneDoc:
    """The scene for a :class:`~mi_invrgbl.scene.frames.Frames`, to be written
    to ``path`` (PLY files named relative to the scene's folder)."""
    doc = xml.SceneDoc.new(str(path))
    if comment:
        doc.root.append(ET.Comment(" %s " % comment.replace("--", "- -")))
    doc.add(xml.default("spp", 4))
    doc.add(xml.default("samples", 16))
    doc.add(xml.element("integrator", "invrgbl", None,
                        [xml.param("integer", "samples", "$samples")]))
    doc.add(sky_emitter(sky_order, sun_irradiance=sun_irradiance))
    doc.add(xml.gaussians_shape("background", background))
    for name, obj in frames.objects.items():
        pose0 = frames[0].objects.get(name)
        rel = obj.ply.name if obj.ply is not None else f"{name}.ply"
        doc.add(xml.gaussians_shape(name, rel, pose0))
    for f in frames:
        doc.add(camera_sensor(f.camera, f.index, frames.camera, f.camera_to_world))
        doc.add(lidar_sensor(f.lidar, f.index, frames.lidar, f.lidar_to_world, lidar_far_clip))
    return doc
