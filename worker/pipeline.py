"""The job pipeline: pose estimation, then training and baking. Shared by the Celery tasks
(``worker.celery_app``) and the embedded runner of ``cmc serve`` (``worker.embedded``).

A job runs in two phases, each a separate task so GPU workers only train and bake:

* ``poses`` (CPU queue): :func:`cmc.poses.estimate_poses` on the uploads, or
  :func:`cmc.poses.poses_from_client` when the upload came with a cameras file; writes the
  scene folder ``{id}/scene/`` and sends the ``train`` phase.
* ``train`` (GPU queue): trains with checkpoints in ``{id}/checkpoint.pt`` (resumed when a
  previous worker died), bakes previews ``{id}/preview-{step}/`` (``Settings.preview_at``, at half the
  texel resolution; the API serves the latest until the scene is ready, also while a resumed job trains
  on), bakes ``{id}/baked/``, marks the scene ready and removes the previews.

Phases work on local copies (:meth:`Storage.reading`, :meth:`Storage.writing`: the stored files
themselves on local storage, downloads and uploads with S3) and publish each result whole.

While a phase runs, a heartbeat thread renews the job's lease, writes progress to the scene
record and reads the cancel flag every ``heartbeat_seconds``, so DELETE stops a job within
seconds; the phase's time limit is enforced by the same thread. Work stops cooperatively at
the next training step (or COLMAP checkpoint), after a checkpoint is written. A process that
shuts down (``JobContext.shutdown``) stops its job the same way at once and hands it on: the
job's message is due again.

Messages to the queue go through the store's outbox (:func:`deliver`): the statement that makes
a message necessary records it as due, and it is cleared once the broker took it. A message the
broker did not take stays due; the Celery workers send due messages every
``DELIVER_EVERY_SECONDS``, so a Redis outage delays a job by the outage, not by the reaper's
``requeue_after_seconds``.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from service.db.rows import Phase, SceneRecord
from service.errors import ErrorCode
from service.layout import ClientNames, SceneLayout
from service.settings import Settings
from worker.context import JobContext
from worker.webhooks import kick as kick_webhooks

if TYPE_CHECKING:
    from collections.abc import Callable

    from cmc.config import TrainConfig
    from cmc.method.training import Progress, Trainer

log = logging.getLogger("cmc.worker")

StopReason = Literal["cancelled", "lease_lost", "time_limit", "shutdown"]

WAITING = "waiting for a worker"  # the status detail of a job between workers
QUEUE_DOWN = "waiting for a worker: the job queue cannot be reached; the job is sent as soon as it is back"
SEND_RETRY_SECONDS = 5.0  # a message taken for sending is due again after this unless it was sent
DELIVER_EVERY_SECONDS = 1.0  # how often Celery workers send due messages (worker.celery_app)


class JobStopped(Exception):
    """The heartbeat asked the phase to stop (see ``_Heartbeat.reason``)."""


class _Heartbeat:
    """Renews the lease, writes progress and watches for cancel / time limit / shutdown."""

    def __init__(self, ctx: JobContext, scene_id: str, time_limit: float):
        self.ctx, self.scene_id = ctx, scene_id
        self.deadline = time.monotonic() + time_limit
        self.reason: StopReason | None = None
        self._stop = threading.Event()
        self._done = threading.Event()
        self._lock = threading.Lock()
        self._pending: dict[str, Any] = {}
        self._thread = threading.Thread(target=self._run, name=f"heartbeat-{scene_id[:8]}", daemon=True)

    def __enter__(self) -> _Heartbeat:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._done.set()
        self._thread.join()

    def set(self, **fields: Any) -> None:
        """Queue fields for the next heartbeat write (progress, status, eta_seconds, detail...)."""
        with self._lock:
            self._pending.update(fields)

    def flush(self) -> None:
        """Write pending fields now (before a phase ends)."""
        self._beat()

    def should_stop(self) -> bool:
        if self.ctx.shutdown.is_set():  # at once, not at the next beat
            self._halt("shutdown")
        return self._stop.is_set()

    def check(self) -> None:
        if self._stop.is_set():
            raise JobStopped(self.reason or "stopped")

    def _halt(self, reason: StopReason) -> None:
        if self.reason is None:
            self.reason = reason
        self._stop.set()

    def _beat(self) -> None:
        with self._lock:
            fields, self._pending = self._pending, {}
        s = self.ctx.settings
        hb = self.ctx.store.heartbeat(self.scene_id, self.ctx.worker_id, s.lease_seconds, **fields)
        if hb.cancel_requested:  # first: a cancelled job's lease is void too
            self._halt("cancelled")
        elif not hb.holds_lease:
            self._halt("lease_lost")
        elif time.monotonic() > self.deadline:
            self._halt("time_limit")
        elif self.ctx.shutdown.is_set():
            self._halt("shutdown")

    def _run(self) -> None:
        while not self._done.wait(self.ctx.settings.heartbeat_seconds):
            try:
                self._beat()
            except Exception:  # the database may blink; the lease is generous
                log.warning("heartbeat of %s failed", self.scene_id, exc_info=True)


def run_job(ctx: JobContext, scene_id: str, phase: Phase) -> str:
    """Run one phase of a job if it can be claimed. Returns what happened (for logs):
    'skipped' (finished, cancelled, another phase, or held by a live worker), 'done',
    'failed', 'cancelled', 'stopped' (lease lost or shutdown: the job stays queued)."""
    rec = ctx.store.claim(scene_id, phase, ctx.worker_id, ctx.settings.lease_seconds)
    if rec is None:
        log.info("job %s phase %s: nothing to do", scene_id, phase)
        return "skipped"
    s = ctx.settings
    limit = s.poses_time_limit if phase == "poses" else s.train_time_limit
    outcome = "done"
    with _Heartbeat(ctx, scene_id, limit) as hb:
        try:
            if phase == "poses":
                _estimate_poses(ctx, rec, hb)
            else:
                _train_and_bake(ctx, rec, hb)
        except Exception as e:
            code = failure_code(e)
            if code is not None:
                ctx.store.fail(scene_id, code, ClientNames(rec.upload_files, rec.upload_names).in_text(str(e)))
                outcome = "failed"
            elif hb.reason is None:
                log.error("job %s phase %s crashed:\n%s", scene_id, phase, traceback.format_exc())
                ctx.store.fail(scene_id, ErrorCode.internal_error, f"{type(e).__name__}: {e}")
                outcome = "failed"
            elif hb.reason == "time_limit":
                ctx.store.fail(scene_id, ErrorCode.time_limit_exceeded, f"{phase} took longer than {limit:.0f} s")
                outcome = "failed"
            elif hb.reason == "shutdown":  # checkpointed: the next worker (or start) resumes it
                ctx.store.release(scene_id, ctx.worker_id, resend=True, detail=WAITING)
                deliver(ctx, scene_id)
                outcome = "stopped"
            else:  # cancelled; or lease lost: the reaper re-queued it, or another worker has it
                ctx.store.release(scene_id, ctx.worker_id)
                outcome = "cancelled" if hb.reason == "cancelled" else "stopped"
    after = ctx.store.get(scene_id, include_deleted=True)
    if after is None or after.deleted:
        ctx.storage.delete_scene(scene_id)  # anything written after the API removed the data
    kick_webhooks(ctx, scene_id)  # a ready or failed scene recorded its event with the change
    log.info("job %s phase %s: %s", scene_id, phase, outcome)
    return outcome


def failure_code(e: BaseException) -> ErrorCode | None:
    """The code a job fails with for exception ``e`` (the first matching row of the table below),
    or None: a stop (cancel, lease lost, time limit, shutdown) or a bug (internal_error)."""
    from cmc.errors import CameraError, PoseEstimationError, SceneError

    table: tuple[tuple[type[BaseException], ErrorCode], ...] = (
        (PoseEstimationError, ErrorCode.pose_estimation_failed),
        (CameraError, ErrorCode.invalid_cameras),
        (SceneError, ErrorCode.invalid_images),  # photos, and a scene folder they made
        (FloatingPointError, ErrorCode.training_failed),  # training diverged
    )
    return next((code for kind, code in table if isinstance(e, kind)), None)


# Share of pose estimation done when a stage starts, for the status' progress (SfM's stages report
# nothing finer): the median stage times on fern's three 12 MP phone photos (bench/reports/history/sift_octave.md:
# intake 0.97 s, SIFT 1.14 s, matching 0.21 s, mapping 0.05 s, near/far 0.02 s of 2.45 s).
POSE_STAGE_PROGRESS = {
    "intake": 0.0,
    "features": 0.4,
    "matching": 0.86,
    "mapping": 0.95,
    "triangulation": 0.95,
    "near_far": 0.97,
    "write": 0.99,
}


# How many of the latest ready jobs a new job looks through for one of its kind (JobPace.of).
PACE_LOOKBACK = 20


@dataclass(frozen=True)
class JobPace:
    """What a job's stages take before the job has measured them, in seconds: as the latest ready
    job of its kind measured them on this deployment (its ``stats``), else as the reference run
    (:mod:`cmc.method.eta`). ``poses_s``: the pose phase (from a job whose photos had the same
    size limit and came with cameras or without, as this one); ``step_s``: a training step;
    ``build_s``, ``bake_s``, ``preview_bake_s``: the model build, the final bake and the preview's
    (from a job of the same preset and size limit; None: the reference's cost model, in training
    steps, and for the preview also when that job baked none); ``checkpoint_s``: that job's last
    checkpoint write, at which training counts the writes to come until it has made one (None:
    not before then); ``full_cost_ratio``: that job's full-loss steps' mean time over its
    reconstruction-only ones', at which training predicts the former from the latter until it
    has run one (None: the cost model of :func:`cmc.method.eta.full_cost_ratio`). ``step_s`` is
    the steps' mean with the checkpoint writes among them, as a job's training time holds them."""

    poses_s: float
    step_s: float
    build_s: float | None = None
    bake_s: float | None = None
    preview_bake_s: float | None = None
    checkpoint_s: float | None = None
    full_cost_ratio: float | None = None

    @staticmethod
    def of(store: Any, rec: SceneRecord) -> JobPace:
        """The pace for ``rec`` from ``store``'s latest ready jobs; the reference's when none is
        of its kind or the store cannot say (an estimate never fails a job)."""
        from cmc.method.eta import REFERENCE_POSES_S, REFERENCE_STEP_S

        poses_s, train = None, None
        try:
            latest = store.latest_ready(PACE_LOOKBACK)
        except Exception:
            log.warning("job %s: no earlier job's pace (the store did not answer)", rec.id, exc_info=True)
            latest = []
        for r in latest:
            if r.options.get("resolution") != rec.options.get("resolution"):
                continue
            if poses_s is None and r.has_cameras == rec.has_cameras:
                poses_s = r.stats.get("poses", {}).get("seconds")
            t = r.stats.get("train", {})
            if train is None and r.options.get("preset") == rec.options.get("preset") and "step_seconds" in t:
                preview = r.stats.get("preview", {}).get("bake_seconds")
                recon, full = t.get("phase_step_seconds") or (None, None)
                ratio = full / recon if recon and full else None
                train = (
                    t["step_seconds"],
                    t["build_seconds"],
                    t["bake_seconds"],
                    preview,
                    t.get("checkpoint_seconds"),
                    ratio,
                )
        return JobPace(poses_s or REFERENCE_POSES_S, *(train or (REFERENCE_STEP_S,)))

    def training_s(self, options: dict[str, Any], previews: int = 1) -> float:
        """Seconds of the model build, training and baking (``previews`` previews too, as the
        measured job's preview bake; the reference's estimate counts none) for a job with ``options``."""
        from cmc.config import preset_config
        from cmc.method.eta import reference_training_s

        steps = options.get("steps") or preset_config(options["preset"]).steps
        if self.build_s is None or self.bake_s is None:
            return reference_training_s(steps, self.step_s)
        return self.build_s + steps * self.step_s + self.bake_s + previews * (self.preview_bake_s or 0.0)

    def final_bake_from_preview(self, preview_s: float) -> float:
        """Seconds the final bake is expected to take after a preview bake of ``preview_s``: as
        the measured job's final bake, else by texels (the preview has a quarter). A preview
        bakes in about 1.5 s on fern, so its own noise, times four or more, would outweigh what
        it says of this job's pace (bench/job_timeline.md)."""
        from cmc.serving.baking import PREVIEW_TEXEL_SCALE

        return self.bake_s if self.bake_s is not None else preview_s / PREVIEW_TEXEL_SCALE**2

    def step_s_from_build(self, build_s: float, width: int, height: int) -> float:
        """Seconds per training step for a model build that takes ``build_s`` seconds on this
        worker: the measured job's step time in the ratio of the two builds (the job's own device
        and load show in its build first), else the reference's cost model
        (:func:`cmc.method.eta.step_s_from_build`)."""
        from cmc.method.eta import step_s_from_build

        if self.build_s is None or self.build_s <= 0:
            return step_s_from_build(build_s, width, height)
        return self.step_s * build_s / self.build_s


