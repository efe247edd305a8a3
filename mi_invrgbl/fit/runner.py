"""``fit``: the two-stage optimisation end to end, as the paper's recipe.

:func:`run_fit` reads top to bottom as the method:

1. load the imported scene, ``frames.json`` and the observations
   (:mod:`.init`); every fifth training frame is kept for validation;
2. stage 1, geometry and a view-independent colour with densification
   (:mod:`.stage1`), then removal of sky look-alikes;
3. lighting: sun and SH order from stage-1 results (:mod:`.model_selection`);
4. freeze geometry: trace every frame once, cache visibility (:mod:`.stage2`);
5. LiDAR response and LiDAR albedo from a log-linear regression (:mod:`.init`),
   albedo and sun irradiance from the stage-1 colours;
6. stage 2, materials, light and response (:mod:`.stage2`);
7. the LiDAR lobe (``pbr`` vs ``lambertian``) and the sky sample count M
   for rendering, both scored on the validation frames;
8. outputs (:mod:`.outputs`).

With a time budget (``--budget``, :mod:`.budget`) each stage's iterations
follow from its share of the budget and its measured speed, and a stage
stops early once its validation score stops improving.

Both stages run in :func:`.loop.train`. A checkpoint
(``DIR/fit/checkpoints/latest.npz``, :mod:`.checkpoint`) is written every
``checkpoint_every`` iterations, at the end of each stage and on Ctrl-C;
``--resume`` continues from it if it is of the same scene and model options.
"""

from __future__ import annotations

import os
import time

import numpy as np
import drjit as dr
import mitsuba as mi

from . import outputs
from ..physics.host_arrays import jit_array
from ..physics.directions import angle_deg
from .budget import (OUTPUT_RESERVE, TIMED, Budget, EarlyStop, Replan,
                     overrun_report, plan_stage, position_lr_factor, probe_batch_scale,
                     PLATEAU_LR_FACTOR, PLATEAU_REDUCTIONS, VALIDATION_SHARE, anneal_lr_factor,
                     small_budget_warning, stage1_seconds, stage_progress, time_iterations,
                     STAGE1_MAX_STEPS, STAGE2_EVAL_INTERVAL, MIN_STAGE2_STEPS,
                     fixed_costs, resumed_plan, resumed_progress, stage2_seconds)
from .checkpoint import checkpoint_path, fingerprint, load_checkpoint, save_checkpoint
from .config import FitConfig  # noqa: F401  (the fit's options, imported from here by callers)
from .evaluate import score_stage2
from .init import init_materials, init_sky_from_mask, load_state, sh_mask
from .loop import LOG_SHARE, Interrupted, LogCadence, StageRun, record_point, train
from .model_selection import (SUN_TRIAL_MARGIN, LightingChoice, LobeChoice, choose_lidar_lobe,
                              choose_lighting, choose_render_samples, choose_sky_start, log_lighting,
                              sun_alternative)
from .progress import SpeedErrorLog
from .stage1 import Stage1, moves_with_positions
from .stage2 import RETRACE_TURN_DEG, FrozenScene, Stage2
from .state import FitState
from .steps import restore_optimizer


