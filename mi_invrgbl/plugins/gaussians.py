"""The ``gaussians`` shape: 3D Gaussians carrying InvRGB+L's material fields."""

from __future__ import annotations


import numpy as np
import mitsuba as mi

from ..physics.fields import MATERIAL
from ..physics.gaussian_ply import GaussianCloud, GaussianFileError, read_ply
from ..physics.host_arrays import jit_tensor

_variant = mi.variant()

#: Scales below this are raised to it: a zero axis would make the ray-space
#: transform of the Gaussian singular (division by the scale).
MIN_SCALE = 1e-6
#: Smallest axis relative to the longest. Mitsuba's ellipsoid intersector
#: misses rays and reports entries far too early on flatter Gaussians
#: (measured: 18 % of rays lost on a 1:1000 layer, none at 1:100 with
#: 1 cm entry error), so flatter ones are thickened to this ratio.
MIN_ASPECT = 1e-2


class GaussiansDoc:
    r"""
    .. _shape-gaussians:

    3D Gaussians with materials (:monosp:`gaussians`)
    -------------------------------------------------

    .. pluginparameters::

     * - filename
       - |string|
       - 3DGS-style PLY file (see :mod:`mi_invrgbl.physics.gaussian_ply`). Plain
         3DGS files load with defaults (normal = shortest axis, albedo = DC colour,
         roughness 0.5, LiDAR albedo = albedo luminance, sun visibility 1).
     * - centers, scales, quaternions, opacities
       - |tensor|
       - Instead of ``filename``: (N,3) centres, (N,3) standard deviations (linear,
         not log), (N,4) unit quaternions w x y z, (N,) or (N,1) opacities in [0,1].
     * - normals, albedo, roughness, lidar_albedo, sun_visibility
       - |tensor|
       - Optional per-Gaussian material fields ((N,3), (N,3), (N,), (N,), (N,)).
     * - to_world
       - |transform|
       - Rigid transform (rotation, translation, uniform scale) applied to the
         Gaussians at load time. (Default: identity)
     * - extent
       - |float|
       - Support of each Gaussian in standard deviations for ray traversal. (Default: 3)
     * - id
       - |string|
       - Node name; the parameters appear as ``<id>.data``, ``<id>.opacities``,
         ``<id>.albedo`` ... in ``mi.traverse``.

    Exposed parameters (``mi.traverse``): ``data`` (N*10: centre, scale,
    quaternion x y z w), ``opacities``, ``normal``, ``albedo``, ``roughness``,
    ``lidar_albedo``, ``sun_visibility`` — all differentiable.

    The shape is Mitsuba's built-in ``ellipsoids`` (Embree-traversed) with the
    material fields attached as per-primitive attributes, so the ``invrgbl`` and
    ``lidar_return`` integrators alpha-blend it front to back and any other
    integrator sees plain ellipsoids. Zero-size axes are raised to 1e-6 and
    axes shorter than 1/100 of the longest are raised to it (Mitsuba's
    ellipsoid intersector is unreliable for flatter Gaussians);
    NaN/inf values are refused with an error naming the file and the field.

    .. code-block:: xml

        <shape type="gaussians" id="background">
            <string name="filename" value="background.ply"/>
        </shape>
    """


#: Every parameter the plugin reads (see the class docstring).
PARAMETERS = ("filename", "centers", "scales", "quaternions", "opacities", "normals", "albedo",
              "roughness", "lidar_albedo", "sun_visibility", "to_world", "extent")


def _tensor_prop(props, name):
    if name not in props:
        return None
    value = props.get(name)
    try:
        return np.array(value, dtype=np.float32)
    except Exception as exc:  # noqa: BLE001  (any conversion failure is a user error)
        raise GaussianFileError("gaussians: parameter '%s' is not an array (%s)" % (name, exc))


def cloud_from_props(props) -> GaussianCloud:
    """Build the Gaussian cloud named by a plugin's properties (file or tensors)."""
    if ("filename" in props):
        path = str(props.get("filename"))
        resolved = mi.file_resolver().resolve(path)
        # str(): Mitsuba's filesystem.path is not os.PathLike (os.fspath raised
        # TypeError, so no 'filename' could ever be loaded).
        return read_ply(str(resolved))
    centers = _tensor_prop(props, "centers")
    if centers is None:
        raise GaussianFileError("gaussians: give either 'filename' or the 'centers' "
                                "(+ 'scales', 'quaternions', 'opacities') tensors")
    n = centers.reshape(-1, 3).shape[0]

    def get(name, width, default=None):
        value = _tensor_prop(props, name)
        if value is None:
            return default
        return value.reshape(n, width) if width > 1 else value.reshape(n)

    # Material tensors are named like the shape's attributes, except the
    # normals (the cloud's ``normals``), as documented above.
    cloud = GaussianCloud(
        centers=centers.reshape(n, 3), scales=get("scales", 3, np.full((n, 3), 0.01, np.float32)),
        quaternions=get("quaternions", 4, np.tile(np.float32([1, 0, 0, 0]), (n, 1))),
        opacities=get("opacities", 1, np.ones(n, np.float32)),
        **{f.cloud: get(f.cloud if f.name == "normal" else f.name, f.width) for f in MATERIAL},
        source="gaussians '%s'" % props.id())
    cloud.validate()
    cloud.quaternions = cloud.quaternions / np.linalg.norm(cloud.quaternions, axis=1, keepdims=True)
    return cloud.with_defaults()