def _estimate_poses(ctx: JobContext, rec: SceneRecord, hb: _Heartbeat) -> None:
    from cmc.data.datasets import CAMERAS_FILE
    from cmc.poses import PoseEstimationCancelled, PoseOptions, estimate_poses, poses_from_client

    pace = JobPace.of(ctx.store, rec)
    later_s = pace.training_s(rec.options, sum(share < 1 for share in ctx.settings.preview_at))
    t0 = time.perf_counter()

    def on_stage(stage: str) -> None:
        """Progress through the pose stages; the stages done so far give the time left in them."""
        done = POSE_STAGE_PROGRESS.get(stage, 0.0)
        left = pace.poses_s if done == 0 else (time.perf_counter() - t0) * (1 - done) / done
        hb.set(progress=done, eta_seconds=round(left + later_s, 1), detail=f"camera poses: {stage}")

    eta = round(pace.poses_s + later_s, 1)
    hb.set(status="estimating_poses", progress=0.0, eta_seconds=eta, detail="estimating camera poses")
    hb.flush()
    layout = SceneLayout(rec.id)
    options = PoseOptions(
        long_side=int(rec.options["resolution"]),
        seed=int(rec.options["seed"]),
        keep_originals=False,  # storage keeps the uploads
        max_pixels=ctx.settings.max_image_pixels,
        convention="opencv",
        decode_memory=ctx.decode_memory,
    )
    hooks = dict(should_stop=hb.should_stop, on_stage=on_stage)
    try:
        with (
            ctx.storage.reading(layout.uploads) as uploaded,
            ctx.storage.writing(layout.scene_dir, manifest=CAMERAS_FILE) as scene_dir,
        ):
            uploads = [uploaded / name for name in rec.upload_files]
            if rec.has_cameras:
                cameras = json.loads(ctx.storage.read_bytes(layout.cameras_upload))
                result = poses_from_client(uploads, cameras, scene_dir, options, **hooks)
            else:
                result = estimate_poses(uploads, scene_dir, options, **hooks)
    except PoseEstimationCancelled:
        raise JobStopped(hb.reason or "cancelled") from None
    hb.check()
    poses = {"seconds": round(time.perf_counter() - t0, 2), "timings_s": result.timings, **result.stats}
    stats = {**rec.stats, "poses": poses}
    eta = round(later_s, 1)
    waiting = dict(progress=0.0, eta_seconds=eta, detail=WAITING, stats=stats)
    if not ctx.store.advance(rec.id, ctx.worker_id, "train", "training", **waiting):
        raise JobStopped("lease_lost")
    deliver(ctx, rec.id)