def run_fit(scene_path, config: FitConfig, log=print):
    """Fit ``scene_path`` (an imported scene); returns the metrics dict."""
    t_start = time.perf_counter()
    state = load_state(scene_path, config, log)
    state.t_start = t_start
    os.makedirs(state.fit_dir, exist_ok=True)
    state.speed_log = SpeedErrorLog(os.path.join(state.fit_dir, "log.csv"))
    fp = fingerprint(state)
    budget = Budget(config.budget_minutes, t_start) if config.budget_minutes > 0 else None

    def checkpoint(stage, it, opt=None):
        save_checkpoint(state, fp, stage, it, opt)

    stage, start, opt_state = "stage 1", 0, None
    if config.resume:
        meta, opt_state = load_checkpoint(state, fp)
        stage, start = meta["stage"], int(meta["iteration"])
        state.wall_offset = float(meta.get("wall_s", 0.0))
        log("[fit] resuming from %s, %s iteration %d" % (checkpoint_path(state), stage, start))
    if budget is not None and config.resume:
        # A resumed fit's budget is the whole fit's: the runs before took
        # ``wall_offset`` of it.
        budget = Budget(config.budget_minutes, t_start - state.wall_offset)
    stage2, lighting = None, None
    try:
        if stage == "stage 1":
            fit_geometry(state, start, opt_state, checkpoint, budget)
            start, opt_state = 0, None
            t = time.perf_counter()
            lighting = choose_sky_start(state, choose_lighting(state))
            apply_lighting(state, lighting)
            state.times["selection"] = time.perf_counter() - t
            log_lighting(state, lighting, state.times["selection"])
            checkpoint("stage 2", 0)
        stage2, frozen = freeze(state, initialise=start == 0)
        if opt_state:
            restore_optimizer(stage2.opt.adam, opt_state)
        fresh, alternative = start == 0, None
        if fresh and lighting is not None:
            # (A fit resumed from stage 2's first checkpoint keeps the test's
            # decision: the trial needs the lighting choice of this run.)
            alternative = sun_alternative(state, lighting)
        started = state.selection.get("shading_init", {}).get("seconds", 0.0)
        if alternative is not None and budget is not None and not budget.sun_trial_fits(started):
            state.log("[fit] sun trial skipped: stage 2 has %.0f s of its %.0f s share left, too "
                      "little for the trial's steps and its start (about what the first start "
                      "took, %.0f s); the sun test's decision stands"
                      % (budget.stage2_left(), budget.share("stage 2"), started))
            state.selection["sun"]["trial"] = {"skipped": True,
                                               "stage2_seconds_left": round(budget.stage2_left(), 1)}
            alternative = None
        if alternative is not None:
            # Without a budget the trial's iterations are part of the stage's
            # count, so it never runs more than the stage would.
            start = config.sun_trial_iterations if budget is not None else \
                min(config.sun_trial_iterations, config.stage2_iterations)
            limit = None if budget is None else budget.sun_trial_limit()
            try:
                stage2, start = sun_trial(state, frozen, stage2, lighting, alternative, start, limit)
            except KeyboardInterrupt:
                # Ctrl-C during the trial: stage 2's start is checkpointed
                # already (``--resume`` starts stage 2 from it, keeping the
                # lighting test's decision); write the outputs so far.
                state.log("\n[fit] interrupted during the sun trial: writing the outputs so far; "
                          "--resume starts stage 2 afresh from its checkpoint")
                raise Interrupted() from None
        last = fit_materials(state, stage2, start, checkpoint, budget, fresh=fresh)
        stage2.commit()
        report_sun_refinement(state)
        t = time.perf_counter()
        lobe = choose_lidar_lobe(state, stage2, frozen)
        apply_lidar_lobe(state, lobe)
        state.times["lobe selection"] = time.perf_counter() - t
        t = time.perf_counter()
        state.selection["samples"] = choose_render_samples(
            state, stage2, frozen,
            deadline=None if budget is None else budget.deadline - OUTPUT_RESERVE * 60 * budget.minutes)
        state.times["samples selection"] = time.perf_counter() - t
        log_choices(state)
        checkpoint("done", last)
        interrupted = False
    except Interrupted:
        interrupted = True
    t = time.perf_counter()
    metrics = outputs.write_outputs(state, stage2, interrupted=interrupted)
    state.times["outputs"] = time.perf_counter() - t
    if budget is not None and not interrupted:
        note = overrun_report(budget.minutes, time.perf_counter() - t_start, state.times)
        if note:
            log(note)
    return metrics


