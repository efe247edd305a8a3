"""Editing Mitsuba scene XML files: the form every application's edit takes.

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

#: Names of ``<string>`` parameters that hold a file path.
PATH_PARAMETERS = ("filename", "rays")
#: Of those, the ones Mitsuba resolves against the XML's folder. The ``lidar``
#: sensor opens ``rays`` itself (relative to the working directory), so that
#: one stays absolute in written files.
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
    def load(path: str) -> "SceneDoc":
        """Parse ``path``; one :class:`UserError` naming the file if that fails."""
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
        doc._map_paths(lambda value: _absolute(value, doc.folder))
        return doc

    def copy(self) -> "SceneDoc":
        return SceneDoc(copy.deepcopy(self.root), self.path)

    def to_string(self, folder: str | None = None) -> str:
        """The XML text, with file paths relative to ``folder`` (default: absolute)."""
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
        with open(path, "w") as f:
            f.write(text)
        written = [path]
        if original is not None:
            before = original.to_string(folder).splitlines(keepends=True)
            diff = difflib.unified_diff(before, text.splitlines(keepends=True),
                                        fromfile=original.path, tofile=path)
            diff_path = os.path.splitext(path)[0] + ".diff"
            with open(diff_path, "w") as f:
                f.writelines(diff)
            written.append(diff_path)
        return written

    def _map_paths(self, fn):
        for elem in _path_elements(self.root):
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
    """``<float|integer|string|boolean name=... value=...>``."""
    e = ET.Element(kind)
    e.set("name", name)
    if kind == "float":
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


def transform(matrix, name: str = "to_world") -> ET.Element:
    e = ET.Element("transform")
    e.set("name", name)
    m = ET.SubElement(e, "matrix")
    m.set("value", " ".join("%.9g" % v for v in np.asarray(matrix, np.float64).reshape(-1)))
    return e


def set_child_param(parent: ET.Element, kind: str, name: str, value) -> None:
    """Set (replace or add) the parameter ``name`` of ``parent``."""
    for child in list(parent):
        if child.get("name") == name:
            parent.remove(child)
    parent.append(param(kind, name, value))


def child_param(parent: ET.Element, name: str):
    """The ``value`` of parameter ``name`` of ``parent`` (None if absent)."""
    for child in parent:
        if child.get("name") == name:
            return child.get("value")
    return None