def deliver(ctx: JobContext, scene_id: str | None = None) -> list[str]:
    """Send the job messages that are due (the store's outbox): every one, or one scene's.
    Returns the scenes sent. A message the broker does not take stays due, is tried again
    after ``SEND_RETRY_SECONDS``, and its job's status says why it waits; the first failure
    ends this round (the broker is down for the others too). Safe from many processes at once:
    a message is taken by one sender (and a duplicate would be dropped by the claim)."""
    sent = []
    for rec in ctx.store.due_messages(scene_id):
        taken = time.time() + SEND_RETRY_SECONDS
        if not ctx.store.take_message(rec, taken):
            continue
        try:
            ctx.queue.submit(rec.id, rec.phase)
        except Exception as e:
            log.warning("job %s: sending %s failed (%s: %s); it stays due", rec.id, rec.phase, type(e).__name__, e)
            ctx.store.message_failed(rec.id, detail=QUEUE_DOWN)
            break
        ctx.store.message_sent(rec.id, taken, detail=WAITING)
        sent.append(rec.id)
    return sent


def _train_and_bake(ctx: JobContext, rec: SceneRecord, hb: _Heartbeat) -> None:
    """Train on the scene's folder with checkpoints written in a scratch folder and each one
    published to storage, bake a preview (``Settings.preview_at``), bake into storage, make the scene ready
    once the local copies are removed (a ready scene has nothing left on this worker's disk)."""
    with ctx.storage.reading(SceneLayout(rec.id).scene_dir) as scene_dir, ctx.storage.scratch() as work:
        phase = _TrainPhase(ctx, rec, hb, scene_dir)
        phase.build()
        train_s = phase.train(work / "checkpoint.pt")
        phase.bake_final(train_s)
    phase.make_ready()


