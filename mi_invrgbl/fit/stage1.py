"""Stage 1: geometry, opacity and a view-independent colour.

Each iteration takes one training frame (objects placed at their pose there),
a random batch of its camera pixels and of its LiDAR beams, traces them
through the current Gaussians and fits

* colour: ``L_rgb`` between the blended colour (plus the sky behind) and the image,
* LiDAR geometry: ``L_range`` (L1 on beams with a return) and ``L_drop``
  (binary cross-entropy between accumulated opacity and the observed
  return/no-return mask).

Batches are drawn only from the pixels and beams that count
(:meth:`~.observations.Masked.valid_index`: motion masks left out).

Every ``densify_every`` iterations Gaussians that are nearly transparent are
pruned and those with large positional gradients are split in two smaller
ones, up to ``max_gaussians`` (3D Gaussian Splatting clones the small ones
instead; ``split_scale`` does that above a size, and measured worse here).
"""

from __future__ import annotations

import numpy as np
import drjit as dr
import mitsuba as mi

from . import losses
from .budget import stage_progress
from ..physics.fields import BY_NAME, GEOMETRY
from ..physics.gaussian_ply import GaussianCloud
from .render import batch_order, camera_unlit, lidar_beams
from .render import gather_rays as _gather_rays
from .steps import safe_step
from .evaluate import score_stage1
from .object_poses import PARTS as POSE_PARTS
from .variables import GaussianVariable, Optimizer, PoseVariable, SkySH
from ..physics.host_arrays import jit_array

#: Learning rate of the sky's SH coefficients (the Gaussians' are in the field table).
SKY_LR = 1e-2


def moves_with_positions(variable) -> bool:
    """The variables whose learning rate follows the centres' schedule: the
    centres, and the objects' pose corrections, which settle with the
    positions they carry."""
    return isinstance(variable, PoseVariable) or (
        isinstance(variable, GaussianVariable) and variable.field is BY_NAME["center"])


