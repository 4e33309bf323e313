"""Remaining-time estimates: a training run whose steps get slower when the full loss starts."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from helpers import finished_job

import cmc.method.training
from cmc.config import preset_config
from cmc.data.datasets import synthetic_scene
from cmc.method.eta import (
    FULL_RAY_COST,
    REFERENCE_POSES_S,
    REFERENCE_STEP_S,
    TrainingETA,
    bake_steps,
    build_steps,
    checkpoints_to_come,
    final_bake_s,
    first_full_step,
    full_cost_ratio,
    input_rays_per_mpi,
    step_s_from_build,
)
from cmc.method.training import Trainer
from cmc.serving.baking import PREVIEW_TEXEL_SCALE


class FakeClock:
    """Stands in for ``time`` in cmc.method.training: the seconds a test moves it by."""

    now = 0.0

    def perf_counter(self) -> float:
        return self.now


def _naive_remaining_s(elapsed: float, done: int, total: int) -> float:
    """The estimate before cmc.method.eta: the mean step time so far times the steps left."""
    return elapsed / done * (total - done)


def test_phase_aware_estimate_beats_the_rate_based_one() -> None:
    """Steps of the full phase take 1.5x those before it (with 5 % jitter); the estimator's
    prior ratio is 1.4, a little off, as a ray count would be."""
    total, first_full = 400, 120
    rng = np.random.default_rng(0)
    times = np.where(np.arange(total) < first_full, 0.2, 0.3) * rng.uniform(0.95, 1.05, total)
    eta = TrainingETA(total, first_full, full_cost_ratio=1.4)
    assert eta.remaining_s(0) is None  # nothing measured yet
    for done in range(1, total + 1):
        eta.record(done - 1, float(times[done - 1]))
        truth = float(times[done:].sum())
        ours = eta.remaining_s(done)
        naive = _naive_remaining_s(float(times[:done].sum()), done, total)
        if 10 <= done <= first_full:  # early, and up to the switch: the naive estimate is far off
            assert abs(ours - truth) <= 0.1 * truth, (done, ours, truth)
            assert abs(ours - truth) < abs(naive - truth)
        if done >= first_full + 10 and done < total:  # the full phase's own time is measured
            assert abs(ours - truth) <= 0.05 * truth, (done, ours, truth)
    naive_at_switch = _naive_remaining_s(float(times[:first_full].sum()), first_full, total)
    truth_at_switch = float(times[first_full:].sum())
    assert naive_at_switch < 0.7 * truth_at_switch  # the old estimate was 30 % short here
    assert eta.remaining_s(total) == 0.0


def test_estimate_follows_steps_that_slow_down() -> None:
    """Steps getting 20 % slower over the run, as training's do: the estimate from the recent
    steps is nearer the truth than the mean of all steps so far, and within 7 % of it."""
    total = 300
    times = np.linspace(0.7, 0.84, total)
    eta = TrainingETA(total, first_full=0, full_cost_ratio=1.0)
    for done in range(1, total):
        eta.record(done - 1, float(times[done - 1]))
        truth = float(times[done:].sum())
        whole_mean = float(times[:done].mean()) * (total - done)
        if done >= 100:
            assert abs(eta.remaining_s(done) - truth) < abs(whole_mean - truth), done
            assert abs(eta.remaining_s(done) - truth) <= 0.07 * truth, done


def test_first_step_counts_only_until_its_phase_has_another() -> None:
    """A process's first step pays one-off costs (3 s here against 1 s): the estimate takes it
    while it is all there is, and drops it from the next step of its phase on."""
    eta = TrainingETA(10, first_full=5, full_cost_ratio=2.0)
    eta.record(0, 3.0)
    assert eta.remaining_s(1) == pytest.approx(4 * 3.0 + 5 * 6.0)
    eta.record(1, 1.0)
    assert eta.step_s(False) == 1.0 and eta.remaining_s(2) == pytest.approx(3 * 1.0 + 5 * 2.0)
    resumed = TrainingETA(10, first_full=5, full_cost_ratio=2.0)  # from a checkpoint in the full phase
    resumed.record(7, 6.0)
    resumed.record(8, 2.5)
    assert resumed.step_s(True) == 2.5 and resumed.step_s(False) == 1.25


def test_fit_reports_the_phase_aware_estimate(monkeypatch) -> None:
    """Trainer.fit's Progress.eta_s, on a fake clock: recon-only steps take 1 s, full ones 1.4 s."""
    # every MPI renders every input ray: the full phase renders 4/3 the rays of the first, each
    # at FULL_RAY_COST of a first-phase ray's cost
    cfg = preset_config("fast", steps=100, rays_per_view=64, unseen_rays=64, cross_view_rays=1.0)
    cfg = replace(cfg, model=replace(cfg.model, num_planes=4))
    trainer = Trainer(synthetic_scene(num_views=3, width=32, height=24), cfg)
    first_full = first_full_step(cfg)
    assert first_full == 30

    clock = FakeClock()

    def fake_step(self: Trainer) -> dict[str, float]:
        clock.now += 1.0 if self.step < first_full else 1.4
        self.step += 1
        return {"mse": 0.0}

    monkeypatch.setattr(cmc.method.training, "time", clock)
    monkeypatch.setattr(Trainer, "train_step", fake_step)
    seen = {}
    result = trainer.fit(on_progress=lambda p: seen.setdefault(p.step, p.eta_s))
    truth = {done: max(first_full - done, 0) * 1.0 + (100 - max(done, first_full)) * 1.4 for done in seen}
    # before the switch: recon-only time x the cost model's ratio (the truth here is 1.4)
    assert seen[10] == pytest.approx(20 + 70 * 4 / 3 * FULL_RAY_COST)
    naive = _naive_remaining_s(10.0, 10, 100)
    assert abs(seen[10] - truth[10]) < 0.2 * truth[10] < abs(naive - truth[10])  # nearer than the naive rate
    assert seen[50] == pytest.approx(truth[50])  # in the full phase: its own measured time
    assert seen[100] == 0.0
    assert result.phase_step_s == pytest.approx((1.0, 1.4))  # each phase's mean step

    # an earlier run's measured ratio (worker.pipeline.JobPace) predicts the full phase exactly
    trainer.step, seen = 0, {}
    trainer.fit(on_progress=lambda p: seen.setdefault(p.step, p.eta_s), full_cost_ratio=1.4)
    assert seen[10] == pytest.approx(truth[10])


