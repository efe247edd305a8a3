"""Object insertion: a fitted node or a mesh placed into another scene.

The edit (see ``docs/applications.md``) adds one ``<shape>`` to the target
scene: a copy of another scene's node (``OTHER.xml:NODE``; a ``gaussians``
node brings its Gaussians and their materials, a mesh node its BSDF), or a
mesh file (``.obj``/``.ply``) with a ``cooktorrance`` BSDF. Once it is in the
scene, the target's sky, sun and lamps light it, and shadows work both ways
without anything special: the ``invrgbl`` integrator and Mitsuba's ``path``
trace every shadow ray through every shape, so the object shades the scene
and the scene shades the object.

Placement: ``--pose x,y,z,yaw`` puts the object's *bottom centre* (the centre
of its bounding box, lowered to the box's floor) at ``(x, y, z)`` and turns
it by ``yaw`` about +z. "Its" frame is the object frame of a fitted node (x
forward, the heading; ``to_world`` of the node in OTHER is dropped, as it only
places the node at OTHER's frame 0), the file's frame for a mesh file, and
OTHER's world orientation for any other node. ``--keep-origin`` places the
frame's origin instead of the bottom centre.

A ``.ply`` file is read as Gaussians when it has the 3DGS fields
(``scale_0``, ``rot_0``), as a mesh otherwise.
"""

from __future__ import annotations

import copy
import dataclasses
import os
import xml.etree.ElementTree as ET

import numpy as np

from ..errors import UserError, mitsuba_message
from . import lighting_edit
from ..scene import xml
from ..scene.posing import place
from ..scene.xml import SceneDoc

MESH_TYPES = {".obj": "obj", ".ply": "ply"}


@dataclasses.dataclass
class ObjectSource:
    """What to insert: XML elements (the shape last) and the object's frame."""

    elements: list            #: elements to add; referenced BSDFs first, the shape last
    kind: str                 #: "gaussians" or "mesh"
    base: np.ndarray          #: object frame -> placed frame (re-centring), 4x4
    extra: np.ndarray         #: transform kept from OTHER under the object frame (meshes)
    description: str

    @property
    def shape(self) -> ET.Element:
        return self.elements[-1]


def split_spec(spec: str):
    """``OTHER.xml:NODE`` -> (path, node); a file -> (path, None)."""
    if ".xml:" in spec:
        path, node = spec.rsplit(":", 1)
        if not node:
            raise UserError("--object %s: give the node after the colon (OTHER.xml:NODE)" % spec)
        return path, node
    if spec.endswith(".xml"):
        raise UserError("--object %s: name the node to take from it, as %s:NODE" % (spec, spec))
    return spec, None


def is_gaussian_ply(path: str) -> bool:
    """Whether a PLY has the 3DGS fields (scale_0, rot_0) in its header."""
    try:
        with open(path, "rb") as f:
            header = f.read(8192).split(b"end_header")[0]
    except OSError as exc:
        raise UserError("%s: cannot read (%s)" % (path, exc.strerror)) from None
    return b"scale_0" in header and b"rot_0" in header


def _bottom_centre(lo, hi) -> np.ndarray:
    return np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])


def _translate(t) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = t
    return m


def _gaussian_bounds(path: str):
    from ..physics.gaussian_ply import GaussianFileError, read_ply
    try:
        cloud = read_ply(path)
    except (GaussianFileError, OSError, ValueError) as exc:
        raise UserError("%s: cannot load Gaussians (%s)" % (path, exc)) from None
    if len(cloud) == 0:
        raise UserError("%s: the file holds no Gaussians" % path)
    return cloud.centers.min(axis=0), cloud.centers.max(axis=0), len(cloud)


def _mesh_bounds(shape_elem: ET.Element, what: str):
    """Load one mesh element alone (with its to_world): bounds, or one clear error."""
    import mitsuba as mi
    root = xml.element("scene")
    root.set("version", "3.0.0")
    e = copy.deepcopy(shape_elem)
    for child in list(e):       # the BSDF does not matter for the bounds
        if child.tag in ("ref", "bsdf"):
            e.remove(child)
    root.append(e)
    try:
        scene = mi.load_string(ET.tostring(root, encoding="unicode"))
    except Exception as exc:  # Mitsuba reports loader errors as RuntimeError
        raise UserError("%s: cannot load the mesh: %s" % (what, mitsuba_message(exc))) from None
    shapes = list(scene.shapes())
    bbox = shapes[0].bbox() if shapes else None
    if bbox is None or not bbox.valid():
        raise UserError("%s: the mesh is empty" % what)
    count = shapes[0].face_count() if hasattr(shapes[0], "face_count") else 0
    return np.array(bbox.min, np.float64).ravel(), np.array(bbox.max, np.float64).ravel(), count