def fit_geometry(state: FitState, start, opt_state, checkpoint, budget=None):
    """Stage 1 from iteration ``start``, then the removal of sky look-alikes."""
    config = state.config
    if start == 0:
        init_sky_from_mask(state)
    s1 = Stage1(state)
    if opt_state:
        restore_optimizer(s1.opt.adam, opt_state)
    total = planned(state, "stage 1", config.stage1_iterations)
    run = StageRun("stage 1", s1.iteration,
                   lambda: (s1.score(state.held_out_frames), float("nan")),
                   lambda name, it: checkpoint(name, it, s1.opt.adam), s1.after_step)
    if budget is not None and start == 0:
        record_point(state, run, 0)   # before the timed iterations move it
        t = time.perf_counter()
        start = 1 + TIMED
        spi = time_iterations(s1.iteration, 1)
        base_camera, base_lidar = s1.batch_camera, s1.batch_lidar

        def set_scale(k):
            s1.batch_camera, s1.batch_lidar = base_camera * k, base_lidar * k
        share = stage1_seconds(budget.minutes, t - state.t_start, len(state.observations), spi)
        if share < budget.share("stage 1"):
            state.log("[fit] budget: stage 1 gets %.0f of its %.0f s, so that stage 2 keeps time "
                      "after the steps between the stages (about %.0f s here)"
                      % (share, budget.share("stage 1"),
                         fixed_costs(len(state.observations), spi)))
        probe = probe_batch_scale(s1.iteration, set_scale, start, share, spi)
        start += probe.iterations_run
        # Past MAX_ITERATIONS the batch grows only where the probe found
        # larger batches cheap (a GPU); on a CPU more steps of the
        # configured batch learn faster than fewer, larger ones.
        plan = plan_stage("stage 1", share - (time.perf_counter() - t),
                          probe.seconds_per_iteration, done=start, batched=probe.scale > 1,
                          most=STAGE1_MAX_STEPS)
        if plan.uncapped is not None:
            state.log("[fit] budget: stage 1 takes %d steps, not the %d its share holds (longer "
                      "schedules fitted worse; STAGE1_MAX_STEPS); stage 2 gets the time left"
                      % (plan.iterations, plan.uncapped))
        set_scale(probe.scale * plan.batch_scale)
        plan.batch_scale *= probe.scale
        state.log("[fit] budget: stage 1 batch %d camera rays + %d LiDAR beams (%s s per step "
                  "at %s times the configured batch)"
                  % (s1.batch_camera, s1.batch_lidar, "/".join("%.3f" % v for v in probe.timings.values()),
                     "/".join(str(k) for k in probe.timings)))
        state.selection.setdefault("budget", {})["stage 1"] = dict(
            plan.as_dict(), probe={str(k): round(v, 4) for k, v in probe.timings.items()})
        warning = small_budget_warning(budget.minutes, t - state.t_start, share,
                                       len(state.observations), spi)
        if warning:
            state.log(warning)
        total = plan.iterations
        started = t     # (``t`` is reused below, after the stage)
        run.stop = stage1_stop(state, s1, plan, started + share)
        run.after_step = stage1_schedule(state, s1, lambda it, total: stage_progress(
            it, total, time.perf_counter() - started, share))
        run.replan = replanner(state, plan, start, started + share, most=STAGE1_MAX_STEPS)
        run.log_share = LOG_SHARE
    elif budget is not None and "stage 1" in state.selection.get("budget", {}):
        # A resumed budgeted stage keeps the batch and iterations its plan
        # chose and goes on as planned: its schedules from where they stood
        # at the checkpoint, the validation stop, the log's cadence.
        record = state.selection["budget"]["stage 1"]
        k = int(record.get("batch_scale", 1))
        s1.batch_camera *= k
        s1.batch_lidar *= k
        plan = resumed_plan("stage 1", record, start, total)
        then = float(record.get("progress", start / max(total, 1)))
        run.stop = stage1_stop(state, s1, plan, time.perf_counter() + plan.seconds)
        run.after_step = stage1_schedule(state, s1, lambda it, total: resumed_progress(
            then, start, it, total))
        run.log_share = LOG_SHARE
        state.log("[fit] budget: stage 1 resumed at iteration %d of %d (schedules at %.0f %% "
                  "of the stage)" % (start, total, 100 * then))
    if total > start:
        last = train(state, run, start, total)
        keep_best(state, run, s1.restore, last)
    if config.prune_sky_lookalikes:
        t = time.perf_counter()
        removed, above = s1.prune_sky_lookalikes()
        state.selection["sky_lookalikes"] = {"removed": removed, "unseen_above": above,
                                             "seconds": time.perf_counter() - t}
        state.times["sky look-alikes"] = state.selection["sky_lookalikes"]["seconds"]
        state.log("[fit] sky look-alikes: %s removed (sky-coloured Gaussians with only sky "
                  "behind them), and %s unseen above them in their columns; %.1f s"
                  % (", ".join("%s %d" % kv for kv in removed.items()) or "none",
                     ", ".join("%s %d" % kv for kv in above.items()) or "none",
                     time.perf_counter() - t))
    s1.pull()
    state.model.push(state.train_frames[0].poses, stage=1)


def stage1_stop(state: FitState, s1, plan, deadline):
    """A budgeted stage 1's :class:`ValidationStop` (its deadline, early
    stop on the validation frames, plateaus, the best state kept)."""
    def resume_from(snapshot, damping):
        s1.restore(snapshot)
        s1.opt.set_damping(damping)
    return ValidationStop(state, plan, deadline, lambda: s1.score(state.validation_frames),
                          keep=s1.snapshot, resume_from=resume_from, share=VALIDATION_SHARE)


def stage1_schedule(state: FitState, s1, progress_at):
    """A budgeted stage 1's work after each step at its progress
    ``progress_at(it, total)`` (0..1): densification while it lasts, the
    position learning rate's decay, the other rates' annealing. The
    progress is kept in the stage's budget record, which the checkpoint
    saves, so a resumed stage goes on from it (:func:`~.budget.resumed_progress`)."""
    def after_step(it, total):
        progress = progress_at(it, total)
        s1.after_step(it, total, progress)
        s1.opt.scale_learning_rates(position_lr_factor(progress), moves_with_positions)
        cfg = state.config
        s1.opt.scale_learning_rates(anneal_lr_factor(progress, cfg.anneal_from, cfg.anneal_end),
                                    lambda v: not moves_with_positions(v))
        state.selection.setdefault("budget", {}).setdefault("stage 1", {})["progress"] = \
            round(progress, 5)
    return after_step


