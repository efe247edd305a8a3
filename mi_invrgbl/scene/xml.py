"""Mitsuba scene XML: the one builder and editor of scene files.

Every scene file the package writes goes through this module: the imported
scene (:mod:`.imported`), the fitted scene (``fit``), the applications'
edits and the synthetic street's files. :class:`SceneDoc` holds a file as an
element tree; the element makers (:func:`element`, :func:`param`,
:func:`rgb`, :func:`vector`, :func:`transform`) and the node makers for this
package's plugins and Mitsuba's sensors (:func:`perspective_sensor`,
:func:`lidar_sensor`, :func:`shsun_emitter`, :func:`gaussians_shape`,
:func:`spot_emitter`, :func:`integrator`) build its nodes, and
:meth:`SceneDoc.to_string` prints every file the same way.

Each application (relight, night, insert, lidar) is an edit of the scene's
XML: emitters replaced or added, a shape added, the integrator's options
changed. Working on the XML rather than on a loaded scene keeps the edit
visible: the edited file is written next to the renders, with a unified
diff against the original, and ``mi.load_file`` on that file reproduces the
renders.

File paths inside the scene (``filename`` of shapes, textures, ``rays`` of
LiDARs) are relative to the XML's folder in Mitsuba; :class:`SceneDoc`
resolves them when it reads a file and writes them relative to the folder of
the edited copy, so the copy loads from anywhere.
"""

from __future__ import annotations

import copy
import difflib
import os
import xml.etree.ElementTree as ET

import numpy as np

from ..errors import UserError, mitsuba_message
from ..outdir import atomic_write_text

#: Names of ``<string>`` parameters that hold a file path.
PATH_PARAMETERS = ("filename", "rays")
#: Of those, the ones written relative to the XML's folder. The ``lidar``
#: sensor's ``rays`` file is not copied beside a scene written elsewhere (a
#: fit's PLYs are), so that one stays absolute in written files.
RELATIVE_PARAMETERS = ("filename",)
#: Emitter types that make up a scene's sky and sun (replaced by relighting).
SKY_TYPES = ("shsun", "constant", "envmap", "sunsky", "sky", "sun", "directional")