def cooktorrance(ident, albedo, roughness, lidar_albedo) -> ET.Element:
    return xml.element("bsdf", "cooktorrance", ident, [
        xml.rgb("albedo", albedo),
        xml.param("float", "roughness", roughness),
        xml.param("float", "lidar_albedo", lidar_albedo),
    ])


def load_object(spec: str, target: SceneDoc, ident: str = "inserted", albedo=(0.5, 0.5, 0.5),
                roughness: float = 0.5, lidar_albedo: float = 0.5,
                keep_origin: bool = False) -> ObjectSource:
    """Read ``--object`` (see the module docstring) as elements for ``target``."""
    path, node = split_spec(spec)
    if not os.path.isfile(path):
        raise UserError("--object: %s not found" % path)
    albedo = np.broadcast_to(np.asarray(albedo, np.float64).ravel(), (3,))
    if node is not None:
        return _from_scene(path, node, target, ident, keep_origin)
    ext = os.path.splitext(path)[1].lower()
    shape_id = target.unique_id(ident)
    if ext == ".ply" and is_gaussian_ply(path):
        lo, hi, n = _gaussian_bounds(path)
        shape = xml.element("shape", "gaussians", shape_id,
                                 [xml.param("string", "filename", os.path.abspath(path))])
        base = np.eye(4) if keep_origin else _translate(-_bottom_centre(lo, hi))
        return ObjectSource([shape], "gaussians", base, np.eye(4),
                            "%d Gaussians from %s" % (n, path))
    if ext not in MESH_TYPES:
        raise UserError("--object %s: expected OTHER.xml:NODE, a .obj or .ply mesh, or a "
                        "Gaussian .ply" % spec)
    shape = xml.element("shape", MESH_TYPES[ext], shape_id,
                             [xml.param("string", "filename", os.path.abspath(path))])
    lo, hi, faces = _mesh_bounds(shape, path)
    bsdf_id = target.unique_id(ident + "_material")
    shape.append(ET.Element("ref", {"id": bsdf_id}))
    base = np.eye(4) if keep_origin else _translate(-_bottom_centre(lo, hi))
    return ObjectSource([cooktorrance(bsdf_id, albedo, roughness, lidar_albedo), shape], "mesh",
                        base, np.eye(4), "mesh %s (%d faces, %.2f x %.2f x %.2f m)"
                        % ((path, faces) + tuple(hi - lo)))


def _from_scene(path, node, target, ident, keep_origin) -> ObjectSource:
    other = SceneDoc.load(path)
    elem = next((e for e in other.children("shape") if e.get("id") == node), None)
    if elem is None:
        names = other.ids("shape")
        raise UserError("%s: no shape node '%s' (its nodes: %s)"
                        % (path, node, ", ".join(names) if names else "none with an id"))
    shape = copy.deepcopy(elem)
    shape.set("id", target.unique_id(ident))
    extra = np.eye(4)
    for t in [c for c in shape if c.tag == "transform" and c.get("name") == "to_world"]:
        shape.remove(t)
    elements = _copy_references(other, shape, target, ident)
    if shape.get("type") == "gaussians":
        filename = xml.child_param(shape, "filename")
        if filename is None:
            raise UserError("%s: node '%s' has no 'filename' to copy its Gaussians from"
                            % (path, node))
        lo, hi, n = _gaussian_bounds(filename)
        base = np.eye(4) if keep_origin else _translate(-_bottom_centre(lo, hi))
        return ObjectSource(elements + [shape], "gaussians", base, extra,
                            "%d Gaussians of node '%s' of %s" % (n, node, path))
    # A mesh node keeps its size and orientation in OTHER: its to_world (rotation,
    # scale and all) stays under the placement, only its position is replaced.
    placed = copy.deepcopy(shape)
    to_world = [c for c in elem if c.tag == "transform" and c.get("name") == "to_world"]
    if to_world:
        placed.insert(0, copy.deepcopy(to_world[0]))
    lo, hi, faces = _mesh_bounds(placed, "%s:%s" % (path, node))
    shape = placed
    base = np.eye(4) if keep_origin else _translate(-_bottom_centre(lo, hi))
    return ObjectSource(elements + [shape], "mesh", base, extra,
                        "mesh node '%s' of %s (%.2f x %.2f x %.2f m)" % ((node, path) + tuple(hi - lo)))