def fit_materials(state: FitState, stage2, start, checkpoint, budget=None, fresh=None):
    """Stage 2 from iteration ``start``; returns the last iteration.

    ``fresh`` (default: ``start == 0``): the stage starts in this run, after
    ``start`` iterations of the sun trial, so a budget is planned here."""
    fresh = start == 0 if fresh is None else fresh
    total = planned(state, "stage 2", state.config.stage2_iterations)
    # The log's held-out score re-traces the turned normals' sky visibility
    # only where no validation score does (an unbudgeted fit): a budgeted
    # stage scores its validation frames, with the refresh, just before.
    run = StageRun("stage 2", stage2.iteration, lambda: score_stage2(
        stage2, state.held_out_frames, refresh=budget is None),
                   lambda name, it: checkpoint(name, it, stage2.opt.adam))
    if budget is not None and fresh:
        record_point(state, run, start)   # before the timed iterations move it
        t = time.perf_counter()
        spi = time_iterations(stage2.iteration, start + 1)
        start += 1 + TIMED
        # Leave time for what follows: the LiDAR lobe's refit and the outputs
        # (5 % of the budget). The choice of M for rendering takes only what
        # is left then (it keeps the fit's M when nothing is): it re-traces
        # sky visibility, up to three times what freezing traced, which on
        # a short budget would starve stage 2.
        # Stage 2 takes what is left: its validation PSNR stops it where
        # more steps stop paying (KITTI at 30 minutes: at step 940 of 1130,
        # 500 s before the budget's end).
        reserve = state.config.lobe_iterations * spi + OUTPUT_RESERVE * 60 * budget.minutes
        seconds, least = stage2_seconds(budget.left(), reserve, spi)
        plan = plan_stage("stage 2", seconds, spi, done=start, batched=False,
                          longest_interval=STAGE2_EVAL_INTERVAL)
        if least:
            state.log("[fit] budget: stage 2 gets its least %d steps (%.0f s), %.0f s past what the "
                      "budget leaves it: the fixed costs so far took %.0f s, and fewer steps would "
                      "end the fit below stage 1" % (MIN_STAGE2_STEPS, seconds,
                                                      seconds - max(0.0, budget.left() - reserve),
                                                      t - budget.t_start))
        elif seconds < budget.share("stage 2"):
            state.log("[fit] budget: stage 2 gets %.0f of its %.0f s (the fixed costs so far took "
                      "%.0f s; a larger --budget gives it its share)"
                      % (seconds, budget.share("stage 2"), t - budget.t_start))
        # Its least steps are counted, not timed, whether the minimum or the
        # budget set its time: the validation scores between steps are not
        # in the timed step, and a deadline set from it stopped an 8-minute
        # KITTI fit's stage 2 at 33 of its least 50, and an 8-minute street
        # fit whose budget bought 66 steps at 40 (a slower machine). (The
        # plan, which a resumed fit goes on with, holds them too.)
        plan.iterations = max(plan.iterations, start + MIN_STAGE2_STEPS)
        state.selection.setdefault("budget", {})["stage 2"] = plan.as_dict()
        total = plan.iterations
        run.stop = stage2_stop(state, stage2, plan, t + seconds,
                               not_before=start + MIN_STAGE2_STEPS)
        run.replan = replanner(state, plan, start, t + seconds)
        run.log_share = LOG_SHARE
    elif budget is not None and "stage 2" in state.selection.get("budget", {}):
        # A resumed budgeted stage 2 goes on as planned, at the learning
        # rates its plateaus had lowered them to (the best state before the
        # checkpoint is not saved: the stop keeps the best from here on).
        record = state.selection["budget"]["stage 2"]
        plan = resumed_plan("stage 2", record, start, total)
        run.stop = stage2_stop(state, stage2, plan, time.perf_counter() + plan.seconds)
        lowered = [p["at"] for p in record.get("plateaus", [])]
        if lowered:
            run.stop.plateaus = list(lowered)
            run.stop.damping = PLATEAU_LR_FACTOR ** len(lowered)
            stage2.opt.set_damping(run.stop.damping)
        run.log_share = LOG_SHARE
        state.log("[fit] budget: stage 2 resumed at iteration %d of %d" % (start, total))
    if total > start:
        last = train(state, run, start, total)
        keep_best(state, run, stage2.restore, last, settle=lambda: follow_normals(state, stage2))
        return last
    if fresh and start > 0:
        # The sun trial ran every iteration the stage had (an unbudgeted
        # fit counts the trial's steps in the stage's): its winner is the
        # stage's result, and the log and the iteration count say so
        # rather than ending at stage 1.
        record_point(state, run, start)
        state.iterations["stage 2"] = start
    follow_normals(state, stage2)
    return max(start, total)