def apply_transform(cloud: GaussianCloud, matrix: np.ndarray) -> GaussianCloud:
    """Move a cloud by a 4x4 rigid transform with optional uniform scale."""
    from ..physics.gaussian_ply import matrix_to_quaternion, quaternion_to_matrix
    lin = matrix[:3, :3].astype(np.float64)
    s = np.cbrt(np.linalg.det(lin))
    rot = lin / s if abs(s) > 0 else lin
    if abs(s) < 1e-12 or not np.allclose(rot @ rot.T, np.eye(3), atol=1e-4):
        raise GaussianFileError("%s: to_world must be a rotation, translation and uniform "
                                "scale (Gaussians cannot be sheared)" % cloud.source)
    cloud.centers = (cloud.centers @ lin.T + matrix[:3, 3]).astype(np.float32)
    cloud.scales = (cloud.scales * abs(s)).astype(np.float32)
    r = quaternion_to_matrix(cloud.quaternions.astype(np.float64))
    cloud.quaternions = matrix_to_quaternion(rot[None] @ r).astype(np.float32)
    cloud.normals = (cloud.normals @ rot.T).astype(np.float32)
    return cloud


def ellipsoids_dict(cloud: GaussianCloud, shape_id: str = "", extent: float = 3.0) -> dict:
    """The ``ellipsoids`` plugin dictionary holding ``cloud`` and its material fields."""
    cloud = cloud.with_defaults()
    n = len(cloud)
    q = cloud.quaternions  # w x y z -> Dr.Jit's x y z w order inside 'data'
    scales = np.maximum(cloud.scales, MIN_SCALE)
    scales = np.maximum(scales, MIN_ASPECT * scales.max(axis=1, keepdims=True))
    data = np.concatenate([cloud.centers, scales,
                           q[:, 1:4], q[:, :1]], axis=1).astype(np.float32)
    normals = cloud.normals / np.maximum(np.linalg.norm(cloud.normals, axis=1, keepdims=True), 1e-12)
    d = {
        "type": "ellipsoids",
        "data": jit_tensor(data),
        "opacities": jit_tensor(np.clip(cloud.opacities, 0, 1).reshape(n, 1)),
        "extent": float(extent),
    }
    for f in MATERIAL:
        value = normals if f.name == "normal" else getattr(cloud, f.cloud)
        d[f.name] = jit_tensor(np.asarray(value, np.float32).reshape(n, f.width))
    if shape_id:
        d["id"] = shape_id
    return d


def cloud_from_shape(shape) -> GaussianCloud:
    """Read an ``ellipsoids``/``gaussians`` shape's current parameters back into numpy."""
    p = mi.traverse(shape)
    data = np.array(p["data"], np.float32).reshape(-1, 10)
    n = data.shape[0]

    def field(name, width):
        if name not in p:
            return None
        v = np.array(p[name], np.float32)
        return v.reshape(n, width) if width > 1 else v.reshape(n)

    quats = np.concatenate([data[:, 9:10], data[:, 6:9]], axis=1)
    return GaussianCloud(
        centers=data[:, :3].copy(), scales=data[:, 3:6].copy(), quaternions=quats,
        opacities=np.array(p["opacities"], np.float32).reshape(n),
        **{f.cloud: field(f.name, f.width) for f in MATERIAL},
        source="shape '%s'" % shape.id()).with_defaults()


def make_gaussians(props):
    """Plugin factory: a Mitsuba ``ellipsoids`` shape with the material fields."""
    try:
        cloud = cloud_from_props(props)
        if ("to_world" in props):
            m = np.array(props.get("to_world").matrix, np.float64).reshape(4, 4)
            cloud = apply_transform(cloud, m)
    except GaussianFileError as exc:
        raise ValueError(str(exc)) from None
    extent = float(props.get("extent", 3.0))
    if not extent > 0:
        raise ValueError("gaussians '%s': extent must be > 0" % props.id())
    if len(cloud) == 0:
        raise ValueError("%s: no Gaussians" % cloud.source)
    shape_id = props.id() or "gaussians"
    unknown = sorted(set(props.keys()) - set(PARAMETERS))
    if unknown:
        # A misspelt parameter would otherwise be ignored without a word.
        raise ValueError("gaussians '%s': unknown parameter(s) %s (known: %s)"
                         % (shape_id, ", ".join("'%s'" % u for u in unknown),
                            ", ".join(PARAMETERS)))
    for name in list(props.keys()):
        props.mark_queried(name)
    return mi.load_dict(ellipsoids_dict(cloud, shape_id, extent))


def register():
    mi.register_shape("gaussians", make_gaussians)
