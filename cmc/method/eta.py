"""Remaining-time estimates: training steps whose cost changes with the loss schedule, and the
stages of a job that have not started yet (the API's ``eta_seconds``). No torch here.

Training: the first ``recon_only_fraction`` of the steps render only the input views' rays (the
reconstruction loss); from the first full-loss step on, each step also renders the rays of the
unseen poses, so a rate measured early misjudges what is left.
:class:`TrainingETA` keeps each phase's mean step time apart and, until the full phase has run a
step, predicts its step time as the reconstruction-only one times :func:`full_cost_ratio`, the
ratio of rays a step renders in the two phases (rendering every ray through every MPI dominates
a step) times the measured share of a full-loss ray's cost (:data:`FULL_RAY_COST`). From its
first step on, the full phase's own measured time replaces the prediction.

Stages that have not run yet are estimated as the latest ready job of the same kind measured
them on the deployment (``worker.pipeline.JobPace``), else from a reference run, until they
measure their own speed: fern's three 12 MP photos at 504x378, ``fast`` preset, on the project's
2-core CPU.

* :data:`REFERENCE_POSES_S`: structure from motion, 2.45 s (median of 3, bench/reports/history/sift_octave.md).
* :data:`REFERENCE_STEP_S`: a training step, 0.42 s in ``cmc serve``: the mean step of three
  300-step jobs (bench/reports/history/job_timeline_fern_cpu_layout{1,2,3}.json, 2026-12-02:
  125.1-126.6 s from the preview to the final bake). A GPU trains much faster: until training
  has run a step, the estimate of a deployment's first job is pessimistic there.
* The model build (the plane sweeps), in training steps (:func:`build_steps`), and baking
  (:func:`bake_steps`): modelled from the same kind of jobs. Without an earlier job, a job that
  bakes a preview measures its bake speed there (:func:`final_bake_s`), and until it has trained
  a second step (the first pays one-off costs) it takes its step time from its own model build's
  pace (:func:`step_s_from_build`; ``worker.pipeline``): a slower or faster CPU than the
  reference shows in the build first.
"""

from __future__ import annotations

import math
from collections import deque

from cmc.config import TrainConfig, preset_config

REFERENCE_POSES_S = 2.45
REFERENCE_STEP_S = 0.42


def first_full_step(cfg: TrainConfig) -> int:
    """Index of the first step with the full loss (``Trainer.compute_losses`` switches at
    ``step >= recon_only_fraction * steps``)."""
    return math.ceil(cfg.loss.recon_only_fraction * cfg.steps)


def input_rays_per_mpi(cfg: TrainConfig, num_views: int) -> float:
    """Input-view rays each MPI renders in a step: every ray drawn from its own photo and the share
    ``cross_view_rays`` of each other photo's (``Trainer.compute_losses``)."""
    return cfg.rays_per_view * (1 + (num_views - 1) * cfg.cross_view_rays)


# A full-loss step's rays cost less than the first phase's: by then alpha has concentrated and
# the backward pass skips the colours of more faint samples (TrainConfig.colour_grad_min_weight).
# 23 fern jobs in `cmc serve` on 2-core CPUs (the job_timeline reports of 2026-12-02 to 12-06,
# bench/job_timeline.md) took 0.87-1.15 times (median 0.97) the first phase's mean step for a
# full-loss step, where the rays alone say 1.17 (2048 unseen rays then).
FULL_RAY_COST = 0.83


def full_cost_ratio(cfg: TrainConfig, num_views: int) -> float:
    """A full-loss step's predicted time over a reconstruction-only step's: the ratio of rays the
    two render times :data:`FULL_RAY_COST`."""
    recon = input_rays_per_mpi(cfg, num_views)
    lc = cfg.loss
    unseen = cfg.unseen_poses * cfg.unseen_rays if (lc.lambda_ac > 0 or lc.lambda_dc > 0) else 0
    return FULL_RAY_COST * (recon + unseen) / recon


