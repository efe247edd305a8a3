"""``fit --budget MINUTES``: iterations, batch sizes and learning-rate
schedule from a wall-time budget and the measured iteration speed, with
early stopping on the validation frames.

The budget is split between the stages (:data:`SHARES`; the rest pays for
loading, tracing, selection and outputs). At each stage's start a few real
iterations are timed; the stage then gets as many iterations as fit in its
share (stage 1 at most :data:`STAGE1_MAX_STEPS`: a longer schedule fitted
worse, and the time its share has left goes to stage 2). Once a tenth of them have run, the stage times itself again
(:class:`Replan`): steps timed while another job held the cores, or while
kernels still compiled, would otherwise plan too few iterations and leave
the share half spent. Past :data:`MAX_ITERATIONS` a stage whose larger
batches cost little more per step (a GPU, as :func:`probe_batch_scale`
finds) takes bigger batches instead of more steps; on a CPU, where a step's
cost grows with its rays, it takes more steps of the configured batch. Stage 1's
position learning rate decays exponentially to 1 % over its planned
iterations or its share of the time, whichever runs out first
(:func:`stage_progress`; as 3D Gaussian Splatting schedules it), so the
geometry settles by the end of the share; its other learning rates fall
over the share's last 30 % (:func:`anneal_lr_factor`). Once a stage's
validation score (PSNR; LiDAR intensity RMSE without images; stage 1
scores it within :data:`VALIDATION_SHARE` of its time, stage 2 at least
every :data:`STAGE2_EVAL_INTERVAL` steps) has not
improved by :data:`MIN_GAIN` for :data:`PATIENCE` evaluations, the stage
goes back to its best state and goes on at lower learning rates
(:data:`PLATEAU_LR_FACTOR`, at most :data:`PLATEAU_REDUCTIONS` times), then
stops.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

#: Fractions of the budget for stage 1 and stage 2. The rest pays for the
#: fixed costs (loading, tracing the frozen frames, the lighting and
#: sample-count choices, the outputs), which hardly grow with the budget: on
#: the KITTI excerpt on 2 cores they took about 340 s of an 8-minute budget
#: and about as much of a 30-minute one. Stage 1 decides KITTI's result and
#: was still gaining when a 40 % share ran out, while stage 2 stopped on its
#: validation PSNR with 500 s of the 30 minutes unused; so stage 1 takes
#: half (less where the fixed costs would leave stage 2 nothing,
#: :func:`stage1_seconds`), and stage 2 takes whatever is left once stage 1
#: and the steps between the stages are done
#: (:func:`~mi_invrgbl.fit.runner.fit_materials`; its share here sizes the
#: sun trial).
SHARES = {"stage 1": 0.5, "stage 2": 0.3}
#: Iterations timed at a stage's start (the first one, which compiles, is not counted).
TIMED = 3
#: Beyond this many iterations a stage doubles its batch instead (up to 4x).
MAX_ITERATIONS = 1500
#: Stage 1's position learning rate at its last planned iteration, relative to the first.
POSITION_LR_END = 0.01
#: Evaluations on the validation frames per stage (for early stopping), at
#: least MIN_EVAL_INTERVAL iterations apart (PSNR creeps up from step to step).
EVALUATIONS = 12
MIN_EVAL_INTERVAL = 10
PATIENCE = 3
#: Share of a budgeted stage 1's time its validation scores may take: past
#: it the scores are spaced out (in multiples of the plan's interval, as the
#: log's points are, :class:`~mi_invrgbl.fit.loop.LogCadence`). Twelve
#: scores are cheap on a long stage but not on a short one: on the KITTI
#: excerpt at 8 minutes on 2 cores a stage-1 score of the validation frames
#: cost 1.95 s, 4-5 steps, where the plan put one every 18-31 steps.
VALIDATION_SHARE = 0.05
MIN_GAIN = 0.02    # dB of validation PSNR (or its equivalent in -20 log10 RMSE)
#: A budgeted stage whose validation score levels off (``PATIENCE``
#: evaluations without ``MIN_GAIN``) with time left goes back to its best
#: state and goes on at this factor on every learning rate...
PLATEAU_LR_FACTOR = 0.3
#: ...this many times before it stops. Stage 2 scores a whole frame per step
#: and its score wanders by about 0.1 dB at a constant rate: on KITTI at
#: 30 minutes it stopped at step 783 with 220 s of the budget unused.
PLATEAU_REDUCTIONS = 2
#: A budgeted stage re-times itself once, after this fraction of its planned
#: iterations (at least MIN_EVAL_INTERVAL)...
REPLAN_AT = 0.1
#: ...and takes more iterations when its plan would end with more than this
#: fraction of the planned iterations' worth of its share unused...
REPLAN_SLACK = 0.2
#: ...but at most this many times the planned iterations.
REPLAN_MAX = 4.0
#: Most steps a budgeted stage 1 takes, however long its share: its
#: schedules (the position learning rate's decay, densification, the other
#: rates' annealing) then run over at most this many steps, and the time
#: its share has left goes to stage 2. On the street on 2 cores stage 1's
#: best validation PSNR was 29.08 dB at 8 minutes (1 009 steps), 29.40 at
#: 30 (3 444) and 28.26 at 60 (6 044 steps; held-out as trained 29.37,
#: 29.63, 28.74): over the longer schedule the positions moved at a high
#: rate for longer and held-out PSNR fell to 25.96 dB at step 2 200; with
#: the cap the 60-minute fit's stage 1 reached 29.18 (best validation) and
#: ``eval`` 29.13 dB against 28.39 (one run each). KITTI's 60-minute
#: fit of the release before peaked at 22.34 dB after 3 229 steps, below
#: this release's 30-minute 22.60 after 2 484. The cap sits a little above
#: the street's best schedule.
STAGE1_MAX_STEPS = 4000
#: Most steps between a budgeted stage 2's validation scores. Its plateau
#: test waits :data:`PATIENCE` scores, three times, so with scores a
#: twelfth of the plan apart it waited longer the longer the budget: on the
#: street's 60-minute fit (scores 345 steps apart) stage 2 ran about 4 100
#: steps, held-out PSNR as trained 28.87 dB at step 1 800 and 28.86 at
#: 4 050, while the 30-minute fit (145 apart) stopped itself at step 1 595.
#: Scores at most this far apart make the test wait as many steps whatever
#: the budget; on the street on 2 cores a score cost 1.6-2.1 s, four to six
#: steps.
STAGE2_EVAL_INTERVAL = 150


@dataclass
class StagePlan:
    name: str
    seconds: float            # the stage's share of the budget
    seconds_per_iteration: float
    iterations: int
    batch_scale: int          # batch size relative to the configured one
    eval_every: int           # iterations between validation scores
    #: The iterations the share would hold where ``most`` cut them (else None).
    uncapped: int | None = None

    def as_dict(self):
        d = {"seconds": round(self.seconds, 2), "seconds_per_iteration":
             round(self.seconds_per_iteration, 4), "iterations": self.iterations,
             "batch_scale": self.batch_scale, "eval_every": self.eval_every}
        if self.uncapped is not None:
            d["uncapped_iterations"] = self.uncapped
        return d


def plan_stage(name, seconds, seconds_per_iteration, done=0, batched=True,
               most=None, longest_interval=None) -> StagePlan:
    """How many iterations of ``seconds_per_iteration`` fit in ``seconds``
    (``done`` already run), and the batch scale past :data:`MAX_ITERATIONS`
    (``batched``: the stage samples rays and a larger batch costs little
    more per step; stage 2 renders whole frames, and on a CPU a doubled
    batch costs a doubled step: the KITTI excerpt's stage 1, 300 s of
    4 096-ray steps, scored 18.28 dB on the validation frames where 8 192-ray
    steps scored 17.77 in the same time, ``tests/bench/stage1_budget.py``).
    ``most``: the stage's last iteration at the latest (its share may then
    be left partly unused; :data:`STAGE1_MAX_STEPS`). ``longest_interval``:
    the most steps between validation scores (:data:`STAGE2_EVAL_INTERVAL`;
    else a twelfth of the plan, :data:`EVALUATIONS`)."""
    n = max(1, int(seconds / max(seconds_per_iteration, 1e-6)))
    scale = 1
    while batched and n > MAX_ITERATIONS and scale < 4:
        # A step with twice the rays costs less than twice (fixed per-step work).
        scale *= 2
        n //= 2
    total, uncapped = done + n, None
    if most is not None and total > most:
        total, uncapped = max(done + 1, int(most)), total
    every = max(MIN_EVAL_INTERVAL, total // EVALUATIONS)
    if longest_interval is not None:
        every = max(MIN_EVAL_INTERVAL, min(every, int(longest_interval)))
    return StagePlan(name, seconds, seconds_per_iteration, total, scale, every, uncapped)


def resumed_plan(name, record, start, total) -> StagePlan:
    """The plan of a budgeted stage that ``fit --resume`` continues at
    iteration ``start``: the iterations and batch its first run planned
    (``record``, the stage's entry in metrics.json's ``selection.budget``,
    saved with the checkpoint), and as many seconds as its remaining
    ``total - start`` iterations took there (the re-timed speed where the
    stage was re-timed). The stage's time in the first run is not in the
    checkpoint; its iterations are."""
    timed = record.get("replanned", {}).get("seconds_per_iteration",
                                            record.get("seconds_per_iteration", 0.0))
    spi = max(float(timed or 0.0), 1e-6)
    eval_every = int(record.get("eval_every", max(MIN_EVAL_INTERVAL, total // EVALUATIONS)))
    return StagePlan(name, max(0, total - start) * spi, spi, int(total),
                     int(record.get("batch_scale", 1)), max(1, eval_every))


def resumed_progress(progress_then, start, it, total):
    """A resumed stage's progress (0..1) at iteration ``it``: from
    ``progress_then``, where its schedules stood at the checkpoint's
    iteration ``start`` (:func:`stage_progress`, which may run ahead of the
    iterations where the stage's time ran out first), on to 1 at ``total``,
    so a resumed stage 1 goes on at the learning rates it had reached
    rather than at its start's."""
    p0 = min(1.0, max(0.0, progress_then))
    if total <= start:
        return 1.0
    return min(1.0, p0 + (1.0 - p0) * max(0, it - start) / (total - start))


#: Batch scales a budgeted stage 1 tries at its start, in order.
PROBE_SCALES = (4, 16)
#: A larger batch is kept when it gives this much more rays per second
#: (4x the rays for at most 1.6x the time): stage 1 learns more from more
#: steps than from more rays per step, so a batch must be nearly free to
#: be worth fewer steps (KITTI, 300 s of stage 1: twice the rays per step
#: scored 0.5 dB lower on the validation frames). A GPU's batch is nearly
#: free (4x the rays for about the same time); on 2 CPU cores the street's
#: was not (4x for 2.4x the time, 1.7x the rays per second), and the bar of
#: 1.5 took it...
PROBE_GAIN = 2.5
#: ...and still leaves the stage this many steps in its share.
MIN_STEPS = 300


@dataclass
class BatchProbe:
    scale: int                    # batch size relative to the configured one
    seconds_per_iteration: float  # at that scale
    iterations_run: int           # iterations the probe ran (they are real steps)
    timings: dict = field(default_factory=dict)   # scale -> seconds per iteration


def probe_batch_scale(step, set_scale, first, seconds, spi1) -> BatchProbe:
    """Size stage 1's batches from the machine: time ``step`` at each of
    :data:`PROBE_SCALES` times the configured batch (``set_scale(k)`` sets it)
    and keep the largest that gives :data:`PROBE_GAIN` times the rays per
    second of the one before while :data:`MIN_STEPS` steps still fit in
    ``seconds``. Where a step's cost is mostly per-call overhead (a GPU on
    batches of a few thousand rays) four times the rays cost little more;
    where it is proportional to the rays (a CPU) the configured batch stays.
    """
    best, spi, it = 1, spi1, first
    timings = {1: spi1}
    for k in PROBE_SCALES:
        set_scale(k)
        t = time.perf_counter()
        for _ in range(TIMED):
            step(it)
            it += 1
        spi_k = (time.perf_counter() - t) / TIMED
        timings[k] = spi_k
        if (k / spi_k) >= PROBE_GAIN * (best / spi) and seconds / spi_k >= MIN_STEPS:
            best, spi = k, spi_k
        else:
            break
    set_scale(best)
    return BatchProbe(best, spi, it - first, timings)


@dataclass
class Replan:
    """Re-time a budgeted stage once it has run :data:`REPLAN_AT` of its plan.

    ``__call__(it, total)`` returns the stage's new last iteration: ``total``
    unchanged until the re-timing, and unchanged after it unless the speed
    measured over the steps run so far (evaluations included, so it errs on
    the slow side) leaves more than :data:`REPLAN_SLACK` of the plan unused
    before ``deadline``. It only adds iterations: a stage slower than planned
    is stopped by its deadline. The added steps keep the plan's batch, and
    stage 1's position learning rate stretches its decay to the new end.
    It never plans past ``most`` (:data:`STAGE1_MAX_STEPS`).
    """
    first: int                # the iteration the stage's timing counts from
    deadline: float           # time.perf_counter() at which the stage's share is spent
    most: int | None = None
    clock: Callable = time.perf_counter
    t_first: float = None
    timed: float = None       # seconds per iteration measured at the re-timing
    done: bool = False

    def __post_init__(self):
        if self.t_first is None:
            self.t_first = self.clock()

    def __call__(self, it, total) -> int:
        ran, planned = it - self.first, total - self.first
        if self.done or ran < max(MIN_EVAL_INTERVAL, REPLAN_AT * planned):
            return total
        self.done = True
        now = self.clock()
        # (A clock that did not move, coarse or faked, must not divide by zero.)
        self.timed = max(now - self.t_first, 1e-9) / ran
        more = int(max(0.0, self.deadline - now) / self.timed)
        if it + more > total + REPLAN_SLACK * planned:
            new = int(min(it + more, self.first + REPLAN_MAX * planned))
            return max(total, min(new, self.most)) if self.most is not None else new
        return total


def stage_progress(it, total, elapsed=None, seconds=None):
    """How far a stage is through its plan, from 0 to 1: iteration ``it`` of
    ``total`` or, for a budgeted stage, ``elapsed`` of its ``seconds``,
    whichever is further. Schedules follow it, not the step count alone: a
    stage whose steps grow slower than its plan timed (densification adds
    Gaussians; the validation scores and densification are not in the timed
    steps) is stopped by its deadline, and on KITTI at 30 minutes stage 1
    ran 56 % of its planned steps with its position learning rate still at
    8 % of the start and still densifying."""
    done = it / max(total, 1)
    if elapsed is not None and seconds:
        done = max(done, elapsed / seconds)
    return min(1.0, max(0.0, done))


def position_lr_factor(progress):
    """Stage 1's position learning rate factor at ``progress`` (0..1) of the
    stage (:func:`stage_progress`)."""
    return POSITION_LR_END ** min(1.0, max(0.0, progress))


#: Stage 1's other learning rates (scales, rotations, opacities, colours,
#: the sky) keep their start until this much of the stage has passed (where
#: densification ends, ``FitConfig.densify_until``)...
ANNEAL_FROM = 0.7
#: ...then fall exponentially to this fraction of it at the stage's end.
#: Each step sees 4 096 pixels of one frame, so at a constant rate the
#: Gaussians' colours and opacities keep moving with the batch: KITTI's
#: stage-1 PSNR in ``log.csv`` at 30 minutes jumped by up to 0.4 dB between
#: points 50 steps apart while its trend rose 0.2 dB over the last 700 steps.
ANNEAL_END = 0.1


def anneal_lr_factor(progress, start=ANNEAL_FROM, end=ANNEAL_END):
    """Stage 1's factor on its other learning rates (not the positions,
    :func:`position_lr_factor`) at ``progress`` (0..1) of the stage: 1 up
    to ``start``, then exponentially down to ``end`` at 1."""
    p = min(1.0, max(0.0, progress))
    if p <= start or start >= 1.0:
        return 1.0
    return end ** ((p - start) / (1.0 - start))


@dataclass
class EarlyStop:
    """Stops once the score has not improved by ``min_gain`` for ``patience`` evaluations."""
    patience: int = PATIENCE
    min_gain: float = MIN_GAIN
    best: float = -math.inf
    since_best: int = 0
    history: list = field(default_factory=list)

    def update(self, score) -> bool:
        """Record a score (higher is better); True when the stage should stop."""
        self.history.append(score)
        if not math.isfinite(score):
            return False
        if score > self.best + self.min_gain:
            self.best, self.since_best = score, 0
        else:
            self.since_best += 1
        return self.since_best >= self.patience


def time_iterations(step, first, count=TIMED):
    """Run ``step(first) .. step(first + count)``; seconds per iteration of
    all but the first (which compiles the kernels)."""
    step(first)
    t = time.perf_counter()
    for it in range(first + 1, first + 1 + count):
        step(it)
    return (time.perf_counter() - t) / count


#: Under a budget the sun trial (the sun's start and both candidates' steps)
#: takes at most this part of stage 2's share: at 100 iterations each it once
#: took 221 s of an 8-minute KITTI fit and left stage 2 none of its 144 s...
SUN_TRIAL_STEPS = 1.0 / 3.0
#: ...of which the sun's start may take this part, so that both candidates
#: get steps to be told apart by (on the street's 8-minute fit the two
#: starts scored 28.52 and 28.62 dB on the validation frames, and after two
#: steps each 28.14 and 28.59)...
SUN_TRIAL_START = 0.75
#: ...and the part of its share stage 2 must keep after the trial for it to
#: run. On the street at 8 minutes the steps between the stages leave stage 2
#: about 60 % of its share (87 of 144 s): a trial of a third of the share
#: leaves it a quarter, about 100 steps, and under the true sun stage 2's
#: validation PSNR rose 0.3 dB in its first 40.
SUN_TRIAL_KEEP = 0.25

#: Share of the budget kept for the outputs after stage 2.
OUTPUT_RESERVE = 0.05


@dataclass
class Budget:
    """The wall-time budget of one fit, counted from ``t_start``."""
    minutes: float
    t_start: float

    @property
    def deadline(self):
        return self.t_start + 60.0 * self.minutes

    def share(self, stage):
        return SHARES[stage] * 60.0 * self.minutes

    def left(self):
        return self.deadline - time.perf_counter()

    def stage2_left(self):
        """Seconds left for stage 2: what remains but the outputs' reserve
        (:data:`OUTPUT_RESERVE` of the budget)."""
        return self.left() - OUTPUT_RESERVE * 60.0 * self.minutes

    def sun_trial_fits(self, start_seconds=0.0) -> bool:
        """Whether stage 2 can afford the sun trial: its limit
        (:data:`SUN_TRIAL_STEPS` of stage 2's share) holds the sun's start
        with room for steps (the start, estimated as ``start_seconds``, what
        the first start took, is at most :data:`SUN_TRIAL_START` of it), and
        after it stage 2 keeps :data:`SUN_TRIAL_KEEP` of its share.

        The trial's start and its two validation scores cost the same however
        few its steps. Before a moved sun stopped re-tracing the sky's
        visibility (:class:`~mi_invrgbl.physics.lighting.LightingCache`),
        one step per candidate took 134 s of an 8-minute KITTI fit whose
        stage 2 had 100 s left, and left stage 2 none; on the street's
        8-minute fit the trial with two steps each took 77 s, 52 of them
        three sky traces, and takes 23 s without them (the sun's start 21 s)."""
        limit = self.sun_trial_limit()
        return (start_seconds <= SUN_TRIAL_START * limit
                and self.stage2_left() - limit >= SUN_TRIAL_KEEP * self.share("stage 2"))

    def sun_trial_limit(self) -> float:
        """Seconds the sun trial may take, its start included
        (:data:`SUN_TRIAL_STEPS` of stage 2's share)."""
        return SUN_TRIAL_STEPS * self.share("stage 2")


#: A fit more than this fraction past its budget says where the time went.
OVERRUN_TOLERANCE = 0.05
#: The steps outside the two stages (sky look-alikes, lighting, freezing,
#: selections, outputs) cost about this many configured stage-1 steps per
#: frame: 16 to 29 in the street's and the KITTI excerpt's fits on 2 cores at
#: 2- to 60-minute budgets (metrics.json: wall time less the stages, over
#: frames x seconds per step). The low end, so that a fit which keeps to its
#: budget is not warned.
FIXED_STEPS_PER_FRAME = 16


#: Where the fixed costs leave little of a budget beside stage 1's share,
#: stage 1 takes at most this part of what remains once they are paid, so
#: that stage 2 keeps the rest...
STAGE1_OF_REST = 0.6
#: ...as long as that rest buys stage 2 at least this many steps (fewer would
#: not take it past its start, and stage 1 keeps its share). Stage 2 starts
#: 1.5-2.9 dB below stage 1 on the KITTI excerpt and climbs back fast: on 2
#: cores +1.43 dB in its first 50 steps at 8 minutes (19.54 -> 20.97 dB
#: held-out, as trained) and +2.09 at 30 (20.07 -> 22.16), where stage 1's
#: last 100 steps at 8 minutes added 0.17 dB. At 8 minutes the fixed costs
#: took 190 s, stage 1 its 240 s, and stage 2 ran its 5 timed steps: its
#: start, about 2 dB below stage 1's best, was the result.
MIN_STAGE2_STEPS = 50
#: A stage-2 step's cost in configured stage-1 steps (stage 2 renders whole
#: frames and scores its validation frames as it goes): 2.5 on 2 cores
#: (KITTI: 0.58 s against 0.23 s), which keeps the 2-core fits' plans as
#: they were; 3.8 on one H200 (the street: 0.088 s against 0.023 s), where
#: per-step overhead dominates, so there the minimum buys about 33 steps.
#: The minimum was 30 s of stage 2 whatever the machine: 50 steps on 2
#: cores but some 300 on a GPU. A 2-minute KITTI fit on one H200 had about
#: 27 s to give stage 2, fell under it, kept all of stage 1's share, and
#: ended 1.2 dB below stage 1 after 5 stage-2 steps.
STAGE2_STEP_COST = 2.5


def min_stage2_seconds(seconds_per_step) -> float:
    """Seconds that buy stage 2 :data:`MIN_STAGE2_STEPS` steps, from a
    configured stage-1 step's ``seconds_per_step``."""
    return MIN_STAGE2_STEPS * STAGE2_STEP_COST * seconds_per_step


def stage2_seconds(left, reserve, seconds_per_step2) -> tuple[float, bool]:
    """Stage 2's time once it is timed: what the budget has ``left`` less the
    ``reserve`` for what follows it, but never less than
    :data:`MIN_STAGE2_STEPS` of its own steps (``seconds_per_step2``), even
    past the budget's end. Returns ``(seconds, whether the minimum set it)``.

    Stage 2 starts below stage 1 and climbs back in its first tens of
    steps; cut to a handful, the fit ends below what stage 1 had. On the
    KITTI excerpt at 8 minutes on 2 cores, on a machine whose steps outside
    the stages took 296 s (24.7 configured stage-1 steps per frame against
    the :data:`FIXED_STEPS_PER_FRAME` planned with), stage 2 had 2 s, ran its
    5 timed steps from a start 1.64 dB below stage 1 (held-out, as trained)
    and ended 1.05 dB below it. Its minimum (50 steps, about 40 s there)
    costs the budget less than that loses."""
    seconds = max(0.0, left - reserve)
    least = MIN_STAGE2_STEPS * seconds_per_step2
    return (least, True) if seconds < least else (seconds, False)


def stage1_seconds(minutes, elapsed, frames, seconds_per_step) -> float:
    """Stage 1's time in a budget of ``minutes``: its share (:data:`SHARES`),
    or less where the steps no budget shrinks (estimated as in
    :func:`small_budget_warning` from ``frames`` and a configured stage-1
    step's ``seconds_per_step``; ``elapsed`` seconds already spent) would
    leave stage 2 too little (:data:`STAGE1_OF_REST`), as long as what is
    left buys stage 2 its :data:`MIN_STAGE2_STEPS`."""
    share = SHARES["stage 1"] * 60.0 * minutes
    rest = 60.0 * minutes - elapsed - fixed_costs(frames, seconds_per_step)
    if (1.0 - STAGE1_OF_REST) * rest < min_stage2_seconds(seconds_per_step):
        return share
    return min(share, STAGE1_OF_REST * rest)


def fixed_costs(frames, seconds_per_step) -> float:
    """Estimated seconds of the steps outside the two stages: ``frames``
    frames at :data:`FIXED_STEPS_PER_FRAME` configured stage-1 steps of
    ``seconds_per_step`` each."""
    return FIXED_STEPS_PER_FRAME * frames * seconds_per_step


def over_budget(minutes, wall_s) -> bool:
    """Whether ``wall_s`` seconds ran more than :data:`OVERRUN_TOLERANCE`
    past a budget of ``minutes`` (never for no budget or no wall time; also
    the convergence bench's "over" mark)."""
    return (minutes is not None and minutes > 0 and wall_s is not None
            and wall_s > (1.0 + OVERRUN_TOLERANCE) * 60.0 * minutes)


def overrun_report(minutes, wall_s, times) -> str | None:
    """The line a budgeted fit logs when it ran past its budget: the steps
    outside the two stages (``times``: seconds by step, as in metrics.json's
    ``times_s``) that no share of the budget can shrink, largest first.
    Those fixed costs grow with the frames and pixels, not the budget; on the
    KITTI excerpt on 2 cores they alone exceed a 2-minute budget."""
    if not over_budget(minutes, wall_s):
        return None
    stages = sum(t for name, t in times.items() if name.startswith("stage"))
    named = sorted(((t, name) for name, t in times.items()
                    if not name.startswith("stage") and t >= 1.0), reverse=True)
    other = wall_s - stages - sum(t for t, _ in named)
    parts = ["%s %.0f s" % (n, t) for t, n in named] + (["other %.0f s" % other] if other >= 1.0
                                                         else [])
    return ("[fit] ran %.0f s of a %g-minute budget: the stages took %.0f s, the rest %.0f s "
            "(%s), which no budget shrinks; budgets below about %.0f s leave the stages no time"
            % (wall_s, minutes, stages, wall_s - stages, ", ".join(parts), wall_s - stages))


def small_budget_warning(minutes, elapsed, stage1_share, frames, seconds_per_step) -> str | None:
    """The line a budgeted fit logs once stage 1 is timed, where the budget
    cannot hold the steps no budget shrinks: ``elapsed`` seconds spent so
    far, stage 1's share, and an estimate of the rest from ``frames`` and a
    configured stage-1 step's ``seconds_per_step``. None where it fits."""
    rest = fixed_costs(frames, seconds_per_step)
    expected = elapsed + stage1_share + rest
    if not over_budget(minutes, expected):
        return None
    return ("[fit] budget: %g minutes is too little for this scene on this machine: after "
            "stage 1 the other steps take about %.0f s here (estimated from %d frames at %.2f s "
            "per stage-1 step), so the fit will take about %.0f s and stage 2 gets only its "
            "least steps" % (minutes, rest, frames, seconds_per_step, expected))
