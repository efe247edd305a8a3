"""Stage 2: materials, lighting and the LiDAR sensor response on frozen geometry.

Before the first iteration every frame is traced once (:func:`.render.freeze`)
and the per-Gaussian sky/sun visibility is computed once per object
placement (one cache for a static scene, one per frame when objects move).
An iteration is then gathers and sums over cached arrays:

* ``L_rgb``: shaded colour (``invrgbl``'s per-Gaussian PBR shading) vs the image;
* ``L_lidar``: the paper's LiDAR intensity with the sensor response vs the
  observed intensity, on beams with a return;
* ``L_rgb->lidar``: bilateral smoothness of the rendered LiDAR-albedo map,
  weighted by the rendered RGB albedo;
* ``L_lidar->rgb``: variance of the rendered RGB albedo inside SLIC
  superpixels of the LiDAR-albedo map;
* ``L_nor`` / ``L_mat``: prior maps, where a frame has them.

Optimised: per-Gaussian normal, albedo, roughness, LiDAR albedo and (with a
sun) sun visibility; the SH sky, the sun's irradiance and, on request
(``learn_sun_direction``, with learned sun visibility), its direction;
range/angle exponents and per-beam gains. The direction is off by default: it
reaches the images only through ``n.l`` and the specular lobe, which the free
per-Gaussian albedo can absorb, and on the synthetic street it moved the sun
8 degrees but away from the truth.

Sun visibility is the paper's ``v_sun``: traced once through the frozen
Gaussians (:meth:`Stage2.init_shading`, which also finds shadows the trace
missed from the LiDAR albedo), then learned. Shadows cast by
what the fit lacks (walls above the LiDAR's top beam, thin or see-through
Gaussians) would otherwise have to be explained as dark albedo; with
``L_lidar->rgb`` asking the albedo to be uniform where the LiDAR albedo is,
the dark patch is explained as shadow instead.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import drjit as dr
import mitsuba as mi

from ..physics import coat
from ..physics import hits as hitlib
from ..physics.colour import LUMINANCE, linear_to_srgb
from ..physics.lighting import (GaussianLighting, GaussianTable, LightingCache, light_at,
                                moving_shadows, point_lights, retrace_turned, shadow_origins,
                                split_transmittance, transmittance)
from . import losses, shading_init
from ..physics.fields import BY_NAME, MATERIAL
from .render import (Response, VirtualNode, camera_shaded, freeze, freeze_pixels,
                     frozen_gaussian_hits, lidar_shaded)
from .steps import safe_step
from .variables import GaussianVariable, Optimizer, ResponseVariable, SkySH, SunVariable
from .superpixels import slic_labels
from ..physics.host_arrays import jit_array

#: Degrees a Gaussian's normal may turn before :meth:`Stage2.refresh_lighting`
#: traces its sky directions again. The integrator re-traces every change.
#: At 1 degree an 8-minute KITTI fit re-traced 12 000 Gaussians per
#: refresh, 5.4 s each, half of its stage 2; a turn of a few degrees moves
#: the visibility of M = 16 cosine-weighted directions little.
RETRACE_TURN_DEG = 3.0

#: Fixed-point rounds that make the start's bounce light the render's
#: (:meth:`Stage2._set_light_level`); the bounce is a small share of the light,
#: so each round shrinks the mismatch several-fold.
BOUNCE_ROUNDS = 3

#: Roughness the start also tries for every Gaussian besides the one it has
#: (the import's, 0.5 unless ``import --roughness`` says otherwise), scored
#: like the other start choices on the validation frames
#: (:meth:`Stage2._choose_roughness`).
#: Seen from a car, road and walls are viewed at grazing angles, where the
#: Fresnel term of a lobe of roughness 0.5 reflects much of a bright sky:
#: the specular light the start subtracts from stage 1's colour can exceed
#: it, and the albedo then sits at its floor with the picture too bright.
#: Both 8-minute fits measured chose 1: KITTI's start scored 16.85 / 17.06 /
#: 17.22 dB at 0.5 / 0.75 / 1, the street's 27.59 / 27.76 / 27.83.
START_ROUGHNESS = (0.75, 1.0)

#: Roughness the start tries only for some Gaussians: glossy surfaces
#: (car paint) whose highlights move with the view. After the starts above
#: and these are made, each Gaussian takes the roughness whose start renders
#: its pixels of the training frames best by a margin
#: (:meth:`Stage2._per_gaussian_roughness`), and that start is kept if it
#: scores at least as well on the validation frames as the best one
#: roughness for all, which is never a glossy one. From a rough start stage
#: 2's gradient does not find a narrow lobe: the glossy Gaussians' albedo
#: then explains their highlights (docs/measurements.md, "Glossy starts per
#: Gaussian").
GLOSSY_START_ROUGHNESS = (0.1, 0.3)

#: A Gaussian leaves the best start's roughness for another only where that
#: one's mean squared pixel error over its pixels is below this share of the
#: best start's: a margin against noise and against the roughness-albedo
#: trade every start can make. At 0.8, with 0.3 allowed for all, 95 % of the
#: street's Gaussians went to 0.3 and its roughness error doubled; at 0.6,
#: 2 % leave 0.75, and the cars end at 0.29-0.35 (truth 0.15-0.2) where
#: without them they ended at 0.61-0.64.
PER_GAUSSIAN_MARGIN = 0.6

#: ... and only where its blend weights over the training frames sum to at
#: least this many pixels.
PER_GAUSSIAN_MIN_PIXELS = 4.0

#: Degrees the sun may turn (``--learn-sun-direction``) before the moving
#: objects' shadows of a frame are traced again (:meth:`FrozenScene.moving_shadow`).
MOVING_SHADOW_TURN_DEG = 0.5

#: Learning rates of the scene-wide variables (the Gaussians' are in the field table).
STAGE2_LR = {"sky": 1e-2, "sun": 2e-2, "sun_direction": 2e-3,
             "range_exponent": 2e-3, "angle_exponent": 2e-3,
             "beam_gains": 1e-2}


class FrozenScene:
    """Cached traversals and visibility of every frame (geometry frozen)."""

    def __init__(self, ctx, frames, min_weight=1e-4):
        """``min_weight``: hits blended with less weight are not cached (see
        :func:`.render.freeze`)."""
        self.ctx = ctx
        cfg = ctx.config
        model = ctx.model
        self.camera, self.lidar, self.caches, self.geometry = {}, {}, {}, {}
        self.pattern_caches = {}
        # Per-frame visibility (objects' shadows move with them) costs G x M
        # shadow rays per frame; by default one cache is shared and lighting is
        # evaluated with the objects placed as in one frame, :attr:`first`.
        dynamic = any(n.dynamic for n in model.nodes.values()) and cfg.per_frame_visibility
        self.per_frame = dynamic
        #: The frame whose object placement the shared lighting is traced at:
        #: the first training frame (the one stage 2's start is set up in),
        #: else the first frame.
        train = [t for t in ctx.train_frames if any(t is f for f in frames)]
        self.first = train[0] if train else (frames[0] if frames else None)
        #: Shape ids of the moving nodes (their shadows: :meth:`moving_shadow`).
        self.moving_ids = {model.shape_ids[n] for n, node in model.nodes.items() if node.dynamic}
        #: frame index -> (sun direction, the moving nodes' shadow factor).
        self._moving = {}
        #: What :meth:`moving_shadow` traced: frames (a turned sun counts
        #: again), shadow rays, seconds (metrics.json ``moving_shadows``).
        self.moving_traced = {"frames": 0, "rays": 0, "seconds": 0.0}
        shared = LightingCache()
        with dr.suspend_grad():
            for frame in frames:
                model.push(frame.poses, stage=2)
                geo = {}
                for name, node in model.nodes.items():
                    data, opac = model.world_geometry(node, frame.poses.get(name))
                    data, opac = dr.detach(data), dr.detach(opac)
                    dr.eval(data, opac)
                    geo[name] = (data, opac)
                # Static nodes share their arrays across frames, so a static
                # scene's lighting cache key (array identities) stays valid.
                for name, node in model.nodes.items():
                    if not node.dynamic and frames and frame is not frames[0]:
                        geo[name] = self.geometry[frames[0].index][name]
                self.geometry[frame.index] = geo
                self.caches[frame.index] = LightingCache() if dynamic else shared
                if frame.camera is not None:
                    self.camera[frame.index] = freeze_pixels(ctx.scene, frame.camera,
                                                             cfg.pixel_grid, cfg.max_hits,
                                                             cfg.min_transmittance, min_weight)
                if frame.lidar is not None:
                    self.lidar[frame.index] = freeze(ctx.scene, frame.lidar.rays, cfg.max_hits,
                                                     cfg.min_transmittance, min_weight)

    def nbytes(self):
        return sum(f.nbytes() for f in list(self.camera.values()) + list(self.lidar.values()))

    def cache(self, frame, pattern=0):
        """``frame``'s lighting cache for sky sample pattern ``pattern`` (frames
        that share the pattern-0 cache share the others too)."""
        first = self.caches[frame.index]
        if pattern == 0:
            return first
        return self.pattern_caches.setdefault((id(first), pattern), LightingCache())

    def place(self, frame):
        """Put the scene's objects where ``frame``'s lighting is traced: at
        ``frame``'s poses with per-frame visibility, else at :attr:`first`'s.

        A trace of sky or sun visibility goes through the scene as it was
        last pushed, while the Gaussians it starts from come from the
        frozen geometry of that placement; the two must agree. Pushed only
        when they do not (a push rebuilds the scene's acceleration
        structure)."""
        target = frame if self.per_frame else self.first
        if target is not None and self.ctx.model.placed is not target.poses:
            self.ctx.model.push(target.poses, stage=2)

    def moving_shadow(self, frame, direction):
        """(G,) factor on the learned sun visibility in ``frame``: the sun's
        transmittance towards ``direction`` through the moving nodes where
        ``frame`` has them (:func:`~mi_invrgbl.physics.lighting.moving_shadows`),
        in the global index order of :meth:`nodes`. Traced once per frame
        and kept while the sun turns by less than
        :data:`MOVING_SHADOW_TURN_DEG`; the moving nodes' own Gaussians get 1."""
        d = np.asarray(direction, np.float64).ravel()
        d = d / np.linalg.norm(d)
        kept = self._moving.get(frame.index)
        if kept is not None and float(kept[0] @ d) >= np.cos(np.radians(MOVING_SHADOW_TURN_DEG)):
            return kept[1]
        model, scene = self.ctx.model, self.ctx.scene
        t = time.perf_counter()
        with dr.suspend_grad():
            if model.placed is not frame.poses:
                model.push(frame.poses, stage=2)
            by_id = {n.shape.id(): n for n in hitlib.gaussian_nodes(scene)}
            ordered = [by_id[name] for name in model.nodes]
            table = GaussianTable.build(ordered).load_geometry()
            factor, rays = moving_shadows(ordered, table, d, self.moving_ids,
                                          return_rays=True)
            dr.eval(factor)
        self._moving[frame.index] = (d, factor)
        self.moving_traced["frames"] += 1
        self.moving_traced["rays"] += rays
        self.moving_traced["seconds"] += time.perf_counter() - t
        return factor

    def nodes(self, frame, values):
        """Virtual nodes of ``frame``: frozen geometry + the material variables."""
        out = []
        model = self.ctx.model
        if not self.per_frame:
            frame = self.first
        for name, node in model.nodes.items():
            data, opac = self.geometry[frame.index][name]
            pose = frame.poses.get(name)
            key = lambda f: "%s.%s" % (name, f.variable)  # noqa: E731
            normal = values[key(BY_NAME["normal"])]
            if pose is not None and node.dynamic:
                normal = model.world_normal(node, pose, normal)
            attributes = {f.name: normal if f.name == "normal" else values[key(f)] for f in MATERIAL}
            out.append(VirtualNode(model.shape_ids[name], data, opac, attributes, node.count))
        return out