def keep_best(state: FitState, run: StageRun, restore, last, settle=None):
    """A budgeted stage's end: back to its best validation state where that
    scores higher (:meth:`ValidationStop.restore_best`), then ``settle()``
    (stage 2's lighting follows the kept normals), and where it went back,
    one more log row at ``last`` scored on the kept state, so that the log's
    last row and metrics.json's held-out score describe what the stage keeps,
    not the state it left."""
    back = isinstance(run.stop, ValidationStop) and run.stop.restore_best(restore, last, run.name)
    if settle is not None:
        settle()
    if back:
        record_point(state, run, last)
    return back


def stage2_stop(state: FitState, stage2, plan, deadline, not_before=None):
    """A budgeted stage 2's :class:`ValidationStop`, scoring the validation
    frames with the lighting caches following the learned normals. Its
    scores stay on the plan's grid (no share): each one first re-traces the
    sky visibility of the turned normals in every cache, the training
    frames' too, so spacing them out would also change what stage 2 learns
    from."""
    def resume_from(snapshot, damping):
        stage2.restore(snapshot)
        stage2.opt.set_damping(damping)
    return ValidationStop(state, plan, deadline, lambda: validation_score(
        *score_stage2(stage2, state.validation_frames, refresh=True)), keep=stage2.snapshot,
        resume_from=resume_from, not_before=not_before)


def follow_normals(state: FitState, stage2):
    """Stage 2's end: its lighting caches follow the normals it kept (what the
    outputs, the lobe and sample-count choices and the fitted scene see),
    and ``metrics.json`` records what the refreshes cost."""
    stage2.refresh_lighting()
    state.selection["lighting_retraced"] = dict(stage2.retraced, seconds=round(
        stage2.retraced["seconds"], 2), turn_deg=RETRACE_TURN_DEG)
    if stage2.moving_shadows:
        traced = stage2.frozen.moving_traced
        state.selection["moving_shadows"] = dict(traced, seconds=round(traced["seconds"], 2))


def replanner(state: FitState, plan, first, deadline, most=None):
    """The budgeted stage's :class:`~.budget.Replan` (never past ``most``),
    which records a raised plan in the fit's selection (a resumed fit keeps
    it) and says so."""
    retime = Replan(first, deadline, most=most)

    def replan(it, total):
        new = retime(it, total)
        if new != total:
            record = state.selection["budget"][plan.name]
            record["replanned"] = {"at": it, "seconds_per_iteration": round(retime.timed, 4),
                                   "iterations_before": total}
            record["iterations"] = new
            state.log("[fit] budget: %s re-timed at iteration %d: %.3f s per step against %.3f s "
                      "timed at its start; %d iterations instead of %d"
                      % (plan.name, it, retime.timed, plan.seconds_per_iteration, new, total))
        return new
    return replan


def planned(state: FitState, stage, iterations):
    """A stage's iteration count: a resumed budgeted fit keeps its plan."""
    return int(state.selection.get("budget", {}).get(stage, {}).get("iterations", iterations))


def validation_score(psnr, rmse):
    """Higher is better: PSNR, or -20 log10 RMSE (the same in dB) without images."""
    return psnr if np.isfinite(psnr) else -20.0 * np.log10(max(rmse, 1e-12))