def bake_steps(width: int, height: int, margin: float, rays_per_mpi: float) -> float:
    """Baking's cost in training steps (a model fitted to one kind of job), until a preview's bake
    has measured it.

    Per plane of every MPI the bake evaluates the field once at each of ``margin^2 * W * H``
    texels and writes it; a step evaluates it at ``rays_per_mpi`` samples
    (:func:`input_rays_per_mpi`), forward and backward. Fern at 504x378 (each MPI rendering
    12288 input rays a step): about 15.7 steps (the final bake 6.1-7.2 s in ``cmc serve``,
    publishing included, against the jobs' mean steps of 0.42 s, the reports of
    :data:`REFERENCE_STEP_S`).
    """
    return margin**2 * width * height / (1.42 * rays_per_mpi)


def build_steps(width: int, height: int) -> float:
    """The model build's cost (the plane sweeps, with loading the photos and the kernels) in
    training steps (a model fitted to one kind of job): fern at 504x378, ``fast``, in ``cmc serve``
    on the 2-core CPU, the three jobs of :data:`REFERENCE_STEP_S` (builds of 8.3-8.7 s against
    their mean steps of 0.417-0.422 s): 19.7-20.9 steps, 20.5 in the middle; in proportion to
    the photos' pixels up to that size, no more above it (the sweep's grid is capped:
    ``SweepConfig.max_texels``)."""
    return 20.5 * min(1.0, width * height / (504 * 378))


def step_s_from_build(build_s: float, width: int, height: int) -> float:
    """Seconds per training step predicted from a model build of ``build_s`` seconds on the same
    machine (photos ``width`` x ``height``): the build and the steps run the same kind of compiled
    kernels on the same cores. On a GPU the steps gain more than the build, so the prediction is
    pessimistic there until a step is measured."""
    return build_s / build_steps(width, height)


def final_bake_s(bake_cost: float, step_s: float, measured_s: float | None = None) -> float:
    """Seconds the final bake is expected to take: ``bake_cost`` training steps (:func:`bake_steps`)
    of ``step_s`` seconds, or a measured estimate ``measured_s``: the final bake of an earlier job
    of the kind (``worker.pipeline.JobPace``), else once a preview was baked the preview's
    measured bake scaled by its texels (fern's final bake took 4.1x the half-resolution preview's
    in a process doing nothing else, 3.9-6.2x in ``cmc serve``, bench/job_timeline.md). On a GPU
    the steps are far faster than the bake, which writes its textures on the CPU: they would say
    less still."""
    return bake_cost * step_s if measured_s is None else measured_s


def reference_training_s(steps: int, step_s: float = REFERENCE_STEP_S) -> float:
    """Seconds to build the model, train ``steps`` steps and bake, as the reference (fern,
    ``fast``) counts them in training steps, at ``step_s`` seconds a step."""
    fast = preset_config("fast")
    bake = bake_steps(504, 378, fast.model.margin, input_rays_per_mpi(fast, 3))
    return (build_steps(504, 378) + steps + bake) * step_s


