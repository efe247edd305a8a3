"""The imported scene's ``scene.xml`` (see ``docs/scene_format.md``).

``scene_xml(camera, lidar, frames, objects, ...)`` returns the XML text:

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
from xml.sax.saxutils import quoteattr

import numpy as np

from ..scene_graph import CAMERA_FLIP
from .. import scene_graph

#: Radiance of the initial uniform sky (a white Lambertian under it has
#: radiance 1, i.e. pixel value ~1 before tone mapping).
SKY_RADIANCE = 1.0
#: Initial direction towards the sun (world frame: z up), normalised on use.
SUN_DIRECTION = (0.3, 0.2, 0.93)
Y0 = 0.28209479177387814


def _matrix(T) -> str:
    return " ".join("%.9g" % v for v in np.asarray(T, np.float64).ravel())


def camera_fov_and_offsets(width, height, fx, cx, cy):
    """Mitsuba ``fov`` (degrees, x axis) and principal point offsets for a
    pinhole with KITTI/OpenCV intrinsics (pixel centres at integers)."""
    fov = math.degrees(2.0 * math.atan(width / (2.0 * fx)))
    ppx = (width / 2.0 - 0.5 - cx) / width
    ppy = (height / 2.0 - 0.5 - cy) / height
    return fov, ppx, ppy


def camera_sensor(name, index, camera, camera_to_world) -> str:
    fov, ppx, ppy = camera_fov_and_offsets(camera.width, camera.height, camera.fx,
                                           camera.cx, camera.cy)
    to_world = np.asarray(camera_to_world) @ CAMERA_FLIP
    return f"""    <sensor type="perspective" id="{name}">
        <float name="fov" value="{fov:.9g}"/>
        <string name="fov_axis" value="x"/>
        <float name="principal_point_offset_x" value="{ppx:.9g}"/>
        <float name="principal_point_offset_y" value="{ppy:.9g}"/>
        <float name="near_clip" value="0.1"/>
        <float name="far_clip" value="10000"/>
        <transform name="to_world"><matrix value="{_matrix(to_world)}"/></transform>
        <sampler type="independent">
            <integer name="sample_count" value="$spp"/>
            <integer name="seed" value="{index}"/>
        </sampler>
        <film type="hdrfilm">
            <integer name="width" value="{camera.width}"/>
            <integer name="height" value="{camera.height}"/>
            <rfilter type="box"/>
        </film>
    </sensor>
"""


def lidar_sensor(name, index, lidar, lidar_to_world, far_clip=120.0) -> str:
    elev = ", ".join("%.6f" % e for e in lidar.elevations_deg)
    return f"""    <sensor type="lidar" id="{name}">
        <string name="elevations" value="{elev}"/>
        <float name="far_clip" value="{far_clip:g}"/>
        <transform name="to_world"><matrix value="{_matrix(lidar_to_world)}"/></transform>
        <sampler type="independent">
            <integer name="sample_count" value="1"/>
            <integer name="seed" value="{index}"/>
        </sampler>
        <film type="hdrfilm">
            <integer name="width" value="{lidar.azimuth_steps}"/>
            <integer name="height" value="{lidar.beams}"/>
            <rfilter type="box"/>
        </film>
    </sensor>
"""


def sky_emitter(order=2, radiance=SKY_RADIANCE, sun_direction=SUN_DIRECTION,
                sun_irradiance=0.0) -> str:
    k = (order + 1) ** 2
    coeffs = np.zeros((k, 3))
    coeffs[0] = radiance / Y0
    sh = "   ".join(" ".join("%.6g" % v for v in c) for c in coeffs)
    d = np.asarray(sun_direction, np.float64)
    d = d / np.linalg.norm(d)
    return f"""    <emitter type="shsun" id="sky">
        <integer name="order" value="{order}"/>
        <string name="sh" value="{sh}"/>
        <vector name="sun_direction" x="{d[0]:.6g}" y="{d[1]:.6g}" z="{d[2]:.6g}"/>
        <rgb name="sun_irradiance" value="{sun_irradiance:g}, {sun_irradiance:g}, {sun_irradiance:g}"/>
    </emitter>
"""


def gaussians_shape(name, filename, to_world=None) -> str:
    tw = ""
    if to_world is not None:
        tw = f'\n        <transform name="to_world"><matrix value="{_matrix(to_world)}"/></transform>'
    return f"""    <shape type="gaussians" id="{name}">
        <string name="filename" value={quoteattr(filename)}/>{tw}
    </shape>
"""


def scene_xml(frames: "scene_graph.Frames", background="background.ply", sky_order=2,
              sun_irradiance=0.0, lidar_far_clip=120.0, comment="") -> str:
    """The scene for a :class:`mi_invrgbl.scene_graph.Frames` (paths of the
    PLY files relative to the scene's folder)."""
    parts = ['<scene version="3.0.0">\n']
    if comment:
        parts.append("    <!-- %s -->\n" % comment.replace("--", "- -"))
    parts.append('    <default name="spp" value="4"/>\n'
                 '    <default name="samples" value="16"/>\n\n'
                 '    <integrator type="invrgbl">\n'
                 '        <integer name="samples" value="$samples"/>\n'
                 '    </integrator>\n\n')
    parts.append(sky_emitter(sky_order, sun_irradiance=sun_irradiance))
    parts.append("\n")
    parts.append(gaussians_shape("background", background))
    for name, obj in frames.objects.items():
        pose0 = frames[0].objects.get(name)
        rel = obj.ply.name if obj.ply is not None else f"{name}.ply"
        parts.append(gaussians_shape(name, rel, pose0))
    parts.append("\n")
    for f in frames:
        parts.append(camera_sensor(f.camera, f.index, frames.camera, f.camera_to_world))
        parts.append(lidar_sensor(f.lidar, f.index, frames.lidar, f.lidar_to_world,
                                  lidar_far_clip))
    parts.append("</scene>\n")
    return "".join(parts)