def _job_config(options: dict[str, Any], settings: Settings) -> TrainConfig:
    """The training configuration of a job: its preset with the job's steps and seed, and the
    deployment's checkpoint interval."""
    from cmc.config import preset_config

    overrides: dict[str, Any] = {"seed": int(options["seed"])}
    if options.get("steps"):
        overrides["steps"] = int(options["steps"])
    if settings.checkpoint_every:
        overrides["checkpoint_every"] = settings.checkpoint_every
    return preset_config(options["preset"], **overrides)


def _training_device(settings: Settings) -> str:
    """``settings.device``, with ``auto`` resolved to CUDA where there is a GPU."""
    import torch

    if settings.device != "auto":
        return settings.device
    return "cuda" if torch.cuda.is_available() else "cpu"


def _resume(ctx: JobContext, rec: SceneRecord, trainer: Trainer, make: Callable[[], Trainer]) -> Trainer:
    """``trainer`` at the job's stored checkpoint when there is a usable one, else a fresh one
    from ``make`` (a checkpoint torn by an old crash or of another configuration is deleted)."""
    key = SceneLayout(rec.id).checkpoint
    with ctx.storage.reading(key) as saved:
        if not saved.exists():
            return trainer
        try:
            trainer.load_checkpoint(saved)
            return trainer
        except Exception:
            log.warning("job %s: unusable checkpoint, training from step 0", rec.id, exc_info=True)
    ctx.storage.delete(key)
    return make()


