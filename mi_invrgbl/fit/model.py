"""The optimised scene graph: Gaussian nodes as Dr.Jit variables.

Each ``gaussians`` node of the scene (the static ``background`` and one node
per moving object) is held here in its own frame (world for the background,
the object's frame for objects) in unconstrained form: one flat Dr.Jit array
per field of :mod:`mi_invrgbl.physics.fields`, keyed by the field's
``variable`` (``center``, ``log_scale``, ``rotation`` (x y z w),
``opacity_logit``, stage 1's ``colour``, and the material fields ``normal``,
``albedo``, ``roughness``, ``lidar_albedo``, ``sun_visibility``, ...).

:meth:`GaussianModel.push` writes a node's world-frame arrays into the scene's
``gaussians`` shape (``mi.traverse`` keys ``<id>.data``, ``<id>.opacities``,
...), differentiably, so the integrators' gathers see the optimiser's
variables. Objects are moved to their pose at a frame by a rigid transform of
centres, rotations and normals.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import drjit as dr
import mitsuba as mi

from ..physics import hits as hitlib
from ..physics.fields import BY_NAME, FIELDS, GEOMETRY, MATERIAL
from ..physics.gaussian_ply import GaussianCloud
from ..plugins.gaussians import cloud_from_shape, apply_transform
from .object_poses import RigidPose
from ..physics.host_arrays import jit_array

GEOMETRY_KEYS = tuple(f.variable for f in GEOMETRY)
MATERIAL_KEYS = tuple(f.variable for f in MATERIAL)
WIDTHS = {f.variable: f.width for f in FIELDS}
#: Opacity logit bounds: keeps sigmoid away from exactly 0/1 (log(1 - a) finite).
LOGIT_RANGE = BY_NAME["opacity"].storage_range()


@dataclass
class Node:
    """One ``gaussians`` shape being optimised."""
    name: str
    count: int
    dynamic: bool
    values: dict = field(default_factory=dict)   # key -> mi.Float (flat, width * count)

    def vec(self, key):
        v = self.values[key]
        w = WIDTHS[key]
        idx = dr.arange(mi.UInt32, self.count) * w
        if w == 1:
            return v
        if w == 3:
            return self.vec_of(v, 3)
        return mi.Vector4f(*[dr.gather(mi.Float, v, idx + j) for j in range(w)])

    def vec_of(self, flat, width):
        idx = dr.arange(mi.UInt32, self.count) * width
        return mi.Vector3f(*[dr.gather(mi.Float, flat, idx + j) for j in range(3)])

    def numpy(self, key):
        w = WIDTHS[key]
        a = np.array(self.values[key], np.float32)
        return a.reshape(self.count, w) if w > 1 else a.reshape(self.count)


def as_rigid(pose) -> RigidPose:
    """A pose as given (a 4x4 node -> world matrix, or a :class:`RigidPose`
    that stage 1 differentiates in its corrections)."""
    return pose if isinstance(pose, RigidPose) else RigidPose.from_matrix(pose)


def _interleave(vectors, count):
    """Flat (count * len(vectors),) array from a list of per-element Floats."""
    width = len(vectors)
    out = dr.zeros(mi.Float, count * width)
    idx = dr.arange(mi.UInt32, count) * width
    for j, v in enumerate(vectors):
        dr.scatter(out, v, idx + j)
    return out


class GaussianModel:
    """All optimised nodes plus the scene they are rendered in."""

    def __init__(self, scene, object_names=()):
        self.scene = scene
        self.params = mi.traverse(scene)
        self.nodes: dict[str, Node] = {}
        self.object_names = set(object_names)
        #: The poses (the mapping itself) the scene's objects were last
        #: pushed at (:meth:`push`); a trace through the scene sees them there.
        self.placed = None
        #: Node name -> the Dr.Jit registry id its hits carry in hit lists.
        self.shape_ids: dict[str, int] = {}
        for shape in scene.shapes():
            if shape.is_ellipsoids():
                self._add_node(shape)
        if not self.nodes:
            raise ValueError("the scene holds no 'gaussians' shape to fit")

    # ------------------------------------------------------------ set-up
    def _add_node(self, shape):
        name = shape.id()
        cloud = cloud_from_shape(shape)
        dynamic = name in self.object_names
        self.nodes[name] = Node(name, len(cloud), dynamic)
        self.shape_ids[name] = hitlib.shape_id(shape)
        self.set_cloud(name, cloud, local=not dynamic)

    def set_cloud(self, name, cloud: GaussianCloud, local=True, pose=None):
        """(Re)initialise a node from a cloud. ``pose`` (4x4) maps world to
        the node frame when the cloud is in world coordinates."""
        if pose is not None:
            cloud = apply_transform(cloud, np.linalg.inv(pose))
        node = self.nodes[name]
        node.count = len(cloud)
        node.values = {f.variable: jit_array(mi.Float, f.to_storage(getattr(cloud, f.cloud)))
                       for f in FIELDS}

    @property
    def total(self):
        return sum(n.count for n in self.nodes.values())

    # ------------------------------------------------------- world arrays
    def world_centers(self, node: Node, pose=None):
        """Differentiable world-frame centres of a node at ``pose`` (node -> world)."""
        c = node.vec("center")
        if pose is not None and node.dynamic:
            pose = as_rigid(pose)
            c = pose.rotation @ c + pose.translation
        return c

    def world_geometry(self, node: Node, pose=None):
        """Differentiable (data, opacities) of a node at ``pose`` (node -> world)."""
        c = self.world_centers(node, pose)
        q = node.vec("rotation")
        q = mi.Quaternion4f(q.x, q.y, q.z, q.w)
        q = q * dr.rsqrt(dr.maximum(dr.squared_norm(q), 1e-20))
        if pose is not None and node.dynamic:
            q = as_rigid(pose).quaternion * q
        s = dr.exp(node.vec("log_scale"))
        # Same thickening as the shape plugin: flatter Gaussians lose rays.
        smax = dr.maximum(dr.maximum(s.x, s.y), s.z)
        s = dr.maximum(s, dr.maximum(1e-2 * smax, 1e-6))
        data = _interleave([c.x, c.y, c.z, s.x, s.y, s.z, q.x, q.y, q.z, q.w], node.count)
        logit = dr.clip(node.values["opacity_logit"], *LOGIT_RANGE)
        return data, dr.rcp(1.0 + dr.exp(-logit))

    def world_normal(self, node: Node, pose=None, values=None):
        """World-frame unit normals (flat), from ``values`` (default: the node's)."""
        n = node.vec("normal") if values is None else node.vec_of(values, 3)
        if pose is not None and node.dynamic:
            n = as_rigid(pose).rotation @ n
        n = n * dr.rsqrt(dr.maximum(dr.squared_norm(n), 1e-20))
        return _interleave([n.x, n.y, n.z], node.count)

    def push(self, poses=None, stage=1, update=True):
        """Write every node's world arrays into the scene (differentiably).

        ``poses`` maps object names to their node -> world pose at this frame
        (4x4, or a :class:`RigidPose`).
        Stage 1 shows the view-independent colour as albedo.
        """
        self.placed = poses
        poses = poses or {}
        for name, node in self.nodes.items():
            data, opac = self.world_geometry(node, poses.get(name))
            p = self.params
            p[name + ".data"] = data
            p[name + ".opacities"] = opac
            for f in MATERIAL:
                if name + "." + f.name not in p:
                    continue
                if f.name == "normal":
                    value = self.world_normal(node, poses.get(name))
                elif f.name == "albedo" and stage == 1:
                    value = node.values["colour"]
                else:
                    value = node.values[f.variable]
                p[name + "." + f.name] = value
        if update:
            self.params.update()

    # ------------------------------------------------------ numpy export
    def cloud(self, name, stage=2) -> GaussianCloud:
        """The node as a :class:`GaussianCloud` in its own frame."""
        node = self.nodes[name]
        arrays = {f.cloud: f.from_storage(node.numpy(f.variable)).astype(np.float32)
                  for f in GEOMETRY + MATERIAL}
        if stage != 2:
            arrays["albedo"] = BY_NAME["colour"].from_storage(node.numpy("colour")).astype(np.float32)
        return GaussianCloud(**arrays, source="node '%s'" % name)

    def state_dict(self):
        return {"%s.%s" % (name, k): np.array(v, np.float32)
                for name, node in self.nodes.items() for k, v in node.values.items()}

    def load_state_dict(self, state):
        for key, value in state.items():
            name, k = key.split(".", 1)
            if name not in self.nodes:
                continue
            node = self.nodes[name]
            node.values[k] = jit_array(mi.Float, value)
            node.count = node.values[k].shape[0] // WIDTHS[k] if k in WIDTHS else node.count