def test_checkpoints_to_come_follow_fits_rule() -> None:
    """checkpoints_to_come against Trainer.fit's rule played step by step: a write at every
    multiple of ``every``, after the first step ``every_s`` past the last write, and at the end."""

    def played(step, total, every, step_s, every_s, since):
        writes, waited = 1, since  # the last write
        for k in range(step + 1, total + 1):
            waited += step_s
            if k % every == 0 or (every_s is not None and waited >= every_s - 1e-9):
                writes, waited = writes + 1, 0.0
        return writes

    rng = np.random.default_rng(0)
    for _ in range(3000):
        total = int(rng.integers(1, 400))
        case = (
            int(rng.integers(0, total + 1)),
            total,
            int(rng.integers(1, 300)),
            float(rng.choice([0.07, 0.25, 1.0])),
            [None, 0.5, 3.0, 60.0][int(rng.integers(4))],
            float(rng.uniform(0, 70)),
        )
        assert checkpoints_to_come(*case) == played(*case), case
    assert checkpoints_to_come(100, 300, 250, 0.3, 30.0, 0.0) == 3  # 30 s later (step 200), at step 250, the end


def test_fit_counts_the_checkpoint_writes_to_come(monkeypatch, tmp_path) -> None:
    """Once fit has written a checkpoint, Progress.eta_s holds the writes still to come at that
    write's time (fake clock: steps of 1 s, writes of 3 s, every 40 steps and at the end)."""
    cfg = preset_config("fast", steps=100, rays_per_view=64, unseen_rays=64, checkpoint_every=40)
    cfg = replace(cfg, model=replace(cfg.model, num_planes=4), loss=replace(cfg.loss, recon_only_fraction=0.0))
    trainer = Trainer(synthetic_scene(num_views=3, width=32, height=24), cfg)

    clock = FakeClock()

    def fake_step(self: Trainer) -> dict[str, float]:
        clock.now += 1.0
        self.step += 1
        return {"mse": 0.0}

    def fake_save(self: Trainer, path) -> None:
        clock.now += 3.0

    monkeypatch.setattr(cmc.method.training, "time", clock)
    monkeypatch.setattr(Trainer, "train_step", fake_step)
    monkeypatch.setattr(Trainer, "save_checkpoint", fake_save)
    seen = {}
    result = trainer.fit(
        on_progress=lambda p: seen.setdefault(p.step, p.eta_s),
        checkpoint_path=tmp_path / "c.pt",
        checkpoint_seconds=None,
    )
    assert seen[30] == pytest.approx(70.0)  # no write measured yet: the steps alone
    assert seen[50] == pytest.approx(50.0 + 2 * 3.0)  # the write at step 80 and the last one
    assert seen[100] == pytest.approx(3.0)  # the last write, after the last step
    assert result.checkpoint_write_s == pytest.approx(3.0)

    # an earlier run's write time (worker.pipeline.JobPace) counts them before this run wrote one
    trainer.step, seen = 0, {}
    trainer.fit(
        on_progress=lambda p: seen.setdefault(p.step, p.eta_s),
        checkpoint_path=tmp_path / "d.pt",
        checkpoint_seconds=None,
        checkpoint_write_s=2.0,
    )
    assert seen[30] == pytest.approx(70.0 + 3 * 2.0)  # steps 40 and 80, the end, at 2 s each
    assert seen[50] == pytest.approx(50.0 + 2 * 3.0)  # this run's own write time from step 40 on
    # without a checkpoint path there are no writes to count
    trainer.step, seen = 0, {}
    trainer.fit(on_progress=lambda p: seen.setdefault(p.step, p.eta_s), checkpoint_write_s=2.0)
    assert seen[30] == pytest.approx(70.0)