class ValidationStop:
    """The stop test of a budgeted stage: its share of time is spent, or its
    validation ``score()`` has stopped improving. The score is evaluated on
    multiples of ``plan.eval_every`` iterations; with ``share`` they are
    spaced out (as the log's points are, :class:`~.loop.LogCadence`) where
    the scores would take more than that share of the stage's time. Their
    count and seconds go into the stage's budget record (``validation``).

    With ``keep`` (a function returning the stage's state), the state at the
    best validation score so far is kept in ``best_state``: a stage stopped
    by its validation score has run ``PATIENCE`` evaluations past its best,
    and on the street its stage 1 had lost 0.46 dB held-out by then (25.08
    dB at step 300, 24.62 at 516).

    With ``resume_from`` (``resume_from(best_state, damping)`` puts the
    stage back into a kept state and sets its optimiser's damping), a stage
    whose score levels off goes back to its best state and goes on with
    every learning rate :data:`~.budget.PLATEAU_LR_FACTOR` times lower, up
    to :data:`~.budget.PLATEAU_REDUCTIONS` times, before it stops: what
    was left of the budget would otherwise go unused.
    """

    def __init__(self, state: FitState, plan, deadline, score, keep=None, resume_from=None,
                 share=None, clock=time.perf_counter, not_before=None):
        self.state, self.plan, self.deadline, self.clock = state, plan, deadline, clock
        #: The deadline stops the stage only from this iteration on (stage 2's least steps).
        self.not_before = not_before
        self.score, self.keep, self.resume_from = score, keep, resume_from
        self.stopper = EarlyStop()
        self.best_score = -np.inf
        self.best_state = None
        self.best_iteration = None
        self.last = (None, np.nan)      # (iteration, score) of the last evaluation
        self.damping = 1.0
        self.plateaus = []              # iterations at which the rates were lowered
        self.cadence = LogCadence(plan.eval_every, share, clock=clock)
        self.scores, self.score_seconds = 0, 0.0    # validation scores so far, their time

    def __call__(self, it):
        if self.clock() > self.deadline and (self.not_before is None or it >= self.not_before):
            return "its share of the budget is spent"
        if not (self.state.validation_frames and self.cadence.due(it)):
            return None
        t = self.clock()
        score = self.score()
        seconds = self.clock() - t
        self.cadence.logged(it, seconds)
        self.scores, self.score_seconds = self.scores + 1, self.score_seconds + seconds
        self.state.selection.setdefault("budget", {}).setdefault(self.plan.name, {})[
            "validation"] = {"scores": self.scores, "seconds": round(self.score_seconds, 2),
                             "every": self.cadence.next_at - it}
        self.last = (it, score)
        if self.keep is not None and np.isfinite(score) and score > self.best_score:
            self.best_score, self.best_state, self.best_iteration = score, self.keep(), it
        if self.stopper.update(score):
            if (self.resume_from is not None and self.best_state is not None
                    and len(self.plateaus) < PLATEAU_REDUCTIONS):
                self.damping *= PLATEAU_LR_FACTOR
                self.plateaus.append(it)
                self.resume_from(self.best_state, self.damping)
                self.stopper.since_best = 0
                record = self.state.selection.setdefault("budget", {}).setdefault(self.plan.name, {})
                record.setdefault("plateaus", []).append({"at": it, "back_to": self.best_iteration})
                self.state.log("[fit] %s: validation score level since iteration %d (%.3f); back "
                               "to it with the learning rates x%.2g" % (
                                   self.plan.name, self.best_iteration, self.best_score, self.damping))
                return None
            return "validation score %.3f no better than %.3f for %d evaluations" % (
                self.stopper.history[-1], self.stopper.best, self.stopper.patience)
        return None

    def restore_best(self, restore, it, name):
        """Go back to the kept state if it scores higher than the state at
        iteration ``it`` (the stage's last); records the outcome under the
        stage's budget entry and returns True where it went back. As for
        the early stop, a gain below ``MIN_GAIN`` is noise: the last state stays."""
        if self.best_state is None or self.best_iteration == it:
            return False
        # A stage stopped by its validation score was just scored at ``it``.
        final = self.last[1] if self.last[0] == it else self.score()
        back = bool(np.isfinite(self.best_score)
                    and not self.best_score <= final + self.stopper.min_gain)
        record = self.state.selection.setdefault("budget", {}).setdefault(name, {})
        record["best_validation"] = {"iteration": self.best_iteration, "score": float(self.best_score),
                                     "last_iteration": it, "last_score": float(final),
                                     "kept": "best" if back else "last"}
        if back:
            restore(self.best_state)
            self.state.log("[fit] %s: back to iteration %d (validation score %.3f, %.3f at its "
                           "last iteration %d)" % (name, self.best_iteration, self.best_score,
                                                   final, it))
        self.best_state = None
        return back


def freeze(state: FitState, initialise):
    """Trace every frame once and build stage 2; on a fresh start (not a
    resumed stage 2) also initialise the LiDAR response and the shading."""
    t = time.perf_counter()
    frozen = FrozenScene(state, state.observations)
    traced = time.perf_counter() - t
    if initialise:
        init_materials(state, frozen)
    t = time.perf_counter()
    stage2 = start_stage2(state, frozen, initialise)
    # Trace the per-Gaussian visibility of every sky pattern now (it is
    # cached on first use), so that it is counted here and not in the first
    # stage-2 iterations, which a budget times to plan the stage (tracing
    # three more patterns there once made a step look 12 s long, not 0.6 s).
    stage2.trace_patterns()
    with dr.suspend_grad():   # and compile the render's kernels
        stage2.render_frame(state.train_frames[0], stage2.values(), lidar=False)
    state.times["freeze"] = traced + time.perf_counter() - t
    state.log("[fit] geometry frozen: %d frames traced once, %.1f MB of hit lists, visibility "
              "cached; %.1f s" % (len(state.observations), frozen.nbytes() / 2**20,
                                  state.times["freeze"]))
    return stage2, frozen


