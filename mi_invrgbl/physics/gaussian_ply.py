"""Reading and writing Gaussians in the 3DGS PLY convention (numpy only).

The file is a binary little-endian PLY with one ``vertex`` element whose float
properties follow the 3D Gaussian Splatting layout::

    x y z  nx ny nz  f_dc_0..2  [f_rest_*]  opacity  <extras>  scale_0..2  rot_0..3

``opacity`` is stored as a logit and ``scale_*`` as natural logs, ``rot_0`` is
the quaternion's real part. mi-invrgbl adds the per-Gaussian material fields of
:mod:`.fields` (``albedo_0..2``, ``roughness``, ``lidar_albedo``,
``sun_visibility``, ...) in the middle, so that Mitsuba's own ``ellipsoids`` PLY reader (which insists on the
first six and last seven fields) still reads our files.

A plain 3DGS file loads with defaults: normals from the shortest ellipsoid axis
when ``nx, ny, nz`` are absent or zero, albedo from the DC colour, roughness
0.5, LiDAR albedo from the albedo's luminance and sun visibility 1.
"""

from __future__ import annotations

import os
from dataclasses import field as dc_field, make_dataclass

import numpy as np

from ..outdir import atomic_write

from .colour import LUMINANCE, linear_to_srgb, srgb_to_linear
from .fields import BY_NAME, GEOMETRY, MATERIAL

SH_C0 = 0.28209479177387814  # real SH band-0 constant: colour = 0.5 + SH_C0 * f_dc
_PLY_TYPES = {"float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
              "uchar": "u1", "uint8": "u1", "char": "i1", "int8": "i1",
              "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
              "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4"}


class GaussianFileError(ValueError):
    """A Gaussian PLY file or array that cannot be used; the message names the file."""


class _CloudMethods:
    """Per-Gaussian arrays in linear (not log/logit) units, world space.

    ``quaternions`` are (w, x, y, z), unit length. ``opacities`` in [0, 1].
    One attribute per field of :mod:`.fields` (``centers``, ``scales``,
    ``quaternions``, ``opacities``, then the material fields ``normals``,
    ``albedo``, ``roughness``, ``lidar_albedo``, ``sun_visibility``, ...;
    material fields may be None until :meth:`with_defaults`), then ``source``
    and ``extra``.
    """

    def __len__(self):
        return int(self.centers.shape[0])

    def with_defaults(self) -> "GaussianCloud":
        """Fill every optional field with its documented default."""
        n = len(self)
        if self.normals is None or not np.any(self.normals):
            self.normals = shortest_axis(self.quaternions, self.scales)
        if self.albedo is None:
            self.albedo = np.full((n, 3), BY_NAME["albedo"].default, np.float32)
        if self.lidar_albedo is None:
            self.lidar_albedo = (self.albedo @ LUMINANCE).astype(np.float32)
        for f in MATERIAL:
            if getattr(self, f.cloud) is None:
                shape = (n,) if f.width == 1 else (n, f.width)
                setattr(self, f.cloud, np.full(shape, f.default, np.float32))
        return self

    def validate(self) -> "GaussianCloud":
        """Refuse NaN/inf and wrong shapes with a message naming the source and field."""
        n = len(self)
        for f in GEOMETRY + MATERIAL:
            value = getattr(self, f.cloud)
            if value is None:
                continue
            shape = (n,) if f.width == 1 else (n, f.width)
            if value.shape != shape:
                raise GaussianFileError("%s: field '%s' has shape %s, expected %s"
                                        % (self.source, f.cloud, value.shape, shape))
            bad = ~np.isfinite(value)
            if bad.any():
                rows = np.unique(np.nonzero(bad)[0])
                raise GaussianFileError("%s: field '%s' holds NaN/inf for %d Gaussian(s) "
                                        "(first: index %d)" % (self.source, f.cloud, rows.size, rows[0]))
        if np.any(self.scales < 0):
            raise GaussianFileError("%s: negative scales" % self.source)
        qn = np.linalg.norm(self.quaternions, axis=1)
        if np.any(qn < 1e-12):
            raise GaussianFileError("%s: %d zero-length rotation quaternion(s)"
                                    % (self.source, int(np.sum(qn < 1e-12))))
        return self

    def subset(self, mask) -> "GaussianCloud":
        """The Gaussians selected by ``mask`` (boolean or index array), copied."""
        pick = lambda a: None if a is None else a[mask].copy()  # noqa: E731
        return GaussianCloud(**{f.cloud: pick(getattr(self, f.cloud)) for f in GEOMETRY + MATERIAL},
                             source=self.source)

    @staticmethod
    def concat(parts, source) -> "GaussianCloud":
        """One cloud holding every Gaussian of ``parts`` (all with defaults filled)."""
        return GaussianCloud(**{f.cloud: np.concatenate([getattr(p, f.cloud) for p in parts], axis=0)
                                for f in GEOMETRY + MATERIAL}, source=source)