def test_a_jobs_eta_keeps_the_builds_pace_until_its_second_step() -> None:
    """worker.pipeline's train phase: the first step an attempt trains pays one-off costs (3 s here,
    against the 1 s the build's pace predicts); the ETA it writes then keeps the predicted step time
    for the steps to come (not 99 x 3 s), and from the second step on the measured one."""
    from cmc.method.training import Progress
    from worker.pipeline import JobPace, _TrainPhase

    writes: list[float] = []
    phase = _TrainPhase.__new__(_TrainPhase)  # only what _on_progress reads
    phase.hb = SimpleNamespace(set=lambda **fields: writes.append(fields["eta_seconds"]))
    phase.resumed_from, phase.preview_s, phase.preview_steps, phase.stats = 0, 0.0, [], {}
    phase.pace = JobPace(REFERENCE_POSES_S, REFERENCE_STEP_S)  # no earlier job: the reference's cost model
    phase.step_s, phase.bake_cost, phase.bake_s = 1.0, 7.0, 5.0  # the build's pace; the preview's bake
    phase.preview_cost, phase.build_cost = 0.25 * phase.bake_cost, 20.5
    eta = TrainingETA(100, first_full=30, full_cost_ratio=1.0)
    eta.record(0, 3.0)
    phase._on_progress(Progress(1, 100, {}, 3.0, eta.remaining_s(1)))
    assert writes[-1] == pytest.approx(99 * 1.0 + 5.0)
    eta.record(1, 1.2)
    phase._on_progress(Progress(2, 100, {}, 4.2, eta.remaining_s(2)))
    assert writes[-1] == pytest.approx(98 * 1.2 + 5.0)