def start_stage2(state: FitState, frozen, initialise=True):
    """Stage 2 on the frozen geometry under the scene's current lighting;
    with ``initialise``, its starting shading (:meth:`Stage2.init_shading`)."""
    t = time.perf_counter()
    stage2 = Stage2(state, frozen)
    state.sun_visibility_learned = stage2.learn_sun_visibility
    state.moving_shadows = stage2.moving_shadows
    if initialise:
        si = state.selection["shading_init"] = stage2.init_shading()
        # (What a start takes: the sun trial's estimate of its own start.)
        si["seconds"] = time.perf_counter() - t
        if "sun_irradiance" in si:
            source = si.get("sun_irradiance_from", "facings")
            state.log("[fit] sun irradiance %s from %s (%d facings with sunlit and shadowed "
                      "Gaussians; %.0f %% of the seen Gaussians in traced shadow)"
                      % (np.round(si["sun_irradiance"], 3).tolist(),
                         "them" if source == "facings" else "the lighting " + source,
                         si["facings"], 100 * si["shadowed"]))
        if "start_candidates" in si:
            sc = si["start_candidates"]
            state.log("[fit] stage 2's start under each sun the lighting kept (validation PSNR, "
                      "albedo spread within LiDAR-albedo groups): %s; kept #%d" % (", ".join(
                          "#%d %s irradiance from %s %s dB, spread %s" % (
                              i + 1, np.round(c["sun_direction"], 2).tolist(), c["sun_irradiance_from"],
                              "-" if c["psnr"] is None else "%.2f" % c["psnr"],
                              "-" if c.get("albedo_spread") is None else "%.4f" % c["albedo_spread"])
                          for i, c in enumerate(sc["candidates"])), sc["chosen"] + 1))
        if "start_roughness" in si:
            sr = si["start_roughness"]
            def rough_name(r):
                return "as imported" if r is None else "%.2g" % r
            mix = sr.get("per_gaussian")
            state.log("[fit] roughness at stage 2's start: %s (validation PSNR %s%s)" % (
                "per gaussian" if sr["kind"] == "per_gaussian" else rough_name(sr["for_all"]),
                ", ".join(
                    "%s %s dB" % (rough_name(c["roughness"]),
                                  "-" if c["psnr"] is None else "%.2f" % c["psnr"])
                    for c in sr["candidates"]),
                "" if mix is None else "; per Gaussian %s dB, shares %s" % (
                    "-" if mix["psnr"] is None else "%.2f" % mix["psnr"],
                    ", ".join("%s %.1f %%" % (k, 100 * v) for k, v in mix["shares"].items()))))
        if "light_scale_scores" in si:
            state.log("[fit] light level at stage 2's start: %.2fx the fitted sky and sun (under "
                      "the fitted light the albedo reproducing stage 1 would clip at 1; starting "
                      "PSNR %s)" % (si["light_scale"], ", ".join(
                          "%sx %s dB" % (k, "-" if v is None else "%.2f" % v)
                          for k, v in si["light_scale_scores"].items())))
        if si.get("unclipped", {}).get("psnr_after") is not None:
            u = si["unclipped"]
            state.log("[fit] sun visibility where the start's albedo clipped: raised on %.1f %%, "
                      "lowered on %.1f %% of the seen Gaussians; starting PSNR %.2f -> %.2f dB (%s)"
                      % (100 * u["raised"], 100 * u["lowered"], u["psnr_before"], u["psnr_after"],
                         "kept" if u["kept"] else "not kept"))
    return stage2