class _TrainPhase:
    """One attempt at the train phase of a job: the model built (or resumed from the job's
    checkpoint), trained with progress, ETA and checkpoints, a preview baked part way, the final
    bake published and the scene made ready. ETAs count in training steps of this worker
    (``step_s`` seconds each, measured once it trains), the model build and the bakes as the
    latest ready job of the kind measured them (:class:`JobPace`), else as ``build_cost`` and
    ``bake_cost`` steps, the final bake once the preview is baked as its bake times its texels."""

    def __init__(self, ctx: JobContext, rec: SceneRecord, hb: _Heartbeat, scene_dir: Path):
        from cmc.data.datasets import load_scene_folder
        from cmc.method.eta import bake_steps, build_steps, input_rays_per_mpi
        from cmc.serving.baking import PREVIEW_TEXEL_SCALE

        self.ctx, self.rec, self.hb, self.layout = ctx, rec, hb, SceneLayout(rec.id)
        self.scene = load_scene_folder(scene_dir)
        self.cfg = cfg = _job_config(rec.options, ctx.settings)
        cams = self.scene.cameras
        rays = input_rays_per_mpi(cfg, len(self.scene))
        self.bake_cost = bake_steps(cams.width, cams.height, cfg.model.margin, rays)
        self.build_cost = build_steps(cams.width, cams.height)
        self.bake_s: float | None = None  # the final bake's seconds once a preview is baked (JobPace)
        baked = rec.stats.get("preview", {}).get("step", -1)  # the latest preview's step (a resumed job)
        steps = {math.ceil(at * cfg.steps) for at in ctx.settings.preview_at if at < 1}
        self.preview_steps = sorted(step for step in steps if step > baked)  # the previews to come
        self.pace = JobPace.of(ctx.store, rec)
        self.step_s = self.pace.step_s  # until this attempt builds its model (then: the build's pace)
        self.steps_measured = False  # whether step_s is this attempt's own measured step time
        self.preview_s = 0.0  # seconds this attempt's training spent baking previews (not steps' time)
        self.device = _training_device(ctx.settings)
        self.stats: dict[str, Any] = dict(rec.stats)
        self.preview_cost = self.bake_cost * PREVIEW_TEXEL_SCALE**2  # a bake's time is about its texels'

    def _previews_due(self, step: int) -> bool:
        """Whether a preview is due at training step ``step`` (one or more of those to come)."""
        return bool(self.preview_steps) and step >= self.preview_steps[0]

    def _final_bake_s(self) -> float:
        from cmc.method.eta import final_bake_s

        measured = self.bake_s if self.bake_s is not None else self.pace.bake_s
        return final_bake_s(self.bake_cost, self.step_s, measured)

    def _bakes_s(self) -> float:
        """Seconds of the bakes still to come (the final, and the previews to come)."""
        if not self.preview_steps:
            return self._final_bake_s()
        preview = self.pace.preview_bake_s
        each = self.preview_cost * self.step_s if preview is None else preview
        return self._final_bake_s() + len(self.preview_steps) * each

    def _eta(self, steps_left: float, built: bool = True) -> float:
        build = 0.0
        if not built:
            build = self.build_cost * self.step_s if self.pace.build_s is None else self.pace.build_s
        return round(build + steps_left * self.step_s + self._bakes_s(), 1)

    def build(self) -> None:
        """The model (plane sweeps: seconds to minutes), at the stored checkpoint when usable."""
        from cmc.kernel_cache import warm_up_kernels
        from cmc.method.training import Trainer

        cfg, hb = self.cfg, self.hb
        size = self.scene.cameras.width, self.scene.cameras.height
        # The kernels first, so that the build's pace (which predicts the steps') is not a compiler's.
        hb.set(
            status="training",
            progress=0.0,
            eta_seconds=self._eta(cfg.steps, built=False),
            detail="loading the compiled kernels (a machine's first job compiles them: up to a minute)",
        )
        hb.flush()
        t = time.perf_counter()
        warm_up_kernels()
        kernels_s = time.perf_counter() - t
        building = f"building the model ({cfg.preset} preset: plane sweep"
        hb.set(detail=building + ")")  # the ETA stays the one set above: the build has not started
        hb.flush()
        started = time.perf_counter()  # of the build under way
        build_s = 0.0  # seconds of the last build (a second follows an unusable checkpoint)

        def on_build_progress(share: float) -> None:
            """The build's share done in the detail; in the ETA the rest of it at its pace so far,
            and the steps to come at the step time that pace predicts for this machine."""
            elapsed = time.perf_counter() - started
            whole = elapsed / share
            self.step_s = self.pace.step_s_from_build(whole, *size)
            eta = round(whole - elapsed + self._eta(cfg.steps), 1)
            hb.set(eta_seconds=eta, detail=f"{building}, {100 * share:.0f} % done)")

        def make() -> Trainer:
            nonlocal started, build_s
            started = time.perf_counter()
            trainer = Trainer(self.scene, cfg, self.device, on_build_progress)
            build_s = time.perf_counter() - started
            return trainer

        self.trainer = _resume(self.ctx, self.rec, make(), make)
        self.step_s = self.pace.step_s_from_build(build_s, *size)  # until this attempt trains a second step
        self.resumed_from = resumed = self.trainer.step
        self.stats["train"] = {
            "steps": cfg.steps,
            "device": str(self.device),
            "resumed_from_step": resumed,
            "kernels_seconds": round(kernels_s, 3),
            "build_seconds": round(build_s, 3),
        }
        hb.set(
            status="training",
            progress=resumed / cfg.steps,
            eta_seconds=self._eta(cfg.steps - resumed),
            detail=f"training ({cfg.preset} preset, {cfg.steps} steps, {self.device})"
            + (f", resumed from the checkpoint of step {resumed}" if resumed else ""),
            stats=self.stats,
        )
        hb.flush()
        if self._previews_due(resumed):
            self._bake_preview()  # at step 0 (a share 0), or resumed past a preview's step
            self.preview_s = 0.0  # before training: not in its elapsed time

    def _bake_preview(self) -> None:
        """Bake the model as it is now and publish it as the scene's preview (whole, or not at
        all) in a folder of its own; the record then names it, and the one it replaces goes."""
        from cmc.serving.baking import MANIFEST, PREVIEW_TEXEL_SCALE, bake

        cfg, hb, step, ctx = self.cfg, self.hb, self.trainer.step, self.ctx
        hb.set(detail=f"baking a preview at step {step} of {cfg.steps}")
        hb.flush()
        t = time.perf_counter()
        with ctx.storage.writing(self.layout.preview(step), manifest=MANIFEST) as folder:
            bake(self.trainer.model, folder, scale=PREVIEW_TEXEL_SCALE)
        bake_s = time.perf_counter() - t
        self.preview_s += bake_s
        self.bake_s = self.pace.final_bake_from_preview(bake_s)
        self.preview_steps = [s for s in self.preview_steps if s > step]
        previous = self.stats.get("preview", {})
        replaced, first_s = previous.get("step"), previous.get("first_seconds_after_upload")
        after_upload = round(time.time() - self.rec.created_at, 1)
        self.stats["preview"] = {
            "step": step,
            "bake_seconds": round(bake_s, 2),
            "seconds_after_upload": after_upload,
            "first_seconds_after_upload": first_s if first_s is not None else after_upload,
        }
        hb.set(
            stats=self.stats, detail=f"training ({cfg.preset} preset, {cfg.steps} steps, {self.device}); preview ready"
        )
        hb.flush()
        if replaced is not None and replaced != step and hb.reason is None:  # the record names the new one
            self._delete_previews(keep=step)

    def _delete_previews(self, keep: int | None = None) -> None:
        """Remove the scene's preview folders but the one of step ``keep`` (any, when None): those
        a later preview or the final bake replaced, and any an attempt that crashed left."""
        ctx, scene = self.ctx, self.rec.id
        kept = None if keep is None else self.layout.preview(keep) + "/"
        for key in ctx.storage.list(scene):
            if self.layout.is_preview(key) and (kept is None or not key.startswith(kept)):
                ctx.storage.delete(key)

    def _on_progress(self, p: Progress) -> None:
        trained = p.step - self.resumed_from
        if trained > 1:
            self.step_s, self.steps_measured = (p.elapsed_s - self.preview_s) / trained, True
            eta = round(p.eta_s + self._bakes_s(), 1)
        else:  # the attempt's first step pays one-off costs: the steps to come keep the build's pace
            eta = self._eta(p.total - p.step)
        self.hb.set(progress=p.step / p.total, eta_seconds=eta)
        if self._previews_due(p.step):
            self._bake_preview()

    def _publish_checkpoint(self, path: Path) -> None:
        try:
            self.ctx.storage.publish(self.layout.checkpoint, path)
        except Exception:  # only for resuming: the next one may get through
            log.warning(
                "job %s: could not store the checkpoint of step %d", self.rec.id, self.trainer.step, exc_info=True
            )

    def train(self, checkpoint: Path) -> float:
        """Train to the last step (checkpoints written at ``checkpoint``); the seconds it took."""
        from cmc.method.training import TrainingCancelled

        t0 = time.perf_counter()
        try:
            result = self.trainer.fit(
                on_progress=self._on_progress,
                should_stop=self.hb.should_stop,
                checkpoint_path=checkpoint,
                resume=False,
                checkpoint_seconds=self.ctx.settings.checkpoint_seconds,
                on_checkpoint=self._publish_checkpoint,
                checkpoint_write_s=self.pace.checkpoint_s,
                full_cost_ratio=self.pace.full_cost_ratio,
            )
        except TrainingCancelled:
            raise JobStopped(self.hb.reason or "cancelled") from None
        if result.checkpoint_write_s is not None:  # the next jobs' first estimate (JobPace)
            self.stats["train"]["checkpoint_seconds"] = round(result.checkpoint_write_s, 3)
        if all(result.phase_step_s):
            self.stats["train"]["phase_step_seconds"] = [round(s, 4) for s in result.phase_step_s]
        return time.perf_counter() - t0

    def bake_final(self, train_s: float) -> None:
        """Publish the final bake (the scene is not ready yet: :meth:`make_ready`)."""
        from cmc.serving.baking import MANIFEST, bake

        ctx, hb, layout = self.ctx, self.hb, self.layout
        expected = self._final_bake_s()

        def eta_while_baking(left_s: float) -> float:
            """Seconds left, at least 0.1 until the bake is done (a small scene's MPIs bake in
            less, which would round to 0)."""
            return max(round(left_s, 1), 0.1)

        hb.set(status="baking", progress=0.0, eta_seconds=eta_while_baking(expected), detail="baking the MPIs")
        hb.flush()
        hb.check()
        t0 = time.perf_counter()

        def on_progress(done: int, total: int) -> None:
            """After each MPI: the share done, and the time left at the pace so far. The last
            MPI's atlas is encoded after its call (``bake``), about one more MPI's time."""
            units = total + 1
            left = (time.perf_counter() - t0) * (units - done) / done
            hb.set(progress=done / units, eta_seconds=eta_while_baking(left))

        with ctx.storage.writing(layout.baked(), manifest=MANIFEST) as baked:
            bake(self.trainer.model, baked, on_progress=on_progress)
        self.stats["train"].update(
            seconds_this_attempt=round(train_s, 2), bake_seconds=round(time.perf_counter() - t0, 2)
        )
        if self.steps_measured:  # the next jobs' first estimate (JobPace)
            self.stats["train"]["step_seconds"] = round(self.step_s, 4)

    def make_ready(self) -> None:
        """Make the scene ready, and drop the checkpoint and the preview the final bake replaces."""
        ctx, layout = self.ctx, self.layout
        ready = dict(progress=1.0, eta_seconds=0.0, detail=None, stats=self.stats)
        if not ctx.store.advance(self.rec.id, ctx.worker_id, "done", "ready", **ready):
            raise JobStopped("lease_lost")
        ctx.storage.delete(layout.checkpoint)  # the baked MPI is the product; the checkpoint was for resuming
        self._delete_previews()  # the API serves the final bake now