#: The cloud's array attributes in field order (geometry first, required).
GaussianCloud = make_dataclass(
    "GaussianCloud",
    [(f.cloud, np.ndarray) for f in GEOMETRY]
    + [(f.cloud, "np.ndarray | None", dc_field(default=None)) for f in MATERIAL]
    + [("source", str, dc_field(default="<arrays>")),
       ("extra", dict, dc_field(default_factory=dict))],
    bases=(_CloudMethods,), namespace={"__module__": __name__, "__doc__": _CloudMethods.__doc__})


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """(N, 4) w x y z -> (N, 3, 3) rotation matrices (columns = local axes)."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], 1)


def matrix_to_quaternion(m: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices -> (N, 4) w x y z (Shepperd's method)."""
    m = np.asarray(m, np.float64)
    tr = np.trace(m, axis1=1, axis2=2)
    cand = np.stack([tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], 1)
    best = np.argmax(cand, 1)
    q = np.empty((m.shape[0], 4))
    for i, k in enumerate(best):
        r = m[i]
        if k == 0:
            s = np.sqrt(max(1 + tr[i], 1e-12)) * 2
            q[i] = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
        elif k == 1:
            s = np.sqrt(max(1 + r[0, 0] - r[1, 1] - r[2, 2], 1e-12)) * 2
            q[i] = [(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
        elif k == 2:
            s = np.sqrt(max(1 + r[1, 1] - r[0, 0] - r[2, 2], 1e-12)) * 2
            q[i] = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s]
        else:
            s = np.sqrt(max(1 + r[2, 2] - r[0, 0] - r[1, 1], 1e-12)) * 2
            q[i] = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def shortest_axis(quaternions: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """Unit normal of each Gaussian: its shortest axis (a flat Gaussian's normal)."""
    rot = quaternion_to_matrix(quaternions)
    axis = np.argmin(scales, axis=1)
    return rot[np.arange(len(axis)), :, axis].astype(np.float32)


def _parse_header(f, path):
    if f.readline().strip() != b"ply":
        raise GaussianFileError("%s: not a PLY file" % path)
    fmt, count, props, element = None, None, [], None
    while True:
        line = f.readline()
        if not line:
            raise GaussianFileError("%s: PLY header has no end_header" % path)
        words = line.decode("ascii", "replace").split()
        if not words:
            continue
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            element = words[1]
            if element == "vertex":
                count = int(words[2])
            elif count is not None:
                raise GaussianFileError("%s: elements after 'vertex' are not supported" % path)
        elif words[0] == "property" and element == "vertex":
            if words[1] == "list":
                raise GaussianFileError("%s: list properties are not supported" % path)
            if words[1] not in _PLY_TYPES:
                raise GaussianFileError("%s: unknown PLY type '%s'" % (path, words[1]))
            props.append((words[2], _PLY_TYPES[words[1]]))
        elif words[0] == "end_header":
            break
    if count is None:
        raise GaussianFileError("%s: PLY file has no vertex element" % path)
    if fmt not in ("binary_little_endian", "ascii"):
        raise GaussianFileError("%s: PLY format '%s' is not supported" % (path, fmt))
    return fmt, count, props


def read_ply(path: str) -> GaussianCloud:
    """Read a 3DGS-style PLY file into a validated :class:`GaussianCloud` with defaults."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise GaussianFileError("%s: file not found" % path)
    with open(path, "rb") as f:
        fmt, count, props = _parse_header(f, path)
        dtype = np.dtype([(name, "<" + t) for name, t in props])
        if fmt == "ascii":
            data = np.loadtxt(f, dtype=np.float64, ndmin=2, max_rows=count)
            if data.shape[0] != count:
                raise GaussianFileError("%s: truncated PLY (%d of %d vertices)" % (path, data.shape[0], count))
            data = np.rec.fromarrays(data.T, names=[p[0] for p in props])
        else:
            raw = f.read(count * dtype.itemsize)
            if len(raw) != count * dtype.itemsize:
                raise GaussianFileError("%s: truncated PLY (%d of %d bytes)"
                                        % (path, len(raw), count * dtype.itemsize))
            data = np.frombuffer(raw, dtype=dtype)
    names = set(data.dtype.names)

    def cols(*keys):
        missing = [k for k in keys if k not in names]
        if missing:
            raise GaussianFileError("%s: missing PLY field(s) %s" % (path, ", ".join(missing)))
        return np.stack([np.asarray(data[k], np.float64) for k in keys], 1)

    arrays = {}
    for f in GEOMETRY + MATERIAL:
        required = f.name in ("center", "scale", "rotation")
        if not (required or all(k in names for k in f.ply)):
            continue                  # defaults below and in with_defaults()
        arrays[f.cloud] = f.ply_to_cloud(cols(*f.ply))
        arrays[f.cloud] = arrays[f.cloud].astype(np.float32)
        if f.width == 1:
            arrays[f.cloud] = arrays[f.cloud][:, 0]
    if "opacities" not in arrays:
        arrays["opacities"] = np.ones(count, np.float32)
    if "albedo" not in arrays and "f_dc_0" in names:
        srgb = np.clip(0.5 + SH_C0 * cols("f_dc_0", "f_dc_1", "f_dc_2"), 0.0, 1.0)
        arrays["albedo"] = srgb_to_linear(srgb).astype(np.float32)
    cloud = GaussianCloud(**arrays, source=path)
    cloud.validate()
    norm = np.linalg.norm(cloud.quaternions, axis=1, keepdims=True)
    cloud.quaternions = (cloud.quaternions / norm).astype(np.float32)
    return cloud.with_defaults()


def write_ply(path: str, cloud: GaussianCloud) -> None:
    """Write ``cloud`` as a binary 3DGS-style PLY with the material fields.

    Written to a temporary file and renamed, so an interrupted write never
    leaves a truncated file under ``path``.
    """
    cloud = cloud.with_defaults()
    n = len(cloud)
    # DC colour so that plain 3DGS viewers show the albedo (in sRGB).
    lin = np.clip(cloud.albedo, 0, 1)
    srgb = linear_to_srgb(lin)
    # Mitsuba's own ``ellipsoids`` reader insists on x y z nx ny nz first and
    # scale_0..2 rot_0..3 last; the DC colour (for plain 3DGS viewers), the
    # opacity and the other material fields go in between.
    head, tail = ("center", "normal"), ("scale", "rotation")
    middle = [f for f in GEOMETRY + MATERIAL if f.name not in head + tail and f.ply]
    dc = [("f_dc_%d" % c, (srgb[:, c] - 0.5) / SH_C0) for c in range(3)]
    fields = []
    for group in ([BY_NAME[k] for k in head], None, middle, [BY_NAME[k] for k in tail]):
        if group is None:
            fields += dc
            continue
        for f in group:
            cols = f.cloud_to_ply(getattr(cloud, f.cloud))
            fields += [(name, cols[:, j]) for j, name in enumerate(f.ply)]
    table = np.empty(n, dtype=[(k, "<f4") for k, _ in fields])
    for k, v in fields:
        table[k] = v
    header = "ply\nformat binary_little_endian 1.0\nelement vertex %d\n" % n
    header += "".join("property float %s\n" % k for k, _ in fields) + "end_header\n"
    def write(tmp):
        with open(tmp, "wb") as f:
            f.write(header.encode("ascii"))
            f.write(table.tobytes())
    atomic_write(path, write)
