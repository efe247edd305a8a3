"""The training loop shared by both stages: iterations with a progress bar,
periodic evaluation into the speed/error log, checkpoints and Ctrl-C."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

from .progress import ProgressBar, peak_rss_mb
from .state import FitState


class Interrupted(Exception):
    """Ctrl-C during a stage: a checkpoint was written."""


@dataclass
class StageRun:
    """What the loop needs of a stage.

    ``step(it)`` runs one iteration and returns (loss, terms, ok);
    ``evaluate()`` returns (held-out PSNR, held-out intensity RMSE) for the log;
    ``after_step(it, total)`` is the stage's own between-iterations work (stage 1
    densifies there), or None; ``checkpoint(stage, it)`` writes a checkpoint;
    ``stop(it)`` returns a reason to end the stage early (a budget's
    deadline or early stopping), or None; ``replan(it, total)`` returns the
    stage's last iteration, which a budget may raise once it has re-timed
    the stage (:class:`~mi_invrgbl.fit.budget.Replan`), or is None;
    ``log_share`` (a budgeted stage) spaces the log's points by what they
    cost (:class:`LogCadence`).
    """
    name: str
    step: Callable
    evaluate: Callable
    checkpoint: Callable
    after_step: Callable | None = None
    stop: Callable | None = None
    replan: Callable | None = None
    log_share: float | None = None


#: Share of a budgeted stage's time its log points may take. Each point
#: scores the held-out frames, which only the log reads: on the KITTI
#: excerpt on 2 cores one stage-1 point costs 2.2 s, 6-7 steps, so a point
#: every 50 steps took 11-13 % of stage 1's share.
LOG_SHARE = 0.03


@dataclass
class LogCadence:
    """Which iterations write a ``log.csv`` point.

    Every ``every`` iterations (``FitConfig.eval_every``); with ``share``,
    after each point the next is put off, in whole multiples of ``every``,
    until the points cost at most ``share`` of the stage's time: the
    point's own seconds against the seconds per iteration measured between
    the last two points (points included, so it errs towards more of
    them). The first point is on a multiple of ``every`` (``next_at``
    None; a resumed stage starts anywhere)."""
    every: int
    share: float | None = None
    clock: Callable = time.perf_counter
    next_at: int | None = None
    _last: tuple = field(default=None, repr=False)

    def due(self, it) -> bool:
        if self.share is None or self.next_at is None:
            return it % self.every == 0
        return it >= self.next_at

    def logged(self, it, seconds):
        """A point was written at ``it`` and took ``seconds``."""
        now = self.clock()
        step = self.every
        if self.share is not None and self._last is not None and it > self._last[0]:
            per_it = max(now - self._last[1], 1e-9) / (it - self._last[0])
            step = self.every * max(1, math.ceil(seconds / (self.share * per_it) / self.every))
        self._last = (it, now)
        self.next_at = (it // self.every) * self.every + step


def _log_name(term):
    return "drop" if term == "raydrop" else "prior" if term in ("nor", "mat") else term


def record_point(state: FitState, run: StageRun, it, loss=float("nan"), terms=None):
    """One row of ``log.csv``: wall time, losses and the progress scores.

    Iteration 0 is a stage's starting point (stage 2: stage 1's geometry
    under the initial materials and light), so the log shows what the stage
    itself gains or loses."""
    psnr, rmse = run.evaluate()
    state.speed_log.add(
        wall_s="%.2f" % (time.perf_counter() - state.t_start + state.wall_offset),
        stage=run.name, iteration=it, loss="%.6g" % loss,
        **{"loss_" + _log_name(k): "%.6g" % v for k, v in (terms or {}).items()},
        heldout_psnr="%.3f" % psnr,
        heldout_intensity_rmse=("%.5f" % rmse) if rmse == rmse else "",
        peak_rss_mb="%.0f" % peak_rss_mb())


def train(state: FitState, run: StageRun, start, total):
    """Run iterations ``start + 1 .. total``; returns the last one."""
    cfg = state.config
    bar = ProgressBar(run.name, total, start_at=start)
    t_stage = time.perf_counter()
    it = start

    cadence = LogCadence(cfg.eval_every, run.log_share)

    def record(it, loss=float("nan"), terms=None):
        t = time.perf_counter()
        record_point(state, run, it, loss, terms)
        cadence.logged(it, time.perf_counter() - t)

    try:
        if start == 0 and total > 0:
            record(0)
        while it < total:
            it += 1
            loss, terms, _ = run.step(it)
            if run.replan is not None:
                total = run.replan(it, total)
                bar.total = max(total, 1)
            if run.after_step is not None:
                run.after_step(it, total)
            bar.update(it, "loss %.4g" % loss)
            reason = run.stop(it) if run.stop is not None else None
            if cadence.due(it) or it == total or reason:
                record(it, loss, terms)
            if cfg.checkpoint_every and it % cfg.checkpoint_every == 0:
                run.checkpoint(run.name, it)
            if reason:
                state.log("[fit] %s stops at iteration %d of %d: %s" % (run.name, it, total, reason))
                break
    except KeyboardInterrupt:
        bar.close()
        state.log("\n[fit] interrupted at %s iteration %d: writing a checkpoint and the outputs so far"
                  % (run.name, it))
        run.checkpoint(run.name, it - 1)
        raise Interrupted() from None
    bar.close()
    state.times[run.name] = state.times.get(run.name, 0.0) + time.perf_counter() - t_stage
    state.iterations[run.name] = it
    return it