class Stage1:
    def __init__(self, ctx):
        self.ctx = ctx
        cfg = ctx.config
        self.model = ctx.model
        self.rng = ctx.rng
        self.grad_accum = {}
        self._view_origin = None  # the step camera's position, for densify_screen
        self.build_optimizer()
        self.batch_camera = cfg.batch_rays
        self.batch_lidar = cfg.lidar_batch_rays

    def variables(self):
        """Geometry and the view-independent colour of every node, and the sky."""
        scale = self.ctx.config.lr_scale
        out = [GaussianVariable(self.model, name, f, f.lr * scale)
               for name in self.model.nodes for f in GEOMETRY + (BY_NAME["colour"],)]
        out.append(SkySH(self.ctx, SKY_LR * scale))
        poses = self.ctx.object_poses
        if poses:
            out += [PoseVariable(poses, name, part, lr * scale, bound)
                    for name in poses.objects for part, (lr, bound) in POSE_PARTS.items()]
        return out

    def build_optimizer(self):
        self.opt = Optimizer(self.variables())

    def pull(self):
        """Adam's values into the model; every frame's object poses follow
        the corrections (the scores and everything after stage 1 read
        ``frame.poses``). A step needs no baked poses (it renders with the
        corrections themselves), so :meth:`iteration` only writes Adam's
        values: baking every frame's poses took 6 % of a KITTI step
        (0.017 of 0.298 s)."""
        self.opt.pull()
        if self.ctx.object_poses:
            self.ctx.object_poses.bake()

    def score(self, frames, **kw):
        """:func:`~.evaluate.score_stage1` of ``frames`` as the stage stands."""
        self.pull()
        return score_stage1(self.ctx, frames, **kw)

    def frame_poses(self, frame):
        """The poses a training step renders ``frame`` with: differentiable
        in the pose corrections where they are fitted."""
        poses = self.ctx.object_poses
        return poses.poses(frame) if poses else frame.poses

    def snapshot(self):
        """The stage's state, Gaussians (their number changes with
        densification), sky and object poses, as host arrays to come back to."""
        self.pull()
        poses = self.ctx.object_poses
        return (self.model.state_dict(),
                np.array(dr.detach(self.ctx.params[self.ctx.sky_key]), np.float32),
                poses.state_dict() if poses else {})

    def restore(self, snapshot):
        """Return to a :meth:`snapshot`; Adam starts afresh from it."""
        model, sky, poses = snapshot
        self.model.load_state_dict(model)
        self.ctx.params[self.ctx.sky_key] = jit_array(mi.Float, sky)
        self.ctx.params.update()
        if self.ctx.object_poses:
            self.ctx.object_poses.load_state_dict(poses)
            self.ctx.object_poses.bake()
        self.grad_accum = {}
        self.build_optimizer()

    def loss_terms(self, frame):
        cfg = self.ctx.config
        terms = {}
        # Batches are drawn from the pixels and beams that count (masked
        # ones never enter a loss, nor the positional gradients).
        pool = frame.camera.valid_index() if frame.camera is not None else ()
        if len(pool) and cfg.weights.rgb > 0:
            cam = frame.camera
            n = len(pool)
            sel = batch_order(pool[self.rng.integers(0, n, min(self.batch_camera, n))])
            idx = jit_array(mi.UInt32, sel)
            # Through the pixel centres: rays through a random point of each
            # pixel (the image's box filter in expectation) scored 18.34 dB
            # against 18.46 on the KITTI excerpt's validation frames after
            # 600 steps, 18.38 against 18.50 rendered with 2 x 2 rays per
            # pixel as eval does (tests/bench/stage1_steps.py).
            rays = _gather_rays(cam.rays, idx)
            rgb, alpha, _ = camera_unlit(self.ctx.scene, rays, cfg.max_hits, cfg.min_transmittance)
            target = dr.gather(mi.Color3f, self.ctx.image_array(frame), idx)
            terms["rgb"] = losses.rgb_loss(rgb, target, space=cfg.rgb_space, norm=cfg.rgb_norm)
            if cam.sky is not None and cfg.stage1_sky > 0:
                terms["sky"] = losses.sky_loss(alpha, jit_array(mi.Bool, cam.sky[sel])) * cfg.stage1_sky
        pool = frame.lidar.valid_index() if frame.lidar is not None else ()
        if len(pool) and (cfg.stage1_range > 0 or cfg.stage1_drop > 0):
            lid = frame.lidar
            n = len(pool)
            sel = batch_order(pool[self.rng.integers(0, n, min(self.batch_lidar, n))])
            idx = jit_array(mi.UInt32, sel)
            rays = _gather_rays(lid.rays, idx)
            ch = lidar_beams(self.ctx.lidar_integrator, self.ctx.scene, rays,
                             dr.gather(mi.UInt32, lid.row, idx), dr.gather(mi.Float, lid.near, idx))
            hit = jit_array(mi.Bool, lid.hit.ravel()[sel])
            obs_range = jit_array(mi.Float, lid.range.ravel()[sel])
            both = hit & (ch[2] > 0)
            terms["range"] = losses.range_loss(ch[1], obs_range, both) * cfg.stage1_range
            terms["raydrop"] = losses.ray_drop_loss(ch[4], hit) * cfg.stage1_drop
        return terms

    def iteration(self, it):
        ctx = self.ctx
        frame = ctx.train_frames[self.rng.integers(0, len(ctx.train_frames))]
        self.opt.pull()
        self.model.push(self.frame_poses(frame), stage=1)
        self._view_origin = _camera_origin(frame) if self.ctx.config.densify_screen else None
        terms = self.loss_terms(frame)
        total = mi.Float(0.0)
        for v in terms.values():
            total = total + v
        ok = safe_step(self.opt.adam, total, ctx.log, ctx.lr_state, "stage-1 iteration %d" % it,
                       before_step=self._accumulate_gradients)
        if ok:
            self.opt.clamp()
            self.hold_objects()
        return float(total[0]), {k: float(v[0]) for k, v in terms.items()}, ok

    def hold_objects(self):
        """The moving objects' Gaussians back inside their boxes (:mod:`.object_bounds`)."""
        for box in self.ctx.object_boxes:
            box.apply(self.opt.adam)

    def after_step(self, it, total, progress=None):
        """Densify every ``densify_every`` iterations in the first
        ``densify_until`` of the stage (``progress``, 0..1: how far the stage
        is, by default ``it / total``; a budgeted stage counts its time too)."""
        cfg = self.ctx.config
        progress = stage_progress(it, total) if progress is None else progress
        if cfg.densify_every and it % cfg.densify_every == 0 and progress <= cfg.densify_until:
            report = self.densify()
            self.ctx.log("\n[fit] densify @%d: %s" % (it, ", ".join(
                "%s %d pruned, %d cloned, %d split: %d" % (n, *r) for n, r in report.items())))

    def _accumulate_gradients(self):
        # Positional gradient magnitude per Gaussian, for densification. Summed
        # on the device and read back only when densifying: a read-back per
        # iteration would wait for the device every step.
        for name, node in self.model.nodes.items():
            key = "%s.%s" % (name, BY_NAME["center"].variable)
            if key not in self.opt.variables:
                continue
            g = dr.grad(self.opt.adam[key])
            if dr.width(g) != 3 * node.count:
                continue
            idx = dr.arange(mi.UInt32, node.count) * 3
            norm = dr.sqrt(sum(dr.square(dr.gather(mi.Float, g, idx + k)) for k in range(3)))
            origin = self._view_origin
            if origin is not None:
                # Metres to image space: a shift of x metres at distance d
                # moves the Gaussian's image by about f x / d pixels, so the
                # image-space gradient is the metric one times d / f (f is
                # the same for every Gaussian and left out).
                norm = norm * _distance_to(self.model, name, node, origin)
            acc = self.grad_accum.get(name)
            if acc is None or dr.width(acc[0]) != node.count:
                acc = [dr.zeros(mi.Float, node.count), dr.zeros(mi.Float, node.count)]
            acc = [acc[0] + norm, acc[1] + dr.select(norm > 0, 1.0, 0.0)]
            dr.eval(acc[0], acc[1])
            self.grad_accum[name] = acc

    def prune_sky_lookalikes(self):
        """Remove the Gaussians that only stand in for the sky and the unseen
        ones above them in their columns (:mod:`.sky_lookalikes`); returns
        ``(look-alikes, above)``, each the count removed per node."""
        from .sky_lookalikes import find_sky_lookalikes
        self.pull()
        masks = find_sky_lookalikes(self.ctx, self.ctx.train_frames)
        removed, above, parents = {}, {}, {}
        for name, (lookalike, over) in masks.items():
            node = self.model.nodes[name]
            drop = lookalike | over
            if not drop.any() or drop.size != node.count:
                continue
            cloud = self.model.cloud(name, stage=1)
            cloud.albedo = np.clip(node.numpy("colour"), 0, 1)
            self._replace_cloud(name, cloud.subset(~drop))
            removed[name], above[name] = int(lookalike.sum()), int(over.sum())
            parents[name] = np.nonzero(~drop)[0]
        if removed:
            self.opt = self.opt.rebuild(self.variables(), parents)
        return removed, above

    def _replace_cloud(self, name, cloud):
        """Swap a node's Gaussians (stage-1 colour carried in ``cloud.albedo``).

        The stage-2 fields' old per-Gaussian rows travel with the cloud: they
        are not optimised yet."""
        self.model.set_cloud(name, cloud, local=True)
        self.model.nodes[name].values["colour"] = jit_array(mi.Float, cloud.albedo)

    # ------------------------------------------------------------ densify
    def densify(self):
        """Prune transparent Gaussians, split/clone those with large gradients."""
        cfg = self.ctx.config
        self.pull()
        report, parents, fresh = {}, {}, {}
        total_now = self.model.total
        # Each node's mean gradients and which Gaussians were seen, read back
        # once (nodes whose accumulation no longer matches their count grow
        # nothing); ranked per node, or with one cut over all of them.
        means = {name: _mean_gradients(acc) for name, acc in self.grad_accum.items()
                 if name in self.model.nodes and dr.width(acc[0]) == self.model.nodes[name].count}
        scene_cut = None
        if cfg.densify_scope == "scene":
            seen_all = [mean[seen] for mean, seen in means.values()]
            scene_cut = _quota_cut(np.concatenate(seen_all) if seen_all else np.zeros(0, np.float32),
                                   cfg.densify_fraction, cfg.densify_grad)
        for name, node in self.model.nodes.items():
            cloud = self.model.cloud(name, stage=1)
            colour = np.clip(node.numpy("colour"), 0, 1)
            cloud.albedo = colour
            keep = cloud.opacities > cfg.prune_opacity
            grow = np.zeros(len(cloud), bool)
            if name in means:
                mean_grad, seen = means[name]
                budget = max(0, cfg.max_gaussians - total_now)
                # The largest positional gradients (top ``densify_fraction``),
                # as long as they are not negligible in absolute terms.
                cut = scene_cut if scene_cut is not None else \
                    _quota_cut(mean_grad[seen], cfg.densify_fraction, cfg.densify_grad)
                cand = np.nonzero(keep & (mean_grad >= cut))[0]
                if budget and cand.size:
                    cand = cand[np.argsort(-mean_grad[cand])][: min(budget, cand.size)]
                    grow[cand] = True
            big = cloud.scales.max(axis=1) > cfg.split_scale
            split = grow & big
            clone = grow & ~big
            # A clone and its parent share the parent's opacity a so that the
            # pair lets through what the parent did: (1 - a')^2 = 1 - a (a
            # full-opacity copy thickens the surface). Clones still cost
            # fidelity on the street (``FitConfig.split_scale``), so by default
            # every growing Gaussian is split instead.
            cloud.opacities = np.where(clone, 1.0 - np.sqrt(np.clip(1.0 - cloud.opacities, 0, 1)),
                                       cloud.opacities).astype(np.float32)
            # Rows of the new arrays: the row of the old ones each comes from.
            # Kept Gaussians continue theirs (and its Adam moments); clones
            # and split halves are fresh (Optimizer.rebuild).
            rows = [np.nonzero(keep & ~split)[0]]
            parts = [cloud.subset(keep & ~split)]
            if clone.any():
                parts.append(cloud.subset(clone))
                rows.append(np.nonzero(clone)[0])
            if split.any():
                rows.append(np.tile(np.nonzero(split)[0], 2))
                for sign in (-1.0, 1.0):
                    s = cloud.subset(split)
                    rot = _rotation(s.quaternions)
                    offset = np.einsum("nij,nj->ni", rot, s.scales * self.rng.normal(size=s.scales.shape))
                    s.centers = (s.centers + sign * 0.5 * offset).astype(np.float32)
                    s.scales = (s.scales / 1.6).astype(np.float32)
                    parts.append(s)
            self._replace_cloud(name, GaussianCloud.concat(parts, cloud.source))
            node = self.model.nodes[name]
            report[name] = (int((~keep).sum()), int(clone.sum()), int(split.sum()), node.count)
            parents[name] = np.concatenate(rows)
            fresh[name] = np.arange(len(parents[name])) >= len(rows[0])
            total_now = total_now - len(cloud) + node.count
        self.grad_accum = {}
        self.opt = self.opt.rebuild(self.variables(), parents, fresh)
        self.hold_objects()
        return report