class SceneDoc:
    """A Mitsuba scene XML file held as an element tree with absolute file paths."""

    def __init__(self, root: ET.Element, path: str):
        self.root = root
        self.path = os.path.abspath(path)
        self.folder = os.path.dirname(self.path)

    # ------------------------------------------------------------------ I/O
    @staticmethod
    def new(path: str, version: str = "3.0.0") -> "SceneDoc":
        """An empty scene to be written to ``path``."""
        root = element("scene")
        root.set("version", version)
        return SceneDoc(root, path)

    @staticmethod
    def load(path: str, resolve_paths: bool = True) -> "SceneDoc":
        """Parse ``path``; one :class:`UserError` naming the file if that fails.

        With ``resolve_paths`` (the default) file paths inside become absolute;
        without, the :data:`RELATIVE_PARAMETERS` ones are kept as written (a
        copy written beside its PLYs) and only the others become absolute.
        """
        if not os.path.isfile(path):
            raise UserError("%s: scene file not found" % path)
        parser = ET.XMLParser(target=ET.TreeBuilder(insert_comments=True))
        try:
            root = ET.parse(path, parser=parser).getroot()
        except ET.ParseError as exc:
            raise UserError("%s: not a valid XML file (%s)" % (path, exc)) from None
        if root.tag != "scene":
            raise UserError("%s: not a Mitsuba scene (root element is <%s>, not <scene>)"
                            % (path, root.tag))
        doc = SceneDoc(root, path)
        doc._map_paths(lambda value: _absolute(value, doc.folder),
                       None if resolve_paths else RELATIVE_PARAMETERS)
        return doc

    def copy(self) -> "SceneDoc":
        return SceneDoc(copy.deepcopy(self.root), self.path)

    def to_string(self, folder: str | None = None) -> str:
        """The XML text, with file paths relative to ``folder`` (default: as held)."""
        root = copy.deepcopy(self.root)
        if folder is not None:
            folder = os.path.abspath(folder)
            for elem in _path_elements(root):
                value = elem.get("value")
                if (elem.get("name") in RELATIVE_PARAMETERS and os.path.isabs(value)
                        and _share_folder(value, folder)):
                    elem.set("value", os.path.relpath(value, folder))
        ET.indent(root, space="    ")
        return ('<?xml version="1.0" encoding="utf-8"?>\n'
                + ET.tostring(root, encoding="unicode") + "\n")

    def write(self, path: str, original: "SceneDoc | None" = None) -> list[str]:
        """Write the XML to ``path``; with ``original``, also ``<path>.diff``.

        Both sides of the diff are printed by the same serialiser, so the diff
        shows the edit alone and not formatting differences.
        """
        folder = os.path.dirname(os.path.abspath(path))
        os.makedirs(folder, exist_ok=True)
        text = self.to_string(folder)
        atomic_write_text(path, text)
        written = [path]
        if original is not None:
            before = original.to_string(folder).splitlines(keepends=True)
            diff = difflib.unified_diff(before, text.splitlines(keepends=True),
                                        fromfile=original.path, tofile=path)
            diff_path = os.path.splitext(path)[0] + ".diff"
            atomic_write_text(diff_path, "".join(diff))
            written.append(diff_path)
        return written

    def _map_paths(self, fn, skip=None):
        for elem in _path_elements(self.root):
            if skip is None or elem.get("name") not in skip:
                elem.set("value", fn(elem.get("value")))

    # -------------------------------------------------------------- queries
    def children(self, tag: str, types=None) -> list[ET.Element]:
        """Top-level elements with this tag (and one of ``types``, if given)."""
        return [e for e in self.root if e.tag == tag
                and (types is None or e.get("type") in types)]

    def by_id(self, ident: str) -> ET.Element | None:
        for e in self.root.iter():
            if e.get("id") == ident and e.tag not in ("ref", "default"):
                return e
        return None

    def ids(self, tag: str) -> list[str]:
        return [e.get("id") for e in self.children(tag) if e.get("id")]

    def integrator(self) -> ET.Element | None:
        found = self.children("integrator")
        return found[0] if found else None

    def defaults(self) -> dict:
        return {e.get("name"): e.get("value") for e in self.children("default")}

    def sensors(self) -> list[ET.Element]:
        return self.children("sensor")

    # ---------------------------------------------------------------- edits
    def remove(self, elem: ET.Element) -> None:
        self.root.remove(elem)

    def add(self, elem: ET.Element, comment: str | None = None) -> ET.Element:
        """Append ``elem`` at the top level (after a comment saying why, if given)."""
        if comment:
            self.root.append(ET.Comment(" %s " % comment))
        self.root.append(elem)
        return elem

    def unique_id(self, base: str) -> str:
        taken = {e.get("id") for e in self.root.iter() if e.get("id")}
        if base not in taken:
            return base
        k = 1
        while "%s_%d" % (base, k) in taken:
            k += 1
        return "%s_%d" % (base, k)

    def set_integrator(self, elem: ET.Element) -> None:
        """Replace the scene's integrator by ``elem`` (at the same place)."""
        old = self.integrator()
        if old is None:
            self.root.insert(0, elem)
        else:
            index = list(self.root).index(old)
            self.root.remove(old)
            self.root.insert(index, elem)


def _absolute(value: str, folder: str) -> str:
    if not value or "$" in value or os.path.isabs(value):
        return value
    candidate = os.path.normpath(os.path.join(folder, value))
    # Mitsuba resolves relative paths against the scene's folder first; keep a
    # path that does not exist there unchanged (the loader will report it).
    return candidate if os.path.exists(candidate) else value


def _share_folder(a: str, b: str) -> bool:
    """Whether two paths have a common folder below the root (then a relative path reads well)."""
    try:
        common = os.path.commonpath([a, b])
    except ValueError:  # different drives
        return False
    return common not in ("", os.path.sep) and os.path.dirname(common) != common


def _path_elements(root):
    for elem in root.iter("string"):
        if elem.get("name") in PATH_PARAMETERS and elem.get("value") is not None:
            yield elem