def _copy_references(other: SceneDoc, shape: ET.Element, target: SceneDoc, ident: str) -> list:
    """Copies of the elements ``shape`` refers to (BSDFs, textures), renamed for ``target``."""
    out, renamed = [], {}
    pending = [shape]
    while pending:
        elem = pending.pop()
        for ref in elem.iter("ref"):
            old = ref.get("id")
            if old not in renamed:
                found = other.by_id(old)
                if found is None:
                    raise UserError("%s: node refers to '%s', which the file does not define"
                                    % (other.path, old))
                new = target.unique_id("%s_%s" % (ident, old))
                renamed[old] = new
                dup = copy.deepcopy(found)
                dup.set("id", new)
                out.insert(0, dup)
                pending.append(dup)
            ref.set("id", renamed[old])
    return out


def placement(obj: ObjectSource, pose) -> np.ndarray:
    """The shape's ``to_world`` for a pose of the object's bottom centre."""
    return np.asarray(pose, np.float64) @ obj.base


def insert_doc(doc: SceneDoc, obj: ObjectSource, pose) -> tuple[SceneDoc, bool]:
    """A copy of ``doc`` with the object at ``pose``; also whether the integrator changed.

    Gaussians need the ``invrgbl`` integrator: a scene rendered by another one
    (a stock ``path``) switches to it, which lights meshes directly (no
    inter-reflections).
    """
    out = doc.copy()
    elements = [copy.deepcopy(e) for e in obj.elements]
    shape = elements[-1]
    m = placement(obj, pose)
    old = [c for c in shape if c.tag == "transform" and c.get("name") == "to_world"]
    if old:   # a mesh node's own to_world: compose it under the placement
        shape.remove(old[0])
        shape.insert(0, xml.element("transform", None, None, []))
        shape[0].set("name", "to_world")
        for child in old[0]:
            shape[0].append(child)
        mat = ET.SubElement(shape[0], "matrix")
        mat.set("value", " ".join("%.9g" % v for v in m.reshape(-1)))
    else:
        shape.insert(0, xml.transform(m))
    for k, e in enumerate(elements):
        out.add(e, "inserted: %s" % obj.description if k == 0 else None)
    switched = False
    integrator = out.integrator()
    if obj.kind == "gaussians" and (integrator is None or integrator.get("type") != "invrgbl"):
        out.set_integrator(xml.element("integrator", "invrgbl"))
        switched = True
    # A fit may store its sun visibility per Gaussian; the inserted object
    # casts its shadow only if visibility is traced.
    lighting_edit.trace_sun_visibility(out)
    return out, switched


class TrackHook:
    """Moves the inserted object along a per-frame track (a render hook).

    ``first_pose`` is the track pose the object was inserted at (its XML
    ``to_world`` is ``placement(obj, first_pose)``); the object's frame here
    is the placed one (its bottom centre), so the track's poses apply as given.
    """

    def __init__(self, shape_id: str, track, first_pose):
        self.id = shape_id
        self.track = [np.asarray(p, np.float64) for p in track]
        self.first = np.asarray(first_pose, np.float64)

    def __call__(self, scene, frame, sensor):
        if frame.index >= len(self.track):
            raise UserError("--track has %d poses but frame %d is rendered (use --frames 0:%d)"
                            % (len(self.track), frame.index, len(self.track)))
        place(scene, {self.id: self.track[frame.index]}, loaded={self.id: self.first})


def scene_bounds_without(scene, shape_id: str):
    """Bounding box of every shape but ``shape_id`` (the target scene's extent)."""
    from .pose_input import scene_bounds
    return scene_bounds(scene, exclude=shape_id)