def _mean_gradients(acc):
    """Each Gaussian's mean accumulated positional gradient since the last
    densification (``acc``: summed gradient norms and step counts), and
    which of them were seen at all."""
    total, steps = (np.array(a, np.float32) for a in acc)
    return total / np.maximum(steps, 1), steps > 0


def _quota_cut(seen: np.ndarray, fraction, floor) -> float:
    """The gradient a Gaussian must reach to grow: the top ``fraction`` of
    ``seen`` (mean gradients), but never below ``floor``; infinite when
    nothing was seen."""
    if not seen.size:
        return np.inf
    return max(floor, float(np.percentile(seen, 100 * (1 - fraction))))


def _camera_origin(frame):
    """The step's camera position (world), or None for a frame without images."""
    if frame.camera is None:
        return None
    o = frame.camera.sensor.world_transform().translation()
    return mi.Point3f(o)


def _distance_to(model, name, node, origin):
    """Each Gaussian's distance from ``origin`` where the model is placed now
    (detached; moving objects at their pose of the step)."""
    with dr.suspend_grad():
        c = model.world_centers(node, (model.placed or {}).get(name))
        return dr.norm(c - origin)


def _rotation(q_wxyz):
    from ..physics.gaussian_ply import quaternion_to_matrix
    return quaternion_to_matrix(q_wxyz.astype(np.float64))