def test_a_jobs_train_phase_counts_the_build_and_bakes_as_the_latest_job_measured_them() -> None:
    """worker.pipeline's train phase with an earlier job's pace (JobPace): before the build, the
    build, the steps and both bakes take what that job measured; during the build, its pace
    scales that job's step time (a GPU's steps gain more than its build: the reference's model in
    steps would be far off there); once a preview is baked, the final bake still takes that job's
    (the preview's bake, times its texels, predicts it only without such a job)."""
    from worker.pipeline import JobPace, _TrainPhase

    phase = _TrainPhase.__new__(_TrainPhase)
    phase.pace = JobPace(5.0, step_s=0.05, build_s=6.0, bake_s=8.0, preview_bake_s=2.0)  # a GPU worker's
    phase.step_s, phase.bake_s, phase.stats, phase.preview_steps = 0.05, None, {}, [0, 30]
    phase.bake_cost, phase.preview_cost, phase.build_cost = 15.7, 15.7 / 4, 20.5
    # two previews to come, each as that job's preview bake
    assert phase._eta(300, built=False) == pytest.approx(6.0 + 300 * 0.05 + 8.0 + 2 * 2.0)
    assert phase.pace.step_s_from_build(9.0, 504, 378) == pytest.approx(0.075)  # a build 1.5x slower
    phase.preview_steps = [30]  # the first baked: one to come
    phase.stats["preview"], phase.bake_s = {"bake_seconds": 1.5}, phase.pace.final_bake_from_preview(1.5)
    assert phase._eta(300) == pytest.approx(300 * 0.05 + 8.0 + 2.0)
    phase.preview_steps = []  # both baked: the final bake to come
    assert phase._eta(300) == pytest.approx(300 * 0.05 + 8.0)
    assert JobPace(5.0, 0.05).final_bake_from_preview(1.5) == pytest.approx(1.5 / PREVIEW_TEXEL_SCALE**2)


def test_cost_model_follows_the_config() -> None:
    fast = preset_config("fast")
    # each MPI renders its own photo's 6144 rays and half of each other photo's
    assert input_rays_per_mpi(fast, 3) == 2 * 6144 and input_rays_per_mpi(fast, 5) == 3 * 6144
    # the rays' ratio, each full-loss ray at FULL_RAY_COST (fern's measured median with 2048
    # unseen rays, 0.97, over their rays' ratio)
    assert full_cost_ratio(fast, 3) == pytest.approx(FULL_RAY_COST * (2 * 6144 + 1024) / (2 * 6144))
    with_2048 = replace(fast, unseen_rays=2048)
    assert full_cost_ratio(with_2048, 3) == pytest.approx(0.97, abs=0.005)
    paper = preset_config("paper")  # every MPI every ray
    assert full_cost_ratio(paper, 3) == pytest.approx(FULL_RAY_COST * (3 * 1024 + 1024) / (3 * 1024))
    silent = replace(fast, loss=replace(fast.loss, lambda_ac=0.0, lambda_dc=0.0))
    assert full_cost_ratio(silent, 3) == FULL_RAY_COST  # no unseen poses are rendered then
    for steps in (1, 7, 10, 400):
        cfg = preset_config("fast", steps=steps)
        # the first step that Trainer.compute_losses runs with the full loss
        assert first_full_step(cfg) == next(s for s in range(steps + 1) if s >= cfg.loss.recon_only_fraction * steps)
    assert bake_steps(504, 378, 1.2, 2 * 6144) == pytest.approx(15.7, abs=0.05)  # fern, the fast preset
    assert bake_steps(504, 378, 1.2, 6144) == pytest.approx(3 * bake_steps(504, 378, 1.2, 3 * 6144))
    assert bake_steps(1008, 756, 1.2, 6144) == pytest.approx(4 * bake_steps(504, 378, 1.2, 6144))
    fern_build = 20.5  # fern's build in the reference's steps
    assert build_steps(504, 378) == pytest.approx(fern_build) and build_steps(252, 189) == pytest.approx(fern_build / 4)
    assert build_steps(1008, 756) == pytest.approx(fern_build)  # the sweep's grid is capped: no more than fern's
    # a machine that builds fern's model in twice the reference's time trains twice as slowly
    reference_build_s = fern_build * REFERENCE_STEP_S
    assert reference_build_s == pytest.approx(8.6, abs=0.05)  # the reference jobs' builds: 8.3-8.7 s
    assert step_s_from_build(2 * reference_build_s, 504, 378) == pytest.approx(2 * REFERENCE_STEP_S)
    # a quarter of the pixels, a quarter of the sweep
    assert step_s_from_build(fern_build, 252, 189) == pytest.approx(4.0)
    assert final_bake_s(7.0, 1.5) == 10.5  # no preview yet: the bake in steps
    assert final_bake_s(7.0, 1.5, 12.0) == final_bake_s(7.0, 0.06, 12.0) == 12.0  # the preview's measured bake