def checkpoints_to_come(
    step: int, total: int, every: int, step_s: float, every_s: float | None, since_saved_s: float
) -> int:
    """Checkpoint writes still to come in a run at ``step`` of ``total`` steps of ``step_s`` seconds,
    by ``Trainer.fit``'s rule: after every step that is a multiple of ``every``, after the first
    step that ends ``every_s`` seconds or more after the last write (``since_saved_s`` ago now; None:
    no such writes), and one after the last step."""
    marks = list(range((step // every + 1) * every, total + 1, every))  # writes by step count
    count = len(marks) + 1
    if every_s is None or step_s <= 0:
        return count
    per = max(1, math.ceil(every_s / step_s))  # steps from a write to the next by time
    start, first = step, max(1, math.ceil((every_s - since_saved_s) / step_s))
    for end in [*marks, total]:
        if end > start:  # writes by time at start + first + i * per, before the next mark (or at the end)
            last = end if end == total and end not in marks else end - 1
            if start + first <= last:
                count += (last - start - first) // per + 1
        start, first = end, per
    return count


# A phase's step time is the mean of its last this many steps: steps get slower as training goes
# (fern's full-loss steps 0.74 s at first, 0.81 s at the end, bench/job_timeline.md), which the
# mean of the whole phase would lag behind.
RECENT_STEPS = 25


class TrainingETA:
    """Seconds left in a training run, with each loss phase's step time measured apart (the mean
    of its last :data:`RECENT_STEPS` steps).

    Args:
        total: steps of the run; first_full: index of the first full-loss step
            (:func:`first_full_step`); full_cost_ratio: predicted full / reconstruction-only step
            time (:func:`full_cost_ratio`, or an earlier run's measured ratio), used only until
            one phase has no measurement.
    """

    def __init__(self, total: int, first_full: int, full_cost_ratio: float):
        self.total, self.first_full, self.ratio = total, min(max(first_full, 0), total), full_cost_ratio
        # per phase (reconstruction-only, full): the times of its last RECENT_STEPS steps
        self._recent: list[deque[float]] = [deque(maxlen=RECENT_STEPS), deque(maxlen=RECENT_STEPS)]
        # the first step recorded (its phase, its seconds): it pays a process's one-off costs
        # (fern on the CPU: 3 s against 1.8 s, bench/job_timeline.md), so it counts only until
        # its phase has another
        self._first: tuple[int, float] | None = None
        # per phase: the seconds and the number of its steps after the first recorded
        self._sum, self._count = [0.0, 0.0], [0, 0]

    @classmethod
    def for_config(cls, cfg: TrainConfig, num_views: int, measured_ratio: float | None = None) -> TrainingETA:
        """The estimator of a run of ``cfg`` on ``num_views`` photos; the full phase's steps
        predicted at ``measured_ratio`` (an earlier run's full / reconstruction-only mean step
        time) when given, else at the ratio of rays."""
        ratio = measured_ratio if measured_ratio is not None else full_cost_ratio(cfg, num_views)
        return cls(cfg.steps, first_full_step(cfg), ratio)

    def record(self, step: int, seconds: float) -> None:
        """Step ``step`` (0-based) took ``seconds``."""
        phase = int(step >= self.first_full)
        if self._first is None:
            self._first = (phase, seconds)
        else:
            self._recent[phase].append(seconds)
            self._sum[phase] += seconds
            self._count[phase] += 1

    def phase_means(self) -> tuple[float | None, float | None]:
        """The mean step time of each phase (reconstruction-only, full) over all its steps but the
        first recorded; None for a phase without such steps."""
        recon, full = (t / n if n else None for t, n in zip(self._sum, self._count, strict=True))
        return recon, full

    def step_s(self, full: bool) -> float | None:
        """Seconds per step of a phase: the mean of its recent steps (the first step recorded only
        while its phase has no other), else predicted from the other phase's."""
        means = [sum(r) / len(r) if r else None for r in self._recent]
        if self._first is not None and means[self._first[0]] is None:
            means[self._first[0]] = self._first[1]
        recon, full_ = means
        if full:
            return full_ if full_ is not None else (None if recon is None else recon * self.ratio)
        return recon if recon is not None else (None if full_ is None else full_ / self.ratio)

    def remaining_s(self, done: int) -> float | None:
        """Seconds for steps ``done`` .. ``total - 1``; None before any step was measured."""
        recon_left = max(self.first_full - done, 0)
        full_left = max(self.total - max(done, self.first_full), 0)
        if recon_left + full_left <= 0:
            return 0.0
        recon_s, full_s = self.step_s(False), self.step_s(True)
        if recon_s is None or full_s is None:
            return None
        return recon_left * recon_s + full_left * full_s