def sun_trial(state: FitState, frozen, stage2, lighting: LightingChoice,
              alternative: LightingChoice, k, time_limit=None):
    """Run ``k`` iterations of stage 2 under ``lighting`` (no sun),
    then as many from the same start under ``alternative`` (the narrowly
    rejected sun), score both on the validation frames and go on with the
    one that scores higher (the sun by :data:`SUN_TRIAL_MARGIN`). Returns
    the stage 2 to continue and the iterations it has done.

    With ``time_limit`` (seconds, under a budget) the sun's start is made
    first and counted against it: what is left is split between the two
    candidates' iterations (the first stops once its half is spent, the
    second runs as many). A sun's start tries every direction the lighting
    kept (:meth:`.Stage2.init_shading`), and on an 8-minute KITTI fit it took
    about 90 s of the trial's 48, which ran 137 s and left stage 2 none of
    its share.

    Both start from the same stage-1 result: the nodes' values and the
    step-size state are put back for each candidate (each stage keeps its
    own optimiser)."""
    frames = [f for f in state.validation_frames if f.camera is not None]
    t = time.perf_counter()
    lr_start = dict(state.lr_state)
    plain_start, plain_light = state.stage2_start(), _light_params(state)
    apply_lighting(state, alternative)
    with_sun = start_stage2(state, frozen)
    # (The start may have moved the sun to another direction the lighting kept.)
    sun_start, sun_light = state.stage2_start(), _light_params(state)
    start_seconds = time.perf_counter() - t
    apply_lighting(state, lighting)
    _set_light_params(state, plain_light)
    state.restore_stage2_start(plain_start)
    deadline = None if time_limit is None else \
        time.perf_counter() + 0.5 * max(0.0, time_limit - start_seconds)
    for it in range(1, k + 1):
        stage2.iteration(it)
        if deadline is not None and time.perf_counter() > deadline:
            k = it
            break
    without = score_stage2(stage2, frames)[0]
    kept = state.stage2_start()
    apply_lighting(state, alternative)
    _set_light_params(state, sun_light)
    state.restore_stage2_start(sun_start)
    state.lr_state.clear()
    state.lr_state.update(lr_start)
    for it in range(1, k + 1):
        with_sun.iteration(it)
    score = score_stage2(with_sun, frames)[0]
    use = bool(np.isfinite(score) and (not np.isfinite(without) or score > without + SUN_TRIAL_MARGIN))
    if use:
        stage2 = with_sun
    else:
        apply_lighting(state, lighting)
        state.restore_stage2_start(kept)
    seconds = time.perf_counter() - t
    state.selection["sun"]["trial"] = {"iterations": k, "psnr_without": without, "psnr_with": score,
                                       "scored_on": "validation", "seconds": seconds,
                                       "sun_start_seconds": start_seconds}
    state.selection["sun"]["use_sun"] = use
    state.times["sun trial"] = seconds
    state.log("[fit] sun trial: %d stage-2 iterations each, validation PSNR %.2f dB without the "
              "sun, %.2f dB with it: %s (%.1f s)" % (k, without, score,
                                                    "sun used" if use else "no sun", seconds))
    return stage2, k


def _light_params(state: FitState):
    """Copies of the scene's sky and sun parameters (to come back to)."""
    keys = [k for k in (state.sky_key, state.sun_key, state.sun_dir_key) if k is not None]
    return {k: type(state.params[k])(dr.detach(state.params[k])) for k in keys}


def _set_light_params(state: FitState, saved):
    for k, v in saved.items():
        state.params[k] = v
    state.params.update()


def apply_lighting(ctx: FitState, choice: LightingChoice):
    """Put a lighting choice into the scene and the state."""
    ctx.use_sun = choice.use_sun
    ctx.sh_order = choice.sh_order
    ctx.sh_mask = sh_mask(choice.sh_order, ctx.sky_emitter.order)
    ctx.params[ctx.sky_key] = jit_array(mi.Float, choice.sh_init)
    if choice.use_sun:
        ctx.params[ctx.sun_dir_key] = mi.Vector3f(*choice.sun_direction)
    ctx.params[ctx.sun_key] = mi.Color3f(choice.sun_irradiance)
    ctx.params.update()
    ctx.selection.update(choice.report)


def apply_lidar_lobe(state: FitState, choice: LobeChoice):
    """Record the LiDAR lobe and, for the Lambertian one, take its refitted values."""
    for var, value in choice.values.items():
        var.write(value)
    state.selection["lidar_lobe"] = choice.report


def log_choices(state: FitState):
    lobe, m = state.selection["lidar_lobe"], state.selection["samples"]
    state.log("[fit] LiDAR model: %s (%s intensity RMSE pbr %.4f, lambertian %s)"
              % (lobe["model"], lobe.get("scored_on", ""), lobe["pbr_rmse"],
                 "%.4f" % lobe["lambertian_rmse"] if "lambertian_rmse" in lobe else "not fitted"))
    state.log("[fit] sky samples M = %d for rendering%s" % (m["samples"], "" if "by_samples" not in m
              else " (%s PSNR %s; %.1f s)" % (m["scored_on"], ", ".join(
                  "M=%s %.2f dB" % (k, v["psnr"]) for k, v in m["by_samples"].items()),
                  state.times["samples selection"])))


def report_sun_refinement(ctx):
    """Record (and log) how far stage 2 moved the selected sun direction."""
    sun = ctx.selection.get("sun", {})
    if not ctx.use_sun or "direction" not in sun:
        return
    d = np.array(dr.detach(ctx.params[ctx.sun_dir_key]), np.float64).ravel()
    d /= max(np.linalg.norm(d), 1e-12)
    d0 = np.asarray(sun["direction"], np.float64)
    d0 /= max(np.linalg.norm(d0), 1e-12)
    moved = angle_deg(d, d0)
    sun["fitted_direction"], sun["moved_deg"] = d.tolist(), moved
    if moved > 0:
        ctx.log("[fit] sun direction refined in stage 2: %s -> %s (%.1f deg)"
                % (np.round(d0, 3).tolist(), np.round(d, 3).tolist(), moved))