def test_a_jobs_first_estimate_is_the_latest_ready_jobs_of_its_kind(tmp_path) -> None:
    """worker.pipeline.JobPace: before a job has measured anything, its stages take what the
    latest ready job of its kind measured (the same size limit; the same preset for training, the
    same kind of cameras for the poses), else the reference run's pace; an unreadable store or
    a job without measured steps falls back too."""
    from cmc.method.eta import reference_training_s
    from service.db.scenes import SceneStore
    from worker.pipeline import JobPace

    store = SceneStore(f"sqlite:///{tmp_path / 'cmc.db'}")
    fast = {"preset": "fast", "resolution": 504, "steps": 100}
    measured = {
        "poses": {"seconds": 5.0},
        "train": {
            "build_seconds": 8.0,
            "step_seconds": 0.3,
            "bake_seconds": 5.0,
            "checkpoint_seconds": 1.5,
            "phase_step_seconds": [0.25, 0.375],
        },
        "preview": {"bake_seconds": 1.0},
    }
    new, _ = store.create("o", fast, ["a.jpg"], ["00.jpg"], False)
    reference = JobPace(REFERENCE_POSES_S, REFERENCE_STEP_S)
    assert JobPace.of(store, new) == reference  # nothing finished yet
    assert reference.training_s(fast) == pytest.approx(reference_training_s(100))

    finished_job(store, fast, measured)
    finished_job(store, {**fast, "resolution": 1008}, {**measured, "poses": {"seconds": 50.0}})  # other photos
    finished_job(store, {**fast, "preset": "paper"}, {**measured, "train": {**measured["train"], "step_seconds": 9}})
    pace = JobPace.of(store, new)
    assert pace == JobPace(5.0, 0.3, 8.0, 5.0, 1.0, 1.5, 1.5)
    assert pace.training_s(fast) == pytest.approx(8.0 + 100 * 0.3 + 6.0)
    assert pace.training_s({**fast, "steps": None}) == pytest.approx(8.0 + preset_config("fast").steps * 0.3 + 6.0)
    assert pace.training_s(fast, previews=2) == pytest.approx(8.0 + 100 * 0.3 + 5.0 + 2 * 1.0)  # each as measured

    finished_job(store, fast, {**measured, "poses": {"seconds": 7.0}}, has_cameras=True)  # the app's cameras
    assert JobPace.of(store, new).poses_s == 5.0
    with_cameras, _ = store.create("o", fast, ["a.jpg"], ["00.jpg"], True)
    assert JobPace.of(store, with_cameras).poses_s == 7.0
    # the latest job of the kind counts; one that measured no steps (resumed at its last) does not
    finished_job(store, fast, {**measured, "train": {**measured["train"], "step_seconds": 0.5}})
    finished_job(store, fast, {"poses": {"seconds": 4.0}, "train": {"build_seconds": 8.0, "bake_seconds": 5.0}})
    assert JobPace.of(store, new) == JobPace(4.0, 0.5, 8.0, 5.0, 1.0, 1.5, 1.5)

    # a build that takes twice the measured job's predicts twice its step time
    assert pace.step_s_from_build(16.0, 504, 378) == pytest.approx(0.6)
    assert reference.step_s_from_build(16.0, 504, 378) == pytest.approx(step_s_from_build(16.0, 504, 378))
    no_preview = {k: v for k, v in measured.items() if k != "preview"}
    finished_job(store, {**fast, "preset": "paper"}, no_preview)
    paper, _ = store.create("o", {**fast, "preset": "paper"}, ["a.jpg"], ["00.jpg"], False)
    assert JobPace.of(store, paper) == JobPace(5.0, 0.3, 8.0, 5.0, None, 1.5, 1.5)

    class Unreadable:
        def latest_ready(self, limit: int):
            raise ConnectionError("the database is down")

    assert JobPace.of(Unreadable(), new) == reference
    store.close()