class VideoStopped(Exception):
    """The video build was cancelled (its scene deleted) or another worker holds it now."""


def run_video(ctx: JobContext, scene_id: str, path: str) -> str:
    """Render the camera-path video ``path`` (spiral, orbit, dolly) of a ready scene into
    storage, if its build record (service.db.videos) can be claimed. Progress renews the lease at
    most once a second; a cancelled or lost build stops at the next frame. Returns 'skipped',
    'done', 'failed' or 'stopped'."""
    from cmc.serving.baking import BakedScene
    from cmc.serving.video import render_path_video

    s, videos = ctx.settings, ctx.store.videos
    rec = ctx.store.get(scene_id)
    if rec is None or rec.status != "ready" or not videos.claim(scene_id, path, ctx.worker_id, s.lease_seconds):
        return "skipped"
    layout = SceneLayout(scene_id)
    mp4 = layout.video(path)
    last = [0.0]

    def on_frame(done: int, total: int) -> None:
        if time.monotonic() - last[0] > s.heartbeat_seconds or done == total:
            last[0] = time.monotonic()
            hb = videos.heartbeat(scene_id, path, ctx.worker_id, s.lease_seconds, done / total)
            if hb.cancel_requested or not hb.holds_lease:
                raise VideoStopped(f"video {path} of {scene_id} stopped")

    try:
        with ctx.storage.reading(layout.baked()) as folder:
            baked = BakedScene.load(folder)
        with ctx.storage.writing(mp4) as out:  # published only if every frame was rendered
            render_path_video(baked, path, out, on_frame=on_frame)
    except VideoStopped:
        return "stopped"  # the unfinished file was dropped with its working folder
    except Exception as e:
        log.exception("video %s of %s failed", path, scene_id)
        error = f"{type(e).__name__}: {e}"
        if videos.finish(scene_id, path, ctx.worker_id, error=error):
            ctx.store.add_event(scene_id, "video.failed", {"path": path, "error": error})
            kick_webhooks(ctx, scene_id)
        return "failed"
    if not videos.finish(scene_id, path, ctx.worker_id):
        return "stopped"  # cancelled at the last frame
    after = ctx.store.get(scene_id)
    if after is None:  # deleted while rendering
        ctx.storage.delete_scene(scene_id)
        return "done"
    ctx.store.add_event(scene_id, "video.ready", {"path": path, "url": f"/v1/scenes/{scene_id}/video?path={path}"})
    kick_webhooks(ctx, scene_id)
    return "done"


def requeue_stale_jobs(ctx: JobContext) -> list[str]:
    """Send again the jobs and video builds whose worker died (lease expired) or whose message
    was lost. Safe to run from every worker at once: each is re-queued by one of them."""
    requeued = []
    for rec in ctx.store.stale_jobs(ctx.settings.requeue_after_seconds):
        if ctx.store.requeue(rec, ctx.settings.max_attempts, detail=WAITING):
            requeued.append(rec.id)
            log.warning("job %s (%s) re-queued: its worker stopped answering", rec.id, rec.phase)
        else:
            kick_webhooks(ctx, rec.id)  # it may have failed (worker_lost)
    if requeued:
        deliver(ctx)
    for video in ctx.store.videos.stale(ctx.settings.requeue_after_seconds):  # video builds alike
        if ctx.store.videos.requeue(video, ctx.settings.max_attempts):
            log.warning("video %s of %s re-sent: its worker stopped answering", video.path, video.scene_id)
            try:
                ctx.queue.submit_video(video.scene_id, video.path)
            except Exception as e:  # the broker is down: the next round sends it (it stays stale)
                log.warning("sending video %s of %s failed: %s", video.path, video.scene_id, e)
    return requeued