def load_parts(doc: SceneDoc, tags, what: str):
    """Load a scene made of ``doc``'s top-level elements with these tags only.

    Reading a scene's lights or cameras this way skips its shapes, which for
    a fitted scene means not reading millions of Gaussians.
    """
    import mitsuba as mi
    root = element("scene")
    root.set("version", doc.root.get("version", "3.0.0"))
    for e in doc.root:
        if e.tag == "default" or e.tag in tags:
            root.append(e)
    try:
        return mi.load_string(ET.tostring(root, encoding="unicode"))
    except Exception as exc:  # Mitsuba reports plugin errors as RuntimeError
        raise UserError("%s: cannot load %s: %s" % (doc.path, what, mitsuba_message(exc))) from None


# ------------------------------------------------------------ element makers


def element(tag: str, type_: str | None = None, ident: str | None = None,
            children=()) -> ET.Element:
    e = ET.Element(tag)
    if type_ is not None:
        e.set("type", type_)
    if ident:
        e.set("id", ident)
    for child in children:
        e.append(child)
    return e


def _fmt(v) -> str:
    return "%.7g" % float(v)


def param(kind: str, name: str, value) -> ET.Element:
    """``<float|integer|string|boolean name=... value=...>`` (a string value,
    e.g. ``"$spp"`` or a number already formatted, is written as given)."""
    e = ET.Element(kind)
    e.set("name", name)
    if kind == "float" and not isinstance(value, str):
        value = _fmt(value)
    elif kind == "boolean":
        value = "true" if value else "false"
    e.set("value", str(value))
    return e


def rgb(name: str, value) -> ET.Element:
    e = ET.Element("rgb")
    e.set("name", name)
    e.set("value", ", ".join(_fmt(v) for v in np.asarray(value, np.float64).ravel()))
    return e


def vector(name: str, value) -> ET.Element:
    e = ET.Element("vector")
    e.set("name", name)
    for axis, v in zip("xyz", np.asarray(value, np.float64).ravel()):
        e.set(axis, _fmt(v))
    return e


def point(name: str, value) -> ET.Element:
    e = vector(name, value)
    e.tag = "point"
    return e


def matrix_text(matrix) -> str:
    """A 4x4 matrix as Mitsuba's ``<matrix value=...>`` text (row-major, 9 digits)."""
    return " ".join("%.9g" % v for v in np.asarray(matrix, np.float64).reshape(-1))


def numbers_text(values, digits: int = 7) -> str:
    """Numbers as one space-separated string (``sh``, ``beam_gains``)."""
    return " ".join("%.*g" % (digits, float(v)) for v in np.asarray(values, np.float64).ravel())


def transform(matrix, name: str = "to_world") -> ET.Element:
    e = ET.Element("transform")
    e.set("name", name)
    m = ET.SubElement(e, "matrix")
    m.set("value", matrix_text(matrix))
    return e


def set_child(parent: ET.Element, child: ET.Element) -> None:
    """Put ``child`` under ``parent``, replacing the one with the same ``name``."""
    for old in list(parent):
        if old.get("name") == child.get("name"):
            parent.remove(old)
    parent.append(child)


def set_child_param(parent: ET.Element, kind: str, name: str, value) -> None:
    """Set (replace or add) the parameter ``name`` of ``parent``."""
    set_child(parent, param(kind, name, value))


def child_param(parent: ET.Element, name: str):
    """The ``value`` of parameter ``name`` of ``parent`` (None if absent)."""
    for child in parent:
        if child.get("name") == name:
            return child.get("value")
    return None


# --------------------------------------------------------------- node makers


def default(name: str, value) -> ET.Element:
    """``<default name=... value=...>``: a ``$name`` parameter ``-D`` can set."""
    e = ET.Element("default")
    e.set("name", name)
    e.set("value", str(value))
    return e


def sampler(sample_count, seed=None) -> ET.Element:
    """``independent`` sampler. Give every sensor its own ``seed``: Mitsuba
    3.9.1 merges XML nodes with identical properties, so two sensors with the
    same pose would otherwise become one object with one id."""
    children = [param("integer", "sample_count", sample_count)]
    if seed is not None:
        children.append(param("integer", "seed", seed))
    return element("sampler", "independent", None, children)


def film(width, height, pixel_format=None) -> ET.Element:
    children = [param("integer", "width", width), param("integer", "height", height),
                element("rfilter", "box")]
    if pixel_format:
        children.append(param("string", "pixel_format", pixel_format))
    return element("film", "hdrfilm", None, children)