@dataclass
class StartLight:
    """The light of the start the scene holds (:meth:`Stage2._init_shading`),
    as :meth:`Stage2._unclip` needs it: the per-Gaussian terms
    :meth:`Stage2._set_light_level` takes (``light``), the level ``k``, the
    sky and sun at level 1, the Gaussians' order, and, with a sun, each
    one's sun visibility, incidence cosine, LiDAR albedo (or None) and
    whether the cameras see it."""
    light: tuple
    k: float
    sky0: object
    sun0: np.ndarray | None
    names: list
    table: object
    counts: list
    visibility: np.ndarray | None = None
    cos: np.ndarray | None = None
    lidar_albedo: np.ndarray | None = None
    seen: np.ndarray | None = None


class Stage2:
    def __init__(self, ctx, frozen: FrozenScene, model_kind="pbr"):
        self.ctx = ctx
        self.frozen = frozen
        self.model_kind = model_kind
        self.rng = ctx.rng
        self.labels = {}
        cfg = ctx.config
        # Learned v_sun only where there is a sun whose shading is fitted.
        self.learn_sun_visibility = bool(cfg.sun_visibility == "learn" and ctx.use_sun
                                         and ctx.sun_key is not None and cfg.weights.rgb > 0)
        # The learned field then holds the static scene's shadows, and each
        # frame's moving objects cast theirs on top (traced per frame: G
        # rays at most, not the G x M of --per-frame-visibility, which
        # traces them into every cache already).
        self.moving_shadows = bool(self.learn_sun_visibility and cfg.moving_shadows
                                   and frozen.moving_ids and not frozen.per_frame)
        # What L_anchor pulls the normals back to: their unit normals now, at
        # stage 2's start (a fit resumed in stage 2 anchors to the normals it
        # resumed with).
        key = BY_NAME["normal"].variable
        self.normal_start = {}
        for name, node in ctx.model.nodes.items():
            n = dr.unravel(mi.Vector3f, dr.detach(node.values[key]))
            self.normal_start[name] = dr.ravel(dr.normalize(n))
        #: Steps taken since the lighting caches last followed the normals.
        self.lighting_stale = False
        self.retraced = {"refreshes": 0, "gaussians": 0, "seconds": 0.0}
        #: Validation scorings of the start's choices: count, seconds.
        self.start_scorings = [0, 0.0]
        #: The light of the start the scene holds (set by :meth:`_init_shading`).
        self._start_light = None
        self.build_optimizer()

    def variables(self):
        """The stage's variables: materials of every node, sky and sun, LiDAR response."""
        ctx, cfg = self.ctx, self.ctx.config
        out = [GaussianVariable(ctx.model, name, f, f.lr) for name in ctx.model.nodes for f in MATERIAL
               if f.name != "sun_visibility" or self.learn_sun_visibility]
        if cfg.weights.rgb > 0:
            out.append(SkySH(ctx, STAGE2_LR["sky"]))
            if ctx.use_sun:
                out.append(SunVariable(ctx, "sun_irradiance", STAGE2_LR["sun"]))
            if self.learn_sun_visibility and cfg.learn_sun_direction:
                # With v_sun stored per Gaussian the direction moves only the
                # shading (n.l, the specular lobe), never a cached trace.
                out.append(SunVariable(ctx, "sun_direction", STAGE2_LR["sun_direction"]))
        if cfg.weights.lidar > 0:
            out += [ResponseVariable(ctx, k, STAGE2_LR[k] if cfg.fit_response else 0.0)
                    for k in ("range_exponent", "angle_exponent", "beam_gains")]
        return out

    def build_optimizer(self, only=None):
        """Adam over :meth:`variables` (those ``only(handle)`` accepts, if given)."""
        self.opt = Optimizer([v for v in self.variables() if only is None or only(v)])

    def model_values(self):
        """The Gaussians' materials by key as the model holds them, without
        the optimiser's copies. A start (:meth:`_init_shading`) sets the
        materials and the scene's light itself before the optimiser is built
        again: :meth:`values` would hand it the last build's roughness (which
        the coat's transmission depends on) and write the last build's sky
        and sun back into the scene, over the light the start has just set."""
        model = self.ctx.model
        return {"%s.%s" % (name, f.variable): model.nodes[name].values[f.variable]
                for name in model.nodes for f in MATERIAL}

    def values(self):
        """Current variables by key (grad-enabled where optimised); the sky and
        sun are written into the scene."""
        ctx = self.ctx
        vals = self.model_values()
        in_scene = False
        for var, value in self.opt.items():
            vals[var.key] = value
            if var.in_scene:
                # (The SH coefficients above the selected order stay zero.)
                var.write(value)
                in_scene = True
        if in_scene:
            ctx.params.update()
        return vals

    def response(self, vals):
        r = self.ctx.response
        return Response(vals.get("response.range_exponent", r.range_exponent),
                        vals.get("response.angle_exponent", r.angle_exponent),
                        vals.get("response.beam_gains", r.beam_gains))

    def snapshot(self):
        """Copies of the optimised variables' values, to come back to."""
        return {k: dr.copy(dr.detach(self.opt.adam[k])) for k in self.opt.variables}

    def restore(self, snapshot):
        """Return to a :meth:`snapshot`."""
        for k, v in snapshot.items():
            self.opt.adam[k] = v
        self.lighting_stale = True

    def commit(self):
        """Write the optimised variables back into the model, scene and response."""
        self.opt.commit()
        self.ctx.params.update()

    def init_shading(self):
        """Start stage 2 from stage 1: trace the sun visibility (objects at the
        first training frame's pose), estimate the sun's irradiance from lit
        and shadowed Gaussians, and set the albedo that reproduces the stage-1
        colour under that light (:mod:`.shading_init`). Returns a report.

        Where the lighting selection kept other sun directions
        (``selection.sun.alternatives``: directions far apart that explained
        at least half as much of the within-surface shading), and where the
        facings' sun irradiance disagrees with the selection's level, the
        start is made under each candidate (``start_candidates`` in the
        report): the shading test ranks directions by how well their shadows
        fit log-luminance and the two levels come from different evidence.
        Each start is scored on the validation frames, and among those
        within :data:`~.shading_init.START_PSNR_MARGIN` of the best, the one
        whose albedo varies least within groups of one LiDAR albedo is kept
        (:func:`~.shading_init.choose_start`). The images alone lean towards
        weak suns, which misplace the fewest shadows (on a street not tuned
        on, a start 31 degrees off with a sun of 0.66 scored 0.6 dB above
        one 7 degrees off with the facings' 4.6, truth 4.0); the LiDAR
        albedo, which sees no shadows, tells which light leaves none in the
        albedo. On the KITTI excerpt, stage 1 runs of different length
        ranked directions up to 60 degrees apart first, and under one of
        them stage 2 started 4.6 dB below stage 1 with the selection's
        level: the margin keeps such starts out. The kept start is
        then made again with the Gaussians' roughness raised
        (:meth:`_choose_roughness`) and the best of those kept."""
        ctx = self.ctx
        sun = ctx.selection.get("sun", {})
        # Each start scales the sky by its light level: every one starts
        # from the selection's sky.
        sky = np.array(dr.detach(ctx.params[ctx.sky_key]), np.float32)

        def start(d, keep):
            return self.start_under(sky, d, keep)
        if not ctx.use_sun:
            report = start(None, None)
            report = self._choose_roughness(report, self._start_score(report), True,
                                            lambda: start(None, None))
            self.build_optimizer()
            return self._with_scorings(report)
        directions = sun.get("alternatives") or [
            np.array(dr.detach(ctx.params[ctx.sun_dir_key]), np.float64).ravel().tolist()]
        trials = []
        for d in directions:
            report = start(d, None)
            trials.append((self._start_score(report), d, report))
            if shading_init.facings_overruled(report.get("sun_irradiance_from", "")):
                # The facings and the selection disagree on the sun's level
                # (KITTI, 30-minute stage 1: facings 28-32, selection 2.3-2.5;
                # the two rules' bounds are set on the street): the start
                # under each decides.
                report = start(d, "facings")
                trials.append((self._start_score(report), d, report))
        best = shading_init.choose_start([t[0] for t in trials],
                                         [t[2].get("albedo_spread") for t in trials])
        score, d, report = trials[best]
        # The roughness starts keep the sun level this start took: each
        # re-estimates the facings under its own roughness (the coat's
        # transmission changes the effective cosines), and the bound can
        # fall between two of them (on the street the facings gave 2.97
        # and 3.04 against selection levels of 0.28-0.30, the bound 10x,
        # in two runs). A start with no facing estimate pins nothing: its
        # restarts decide again.
        keep = shading_init.kept_sun_level(report.get("sun_irradiance_from", ""))
        # (Not made again here: the roughness choice makes it again only
        # where the imported roughness wins.)
        report = self._choose_roughness(report, score, best == len(trials) - 1,
                                        lambda: start(d, keep))
        if len(trials) > 1:
            report["start_candidates"] = {
                "scored_on": "validation", "chosen": best,
                "candidates": [{"sun_direction": list(map(float, dd)),
                                "sun_irradiance_from": r.get("sun_irradiance_from"),
                                "sun_irradiance": r.get("sun_irradiance"),
                                "albedo_spread": r.get("albedo_spread"),
                                "psnr": sc if np.isfinite(sc) else None}
                               for sc, dd, r in trials]}
        sun["direction"] = list(map(float, d))
        self._unclip(report)
        self.build_optimizer()
        return self._with_scorings(report)

    def _unclip(self, report):
        """Where the kept start's albedo clipped, the sun visibility that
        lets it reproduce stage 1's colour
        (:func:`~.shading_init.unclip_visibility`), and the albedo made
        again under it; kept if the start then scores at least as well on
        the validation frames (``unclipped`` in the report). Only where
        stage 2 learns the visibility (a traced one stays the trace's)."""
        st = self._start_light
        if not self.learn_sun_visibility or st is None or st.visibility is None:
            return
        k, sky0, E0, names, table, counts = st.k, st.sky0, st.sun0, st.names, st.table, st.counts
        cos = st.cos
        colour, spec, D, sun_term, bounce, indirect, t_out = st.light
        model = self.ctx.model
        albedo = np.concatenate([model.nodes[n].numpy("albedo") for n in names]).astype(np.float64)
        had = np.concatenate([model.nodes[n].numpy("sun_visibility") for n in names]).astype(np.float64)
        ambient = (D + (indirect(albedo) if indirect is not None else bounce)) * k * t_out
        per_v = E0[None, :] * cos[:, None] / np.pi * k * t_out
        v, raised, lowered = shading_init.unclip_visibility(colour - spec * k, ambient, per_v, had,
                                                            albedo, st.seen, st.lidar_albedo)
        entry = {"raised": round(raised, 4), "lowered": round(lowered, 4)}
        if raised + lowered > 0:
            before = self._start_score(report)

            def start_with(visibility):
                for name, x in zip(names, shading_init.split_by_node(visibility, table, counts)):
                    model.nodes[name].values["sun_visibility"] = jit_array(mi.Float, x)
                self._set_light_level(k, sky0, E0, (colour, spec, D, E0[None, :] * (
                    visibility * cos)[:, None] / np.pi, bounce, indirect, t_out), names, table,
                    counts)
            start_with(v)
            after = self._starting_score()
            entry.update(psnr_before=before, psnr_after=after, kept=bool(after >= before))
            if after < before:
                start_with(had)
        report["unclipped"] = entry

    def _with_scorings(self, report):
        report["scorings"] = {"count": self.start_scorings[0],
                              "seconds": round(self.start_scorings[1], 2)}
        return report

    def start_under(self, sky, direction, keep=None):
        """One start (:meth:`_init_shading`) from the sky coefficients ``sky``
        (numpy) under the sun ``direction`` (None: the scene's), its sun level
        as ``keep`` says (:func:`~.shading_init.reconcile_sun_irradiance`);
        returns its report."""
        ctx = self.ctx
        ctx.params[ctx.sky_key] = jit_array(mi.Float, sky)
        if direction is not None:
            ctx.params[ctx.sun_dir_key] = mi.Vector3f(*[float(x) for x in direction])
        ctx.params.update()
        return self._init_shading(keep=keep)

    def _choose_roughness(self, kept, score, kept_is_current, restart):
        """The start made again (``restart``) with every Gaussian's roughness
        at each of :data:`START_ROUGHNESS` and :data:`GLOSSY_START_ROUGHNESS`;
        of the imported roughness and :data:`START_ROUGHNESS`, the one whose
        start scores best on the validation frames is kept. Then a start with a
        roughness per Gaussian (:meth:`_per_gaussian_roughness`) replaces it
        where it scores at least as well. ``kept``: the report of the start
        made with the roughness they have, ``score`` its validation score;
        ``kept_is_current``: whether the scene still holds that start (it is
        made again only if it wins and the scene no longer holds it; a start
        can be made from any earlier one). Returns the kept start's report,
        with ``start_roughness``."""
        model = self.ctx.model
        key = BY_NAME["roughness"].variable
        names = list(model.nodes)
        had = {n: node.values[key] for n, node in model.nodes.items()}
        trials = [(score, None, kept)]
        current = 0 if kept_is_current else None
        # Per start, its pixel error per Gaussian (None where not measured).
        errors = [self.gaussian_errors() if kept_is_current else None]
        # (With no roughness starts at all, e.g. a test's, none are glossy.)
        glossy = tuple(GLOSSY_START_ROUGHNESS) if START_ROUGHNESS else ()
        for r in tuple(START_ROUGHNESS) + glossy:
            for node in model.nodes.values():
                node.values[key] = dr.full(mi.Float, r, node.count)
            rep = restart()
            trials.append((self._start_score(rep), r, rep))
            errors.append(self.gaussian_errors())
            current = len(trials) - 1
        # A glossy roughness is never the start for all: on the street its
        # start scored best (27.3 dB against 26.7 for 0.75) and took every
        # surface to 0.3, doubling the roughness error (0.39 against 0.19)
        # and raising the albedo error; it only competes Gaussian by Gaussian.
        rough_starts = [i for i, t in enumerate(trials) if t[1] not in glossy]
        best = max(rough_starts, key=lambda i: trials[i][0])
        best_score, r, report = trials[best]

        def per_node(i):
            rr = trials[i][1]
            return [had[n] if rr is None else dr.full(mi.Float, rr, model.nodes[n].count)
                    for n in names]
        # "kind" says which start stage 2 goes on from: the imported
        # roughness, one of START_ROUGHNESS for all ("for_all" names it;
        # None = as imported) or a roughness per Gaussian.
        entry = {"scored_on": "validation", "kind": "as_imported" if r is None else "for_all",
                 "for_all": r,
                 "candidates": [{"roughness": rr, "psnr": sc if np.isfinite(sc) else None}
                                for sc, rr, _ in trials]}
        mixed = self._per_gaussian_roughness(trials, errors, best, per_node)
        if mixed is not None:
            rough, shares = mixed
            for name, x in zip(names, rough):
                model.nodes[name].values[key] = jit_array(mi.Float, x)
            rep = restart()
            mix_score = self._start_score(rep)
            kept_mix = bool(mix_score >= best_score)
            entry["per_gaussian"] = {"psnr": mix_score if np.isfinite(mix_score) else None,
                                     "shares": shares, "kept": kept_mix}
            if kept_mix:
                entry["kind"] = "per_gaussian"
                rep["start_roughness"] = entry
                return rep
            current = None
        if best != current:
            for name, x in zip(names, per_node(best)):
                model.nodes[name].values[key] = x
            report = restart()
        report["start_roughness"] = entry
        return report

    def _per_gaussian_roughness(self, trials, errors, best, per_node):
        """Each Gaussian's start roughness from the starts ``trials`` made:
        the one whose start rendered its pixels of the training frames best
        (``errors``: per start, :meth:`gaussian_errors`' result or None),
        where it beats the validation's best start ``best`` by
        :data:`PER_GAUSSIAN_MARGIN` on at least
        :data:`PER_GAUSSIAN_MIN_PIXELS` pixels; the best start's elsewhere.
        ``per_node(i)``: start ``i``'s roughness as one array per node.
        Returns (one numpy array per node, {roughness: share of the
        Gaussians}) or None where no Gaussian changes."""
        if errors[best] is None:
            return None
        measured = [i for i, e in enumerate(errors) if e is not None]
        if len(measured) < 2:
            return None
        # (A non-finite error never wins, and never hides a finite one.)
        err = np.stack([errors[i][0] for i in measured]).astype(np.float64)
        err = np.where(np.isfinite(err), err, np.inf)
        wsum = errors[best][1]
        pick = np.argmin(err, axis=0)
        better = err[pick, np.arange(err.shape[1])] < PER_GAUSSIAN_MARGIN * errors[best][0]
        choice = np.where(better & (wsum >= PER_GAUSSIAN_MIN_PIXELS),
                          np.array(measured)[pick], best)
        if not np.any(choice != best):
            return None
        counts = [self.ctx.model.nodes[n].count for n in self.ctx.model.nodes]
        starts = {i: np.concatenate([np.array(x, np.float32) for x in per_node(i)])
                  for i in np.unique(choice)}
        rough = np.zeros(choice.shape[0], np.float32)
        for i, values in starts.items():
            rough[choice == i] = values[choice == i]
        shares = {("as imported" if trials[i][1] is None else "%.2g" % trials[i][1]):
                  round(float(np.mean(choice == i)), 4) for i in starts}
        return np.split(rough, np.cumsum(counts)[:-1]), shares

    def _start_score(self, report):
        """Validation PSNR of the start :meth:`_init_shading` just set (its
        light-level search's best, or scored now)."""
        scores = [v for v in report.get("light_scale_scores", {}).values() if v is not None]
        score = max(scores) if scores else self._starting_score()
        return score if np.isfinite(score) else -np.inf

    def _init_shading(self, keep=None):
        """One start under the scene's current sun direction (see
        :meth:`init_shading`); ``keep``: which sun level to take whatever the
        facings and the lighting selection say (one of
        :data:`~.shading_init.SUN_LEVELS`; None: their rules decide)."""
        ctx, model = self.ctx, self.ctx.model
        frame = self.frozen.first
        names = list(model.nodes)
        counts = [model.nodes[n].count for n in names]
        report = {}
        suns = [e for kind, e in point_lights(ctx.scene) if kind == "sun"] if ctx.use_sun else []
        with dr.suspend_grad():
            model.push(frame.poses, stage=2)
            if suns:
                # Traced v (also the learned v_sun's start), through the scene's
                # own copy of the frozen Gaussians.
                scene_nodes = {n.shape.id(): n for n in hitlib.gaussian_nodes(ctx.scene)}
                ordered = [scene_nodes[n] for n in names]
                table = GaussianTable.build(ordered).load_geometry()
                d, _, _ = light_at("sun", suns[0], table.center)
                # From above the surface, as the sun selection and the
                # integrator trace (lighting.SHADOW_OFFSET).
                origin = shadow_origins(table, d)
                if self.moving_shadows:
                    # The field's start is the static scene's shadow: the
                    # moving objects cast theirs per frame on top.
                    vis, _ = split_transmittance(ctx.scene, origin, d, mi.Float(dr.inf), ordered,
                                                 self.frozen.moving_ids)
                else:
                    vis = transmittance(ctx.scene, origin, d, mi.Float(dr.inf), ordered)
                vis = np.clip(np.array(vis), 0.0, 1.0)
                for name, v in zip(names, shading_init.split_by_node(vis, table, counts)):
                    model.nodes[name].values["sun_visibility"] = jit_array(mi.Float, v)
                sun_dir = np.array(d, np.float64).T
            nodes = self.frozen.nodes(frame, self.model_values())
            lighting = self.lighting(nodes, self.frozen.caches[frame.index], frame=frame)
            table = lighting.table
            D = shading_init.as_rows(lighting.diffuse_sky)
            colour = np.concatenate([model.nodes[n].numpy("colour") for n in names])
            # Bounce light at the start: stage 1's colours are the radiance
            # the Gaussians send out, so W c is what they pass on (it does
            # not scale with the light level chosen below).
            bounce = (shading_init.as_rows(lighting.pass_on(mi.Color3f(colour.T.astype(np.float32)),
                                                             through_coat=False))
                      if lighting.bounces > 0 else np.zeros_like(D))
            sun_term = np.zeros_like(D)
            seen_w = shading_init.seen_weight(
                table, [(self.frozen.camera[f.index], f.camera.valid())
                        for f in ctx.train_frames if f.index in self.frozen.camera])
            seen = seen_w > 0.05
            fresnel = bool(ctx.config.diffuse_fresnel)
            if suns:
                normals = np.array(table.normal, np.float64).T
                cos = np.maximum(np.sum(normals * sun_dir, axis=1), 0.0)
                if fresnel:
                    # The render's sun term carries the coat's transmission
                    # on the way in: an effective cosine keeps the sunlit /
                    # shadowed ratios below in step with it.
                    rough = hitlib.gather_attribute(nodes, "roughness", table.ids, table.prims,
                                                    mi.Bool(True))
                    cos = cos * np.array(coat.transmission(
                        jit_array(mi.Float, cos), rough, ctx.camera_integrator.f0), np.float64)
                rho = np.concatenate([model.nodes[n].numpy("lidar_albedo") for n in names]) \
                    if any(f.lidar is not None for f in ctx.train_frames) else None
                # Shadowed Gaussians are lit by the sky and by what their
                # sunlit neighbours pass on: leaving the bounce out of the
                # lit/shadow ratio credits the bounce to the sky and
                # underestimates the sun (street, fixed-iteration fits: 0.4-3.1
                # in luminance with the sky term alone, 3.1-3.4 with the
                # bounce, truth 3.9).
                ambient = D + bounce
                E, groups = shading_init.estimate_sun_irradiance(colour, ambient, vis, cos, normals,
                                                                  seen, rho)
                # The lighting selection's level: its sun/sky ratio times the sky term.
                level = (np.pi * ctx.selection.get("sun", {}).get("sun_to_sky", 1.0)
                         * float(np.median(D[seen] @ LUMINANCE)) if seen.any() else 1.0)
                E, source = shading_init.reconcile_sun_irradiance(E, level, keep)
                if self.learn_sun_visibility and rho is not None and ctx.config.weights.lidar2rgb > 0:
                    # L_lidar->rgb's premise at the start: where the colour is
                    # much darker than the LiDAR albedo predicts, the sun is
                    # blocked; where much brighter, it is not. Corrections
                    # also clean the groups the irradiance is estimated
                    # from, so the two alternate until the irradiance settles.
                    E, vis, source, lowered, raised = shading_init.settle_sun_and_visibility(
                        colour, ambient, E, source, vis, cos, normals, seen, rho, level, keep)
                    report["lidar_albedo_shadowed"] = lowered
                    report["lidar_albedo_unshadowed"] = raised
                    for name, v in zip(names, shading_init.split_by_node(vis, table, counts)):
                        model.nodes[name].values["sun_visibility"] = jit_array(mi.Float, v)
                ctx.params[ctx.sun_key] = mi.Color3f(*[float(x) for x in E])
                ctx.params.update()
                sun_term = E[None, :] * (vis * cos)[:, None] / np.pi
                report.update(sun_irradiance=E.tolist(), sun_irradiance_from=source,
                              facings=int(groups),
                              shadowed=float(np.mean(vis[seen] < 0.5)) if seen.any() else 0.0)
            # The specular light each Gaussian sends the training cameras
            # (scales with the light level k like the sky and sun terms):
            # stage 1's colour is diffuse plus specular, and an albedo that
            # reproduced the whole colour as diffuse light started the
            # KITTI excerpt 0.8 dB below stage 1, 70 % of the pixels too bright.
            # The lobe sees the Gaussians blocking its sky samples as stage 1
            # coloured them (their albedo is what this start solves for).
            spec, t_out = self.seen_by_cameras(names, transmission=fresnel, blockers=colour)
            report["specular_share"] = (float(np.sum((spec[seen] @ LUMINANCE)) / max(
                float(np.sum(colour[seen] @ LUMINANCE)), 1e-12)) if seen.any() else 0.0)
            # Where the fitted light is too dark for the colours stage 1
            # fitted, the albedo would clip at 1 and stage 2 would start far
            # below stage 1 (KITTI under a bridge: sky term dark, 92 % of the
            # albedo channels clipped, 16 -> 8 dB). Raising sky and sun
            # together cures that but also brightens the sky seen directly,
            # which costs PSNR where that sky is not saturated white. So the
            # level is a choice: no raise, the full raise and three steps
            # between (geometric), each scored on the validation frames.
            k_max = shading_init.light_scale(colour - spec, (D + sun_term + bounce) * t_out, seen)

            def indirect(albedo):
                # The render's bounce light at level 1 for ``albedo``: what the
                # albedo reflects of the direct light, passed on ``bounces`` times.
                ind = np.zeros_like(D)
                for _ in range(lighting.bounces):
                    leaving = (albedo * (D + sun_term + ind)).T.astype(np.float32)
                    ind = shading_init.as_rows(lighting.pass_on(mi.Color3f(leaving)))
                return ind
            light = (colour, spec, D, sun_term, bounce, indirect if lighting.bounces > 0 else None,
                     t_out)
            sky0, E0 = dr.detach(ctx.params[ctx.sky_key]), E if suns else None
            levels = [1.0] if k_max <= 1.0 else [float(k_max ** q) for q in (0, 0.25, 0.5, 0.75, 1)]
            scores = {}
            if len(levels) == 1:
                k = levels[0]
                self._set_light_level(k, sky0, E0, light, names, table, counts)
            else:
                def score_at(level):
                    self._set_light_level(level, sky0, E0, light, names, table, counts)
                    return self._starting_score()
                k, scores, last = shading_init.search_levels(levels, score_at)
                if k != last:
                    self._set_light_level(k, sky0, E0, light, names, table, counts)
            if suns:
                report["sun_irradiance"] = (E0 * k).tolist()
                if rho is not None:
                    albedo = np.concatenate([model.nodes[n].numpy("albedo") for n in names])
                    report["albedo_spread"] = shading_init.albedo_spread(
                        albedo, rho, np.array(table.center, np.float64).T,
                        np.where(seen, seen_w, 0.0))
            report["light_scale"] = float(k)
            # What :meth:`_unclip` needs of the start the scene now holds.
            self._start_light = StartLight(light, k, sky0, E0, names, table, counts)
            if suns:
                self._start_light.visibility, self._start_light.cos = vis, cos
                self._start_light.lidar_albedo, self._start_light.seen = rho, seen
            if scores:
                report["light_scale_scores"] = {"%.3g" % v: sc if np.isfinite(sc) else None
                                                for v, sc in scores.items()}
        return report

    def _set_light_level(self, k, sky0, E0, light, names, table, counts):
        """Sky and sun at ``k`` times their fitted level and the albedo that
        reproduces the stage-1 colours under them.

        ``light``: per Gaussian at level 1, (stage-1 colour, specular light,
        sky term, sun term, the bounce stage 1's colours pass on, the
        render's bounce for an albedo or None without bounces). The albedo
        starts at (colour - k spec) / (k (sky + sun) + bounce), then
        :data:`BOUNCE_ROUNDS` fixed-point rounds replace the bounce by the
        render's: the render passes on what the albedo reflects of the
        direct light (one bounce: ``W (a * direct)``), not stage 1's whole
        colour ``W c``. On the fit tests' street, without the rounds, the
        start rendered its pixels 0.054 darker than stage 1's colours."""
        colour, spec, D, sun_term, bounce, indirect, t_out = light
        ctx, model = self.ctx, self.ctx.model
        ctx.params[ctx.sky_key] = sky0 * k
        if E0 is not None:
            ctx.params[ctx.sun_key] = mi.Color3f(*[float(x) for x in E0 * k])
        ctx.params.update()
        # ``t_out``: the diffuse light's way out through the coat, per
        # Gaussian as the training cameras see it (1 without diffuse_fresnel).
        albedo = shading_init.albedo_from_shading(colour - spec * k, (D * k + bounce) * t_out,
                                                  sun_term * k * t_out)
        for _ in range(BOUNCE_ROUNDS if indirect is not None else 0):
            albedo = shading_init.albedo_from_shading(colour - spec * k,
                                                      (D + indirect(albedo)) * k * t_out,
                                                      sun_term * k * t_out)
        for name, a in zip(names, shading_init.split_by_node(albedo, table, counts)):
            model.nodes[name].values["albedo"] = jit_array(mi.Float, a)
        self.build_optimizer()

    def seen_by_cameras(self, names, frames=8, transmission=False, blockers=None):
        """What the training cameras see of each Gaussian, averaged over their
        views: per Gaussian (rows in ``names``' order), the specular radiance it
        sends to the training cameras under the scene's current light,
        averaged with its blend weights over up to ``frames`` training frames
        spread over the sequence; 0 for Gaussians those frames do not see.
        Returns it with, per Gaussian (a column), the mean coat factor of
        its diffuse light towards those cameras
        (:func:`~mi_invrgbl.physics.coat.way_out`) with ``transmission``
        (``diffuse_fresnel``), else ones.

        The specular part of the shading does not depend on the receiver's
        albedo, so it is rendered once with the albedo at zero (no diffuse,
        no bounce). ``blockers`` (per Gaussian, that order: radiance out of
        its coat, e.g. stage 1's colours), with bounces, is what the lobe
        sees of the Gaussians that block its sky samples (a window mirrors
        the facade across the street); without it they are black to it."""
        ctx = self.ctx
        vals = self.model_values()
        for n in names:
            key = "%s.%s" % (n, BY_NAME["albedo"].variable)
            vals[key] = dr.zeros(mi.Float, dr.width(vals[key]))
        acc, wsum, tsum = None, None, None
        with dr.suspend_grad():
            for f, fh, nodes, lighting, gi, w in self._training_hits(frames, vals):
                if blockers is not None and lighting.bounces > 0:
                    lighting.reflect_blockers(mi.Color3f(blockers.T.astype(np.float32)),
                                              through_coat=False)
                g = frozen_gaussian_hits(nodes, f.camera.rays, fh)
                colour, _, n, tau, _ = ctx.camera_integrator.shade_gaussian_hits(
                    lighting, nodes, f.camera.rays, fh, g)
                c = np.array(colour, np.float64).T
                if acc is None:
                    acc = np.zeros((lighting.table.total, 3))
                    wsum = np.zeros(lighting.table.total)
                    tsum = np.zeros(lighting.table.total)
                wsum += np.bincount(gi, w, minlength=wsum.shape[0])
                for k in range(3):
                    acc[:, k] += np.bincount(gi, w * c[:, k], minlength=acc.shape[0])
                if transmission:
                    _, d = hitlib.expand_rays(f.camera.rays, fh)
                    t = np.array(coat.way_out(dr.dot(n, d), tau, lighting.f0), np.float64)
                    tsum += np.bincount(gi, w * t, minlength=tsum.shape[0])
        if acc is None:
            count = sum(ctx.model.nodes[n].count for n in names)
            return np.zeros((count, 3)), np.ones((count, 1))
        seen = wsum > 1e-6
        spec = np.where(seen[:, None], acc / np.maximum(wsum, 1e-6)[:, None], 0.0)
        t_out = np.where(seen, tsum / np.maximum(wsum, 1e-6), 1.0) if transmission else \
            np.ones_like(wsum)
        return spec, t_out[:, None]

    def _training_hits(self, frames, vals):
        """For up to ``frames`` training frames with a frozen camera, spread
        over the sequence, with the model values ``vals``:
        yields (frame, its frozen hits, nodes, lighting, each hit's Gaussian
        in the lighting table's order, each hit's blend weight with the
        pixels the camera does not observe at 0). What the per-Gaussian
        averages over the training views (:meth:`seen_by_cameras`,
        :meth:`gaussian_errors`) share; callers iterate it under
        ``dr.suspend_grad()``."""
        train = [f for f in self.ctx.train_frames if f.index in self.frozen.camera]
        if not train:
            return
        pick = np.unique(np.linspace(0, len(train) - 1, min(frames, len(train))).round().astype(int))
        for i in pick:
            f = train[i]
            fh = self.frozen.camera[f.index]
            nodes = self.frozen.nodes(f, vals)
            lighting = self.lighting(nodes, self.frozen.cache(f), frame=f)
            gi = np.array(lighting.table.global_index(fh.node_ids, fh.prims))
            w = np.where(f.camera.valid()[np.array(fh.ray)], np.array(fh.weight, np.float64), 0.0)
            yield f, fh, nodes, lighting, gi, w

    def gaussian_errors(self, frames=8):
        """Per Gaussian (the lighting table's order, ``model.nodes``'), the
        squared sRGB error of the pixels it shows in up to ``frames``
        training frames under the current start, averaged with its blend
        weights, and the sum of those weights (pixels). Gaussians no frame
        sees have error 0 and weight 0; None without training frames."""
        ctx = self.ctx
        err, wsum = None, None
        with dr.suspend_grad():
            for f, fh, nodes, lighting, gi, w in self._training_hits(frames, self.model_values()):
                out = camera_shaded(ctx.camera_integrator, ctx.scene, lighting, nodes,
                                    f.camera.rays, fh)
                rgb = np.stack([np.array(out["rgb"][k], np.float64) for k in range(3)], axis=1)
                target = f.camera.image.reshape(-1, 3).astype(np.float64)
                e = np.sum((linear_to_srgb(np.clip(rgb, 0.0, 1.0))
                            - linear_to_srgb(np.clip(target, 0.0, 1.0))) ** 2, axis=1)
                e = np.where(np.isfinite(e), e, 0.0)
                if err is None:
                    err = np.zeros(lighting.table.total)
                    wsum = np.zeros(lighting.table.total)
                err += np.bincount(gi, w * e[np.array(fh.ray)], minlength=err.shape[0])
                wsum += np.bincount(gi, w, minlength=wsum.shape[0])
        if err is None:
            return None
        return np.where(wsum > 1e-6, err / np.maximum(wsum, 1e-6), 0.0), wsum

    def _starting_score(self):
        """PSNR of the current starting point on up to three of the frames
        that score model choices (:attr:`FitState.selection_frames`)."""
        from .evaluate import score_stage2
        t = time.perf_counter()
        frames = [f for f in self.ctx.selection_frames if f.camera is not None][:3]
        psnr, _ = score_stage2(self, frames)
        # What the start's choices cost (metrics.json shading_init.scorings).
        self.start_scorings[0] += 1
        self.start_scorings[1] += time.perf_counter() - t
        return psnr

    def lighting(self, nodes, cache, samples=None, pattern=0, frame=None):
        """The Gaussians' incident light as the fit shades them (its M,
        bounces and sun visibility), from ``cache``. A cache that is empty or
        out of date (a moved sun) is traced now, with the objects placed for
        ``frame`` (:meth:`FrozenScene.place`)."""
        cfg = self.ctx.config
        place = None if frame is None else (lambda: self.frozen.place(frame))
        extra = None
        if self.moving_shadows and frame is not None:
            extra = [self.frozen.moving_shadow(frame, dr.detach(e.sun_direction_world()))
                     if kind == "sun" else None for kind, e in point_lights(self.ctx.scene)]
        return GaussianLighting(self.ctx.scene, nodes, samples or cfg.samples, cache,
                                trace_sun=not self.learn_sun_visibility, bounces=cfg.bounces,
                                pattern=pattern, before_trace=place,
                                diffuse_fresnel=bool(cfg.diffuse_fresnel),
                                f0=self.ctx.camera_integrator.f0, light_transmittance=extra)

    def refresh_lighting(self, vals=None):
        """Re-trace the sky visibility of the Gaussians whose normal turned
        since it was traced (:func:`~mi_invrgbl.physics.lighting.retrace_turned`),
        in every traced cache; returns how many Gaussians were traced again.

        Stage 2 learns the normals while the visibility of each Gaussian's M
        sky directions stays cached, and the directions turn with the
        normal: without this the albedo is fitted to visibility the fitted
        scene never renders (KITTI, 30 minutes: the scene rendered 0.1 dB
        below the fit's own images of a training frame, pixels off by up to
        15 %). Called before the scores that choose (validation), so that
        what the fit keeps is what the integrator renders, and once at the
        stage's end."""
        if not self.lighting_stale or self.ctx.config.weights.rgb <= 0:
            return 0
        t = time.perf_counter()
        ctx, frozen = self.ctx, self.frozen
        vals = self.values() if vals is None else vals
        seen, count = set(), 0
        with dr.suspend_grad():
            for index in frozen.camera:
                frame = next((f for f in ctx.observations if f.index == index), None)
                if frame is None:
                    continue
                nodes = None
                for p in range(max(1, ctx.config.sky_patterns)):
                    cache = frozen.caches[index] if p == 0 else \
                        frozen.pattern_caches.get((id(frozen.caches[index]), p))
                    if cache is None or id(cache) in seen or not cache.key:
                        continue
                    seen.add(id(cache))
                    nodes = nodes or frozen.nodes(frame, vals)
                    frozen.place(frame)
                    count += retrace_turned(ctx.scene, nodes, cache, ctx.config.samples, p,
                                            ctx.config.bounces, RETRACE_TURN_DEG)
        self.lighting_stale = False
        self.retraced["refreshes"] += 1
        self.retraced["gaussians"] += count
        self.retraced["seconds"] += time.perf_counter() - t
        return count

    def trace_patterns(self):
        """Fill the lighting cache of every sky pattern (one per distinct
        cache: once for a static scene, per frame with per-frame visibility),
        and the moving objects' shadows of every training frame."""
        ctx = self.ctx
        if ctx.config.weights.rgb <= 0:
            return
        vals = self.values()
        seen = set()
        with dr.suspend_grad():
            for frame in ctx.train_frames:
                if frame.index not in self.frozen.camera or id(self.frozen.caches[frame.index]) in seen:
                    continue
                seen.add(id(self.frozen.caches[frame.index]))
                nodes = self.frozen.nodes(frame, vals)
                for p in range(max(1, ctx.config.sky_patterns)):
                    dr.eval(self.lighting(nodes, self.frozen.cache(frame, p), pattern=p,
                                          frame=frame).diffuse)
            if self.moving_shadows:
                # Every training frame's moving shadows too: traced on first
                # use, they made the first stage-2 steps, which a budget times,
                # look slow (KITTI, 30 minutes: 1.25 s per step planned where
                # the steps took 0.66 s, and stage 2 ran 356 steps in 236 s of
                # its 442 s share).
                d = [dr.detach(e.sun_direction_world()) for kind, e in point_lights(ctx.scene)
                     if kind == "sun"]
                for frame in ctx.train_frames:
                    if frame.index in self.frozen.camera and d:
                        self.frozen.moving_shadow(frame, d[0])
                self.frozen.place(self.frozen.first)

    # ---------------------------------------------------------- render
    def render_frame(self, frame, vals, camera=True, lidar=True, samples=None, caches=None,
                     pattern=0):
        """Camera and LiDAR channels of ``frame`` from the frozen caches.

        ``samples`` (default: the config's M) and ``caches`` (frame index ->
        :class:`LightingCache`, default: the frozen scene's) let a caller
        score another sky sample count without touching the fit's own.
        ``pattern``: which turn of the sky directions lights the Gaussians
        (training cycles through ``config.sky_patterns``; scores and outputs
        use pattern 0, the one the fitted scene renders with)."""
        ctx = self.ctx
        nodes = self.frozen.nodes(frame, vals)
        out = {}
        if camera and frame.index in self.frozen.camera and ctx.config.weights.rgb > 0:
            cache = caches[frame.index] if caches else self.frozen.cache(frame, pattern)
            lighting = self.lighting(nodes, cache, samples, pattern, frame=frame)
            out["camera"] = camera_shaded(ctx.camera_integrator, ctx.scene, lighting, nodes,
                                          frame.camera.rays, self.frozen.camera[frame.index])
        if lidar and frame.index in self.frozen.lidar:
            out["lidar"] = lidar_shaded(nodes, frame.lidar.rays, frame.lidar.row, frame.lidar.near,
                                        self.frozen.lidar[frame.index], self.response(vals),
                                        self.model_kind)
        return out

    def superpixels(self, frame, out):
        """SLIC labels of the frame's rendered LiDAR-albedo map (recomputed on demand)."""
        cam = frame.camera
        rho = np.array(dr.detach(out["camera"]["lidar_albedo"]), np.float32).reshape(cam.height, cam.width)
        labels, n = slic_labels(rho, region_size=self.ctx.config.slic_size)
        self.labels[frame.index] = (jit_array(mi.UInt32, labels), int(n))

    def loss_terms(self, frame, out, weights):
        ctx = self.ctx
        terms = {}
        if "camera" in out:
            c = out["camera"]
            cam = frame.camera
            target = ctx.image_array(frame)
            # Masked pixels (moving things no node models) weigh 0 in every term.
            terms["rgb"] = losses.rgb_loss(c["rgb"], target, cam.valid_mask(), space=ctx.config.rgb_space,
                                           norm=ctx.config.rgb_norm)
            mask = cam.restrict(c["alpha"] > 0.5)
            if weights.rgb2lidar > 0:
                terms["rgb2lidar"] = losses.bilateral_smoothness(
                    c["lidar_albedo"], c["albedo"], cam.height, cam.width,
                    ctx.config.bilateral_sigma, mask)
            if weights.lidar2rgb > 0:
                if frame.index not in self.labels:
                    self.superpixels(frame, out)
                labels, n = self.labels[frame.index]
                terms["lidar2rgb"] = losses.superpixel_variance(c["albedo"], labels, n, mask)
            if weights.nor > 0 and "normal" in cam.priors:
                terms["nor"] = losses.prior_loss(c["normal"], ctx.prior_array(frame, "normal"), mask)
            if weights.mat > 0:
                mat = []
                if "albedo" in cam.priors:
                    mat.append(losses.prior_loss(c["albedo"], ctx.prior_array(frame, "albedo"), mask))
                if "roughness" in cam.priors:
                    mat.append(losses.prior_loss(c["roughness"], ctx.prior_array(frame, "roughness"), mask))
                if mat:
                    terms["mat"] = sum(mat[1:], mat[0])
        if "lidar" in out:
            lid = frame.lidar
            obs = jit_array(mi.Float, lid.intensity)
            hit = jit_array(mi.Bool, lid.hit)
            # Normalised to the observed scale: raw return power can be ~1e-3,
            # which would make L_lidar vanish next to L_rgb at the paper's weights.
            inv = 1.0 / ctx.intensity_scale
            terms["lidar"] = losses.lidar_loss(out["lidar"]["intensity"] * inv, obs * inv,
                                               lid.restrict(hit & (out["lidar"]["alpha"] > 0.5)))
        return terms

    def anchor_term(self, vals):
        """L_anchor over every node's Gaussians (count-weighted mean)."""
        total, count = mi.Float(0.0), 0
        for name, start in self.normal_start.items():
            g = dr.width(start) // 3
            if g == 0:
                continue
            n = vals["%s.%s" % (name, BY_NAME["normal"].variable)]
            total += losses.normal_anchor(n, start) * float(g)
            count += g
        return total / float(count) if count else mi.Float(0.0)

    def iteration(self, it, weights=None):
        ctx = self.ctx
        weights = weights or ctx.config.weights
        frame = ctx.train_frames[self.rng.integers(0, len(ctx.train_frames))]
        vals = self.values()
        # A different turn of every Gaussian's sky directions each step: the
        # albedo then fits the sky integral, not the error of one fixed set of
        # M directions (with one set, the fitted street scored 0.8-1.3 dB
        # lower when rendered with 32 directions than with the 16 it was fitted with).
        pattern = it % max(1, ctx.config.sky_patterns)
        out = self.render_frame(frame, vals, camera=weights.rgb > 0, lidar=weights.lidar > 0,
                                pattern=pattern)
        terms = self.loss_terms(frame, out, weights)
        if weights.anchor > 0:
            terms["anchor"] = self.anchor_term(vals)
        total = weights.combine(terms)
        ok = safe_step(self.opt.adam, total, ctx.log, ctx.lr_state, "stage-2 iteration %d" % it)
        if ok:
            self.opt.clamp()
            self.lighting_stale = True
        return float(total[0]), {k: float(v[0]) for k, v in terms.items()}, ok