def perspective_sensor(ident, fov, to_world, width, height, spp, seed=None,
                       principal_point=(0.0, 0.0), near_clip=0.1, far_clip=10000.0,
                       pixel_format=None) -> ET.Element:
    """A ``perspective`` sensor, ``fov`` in degrees along x, principal point
    offsets in film sizes (Mitsuba's convention)."""
    children = [param("float", "fov", "%.9g" % fov), param("string", "fov_axis", "x")]
    if any(principal_point):
        children += [param("float", "principal_point_offset_x", "%.9g" % principal_point[0]),
                     param("float", "principal_point_offset_y", "%.9g" % principal_point[1])]
    children += [param("float", "near_clip", "%g" % near_clip),
                 param("float", "far_clip", "%g" % far_clip), transform(to_world),
                 sampler(spp, seed), film(width, height, pixel_format)]
    return element("sensor", "perspective", ident, children)


def lidar_sensor(ident, elevations_deg, azimuth_steps, to_world, far_clip=120.0,
                 seed=None) -> ET.Element:
    """The package's ``lidar`` sensor: one film row per beam elevation."""
    elev = ", ".join("%.6f" % e for e in elevations_deg)
    return element("sensor", "lidar", ident, [
        param("string", "elevations", elev), param("float", "far_clip", "%g" % far_clip),
        transform(to_world), sampler(1, seed), film(azimuth_steps, len(elevations_deg))])


def lidar_rays_sensor(ident, rays_file, n_rays, to_world, far_clip=120.0,
                      seed=None) -> ET.Element:
    """The package's ``lidar`` sensor in ``rays`` mode: an ``n_rays`` x 1 film,
    the pattern read from ``rays_file`` (relative to the scene's folder)."""
    return element("sensor", "lidar", ident, [
        param("string", "rays", rays_file), param("float", "far_clip", "%g" % far_clip),
        transform(to_world), sampler(1, seed), film(n_rays, 1)])


def shsun_emitter(ident, sh, order, sun_direction, sun_irradiance,
                  sun_radius=None) -> ET.Element:
    """The package's ``shsun`` emitter: ``sh`` holds at least ``(order + 1)^2``
    RGB rows (written one RGB triple per comma-separated group)."""
    sh = np.asarray(sh, np.float64).reshape(-1, 3)[: (order + 1) ** 2]
    children = [param("integer", "order", order),
                param("string", "sh", ",  ".join(numbers_text(row) for row in sh)),
                vector("sun_direction", sun_direction), rgb("sun_irradiance", sun_irradiance)]
    if sun_radius is not None:
        children.append(param("float", "sun_radius", sun_radius))
    return element("emitter", "shsun", ident, children)


def gaussians_shape(ident, filename, to_world=None) -> ET.Element:
    children = [param("string", "filename", filename)]
    if to_world is not None:
        children.append(transform(to_world))
    return element("shape", "gaussians", ident, children)


def spot_to_world(position, direction) -> np.ndarray:
    """A frame whose +z (a spot light's axis) points along ``direction``, placed at ``position``."""
    z = np.asarray(direction, dtype=np.float64)
    z = z / np.linalg.norm(z)
    helper = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, position
    return m


def spot_emitter(ident, intensity, to_world, cutoff_angle, beam_width) -> ET.Element:
    """Mitsuba's ``spot`` light (angles in degrees), its axis the +z of ``to_world``."""
    return element("emitter", "spot", ident, [
        rgb("intensity", intensity), param("float", "cutoff_angle", cutoff_angle),
        param("float", "beam_width", beam_width), transform(to_world)])


def integrator(type_: str, **params) -> ET.Element:
    """An integrator with parameters typed from their Python values (bool ->
    boolean, int -> integer, float -> float, str -> string)."""
    children = []
    for name, value in params.items():
        if isinstance(value, bool):
            kind = "boolean"
        elif isinstance(value, (int, np.integer)):
            kind = "integer"
        elif isinstance(value, (float, np.floating)):
            kind, value = "float", "%.6g" % value
        else:
            kind = "string"
        children.append(param(kind, name, value))
    return element("integrator", type_, None, children)
