"""The Celery worker: ``celery -A worker.celery_app worker -Q cpu`` (pose estimation) or
``-Q gpu`` (training and baking); settings from ``CMC_*`` variables (service.settings).

Delivery guarantees: tasks are acknowledged after they finish (``acks_late``) and given back
when their worker process dies (``reject_on_worker_lost``); each worker takes one message at a
time (prefetch 1); Redis' visibility timeout is longer than the longest job, so a running job
is never handed out twice while its worker lives. A worker that dies is detected sooner by the
job lease in the database: every worker runs the reaper (``requeue_stale_jobs``) at start and
every ``lease_seconds / 2``, and the next worker resumes from the last checkpoint. A message
delivered twice is harmless: claiming a job in the database is atomic.

Webhooks: ``celery -A worker.celery_app worker -Q webhooks`` runs the ``cmc.webhook`` task, one
try of a delivery that re-sends itself with a countdown after a failure (worker.webhooks); the
reaper also re-sends deliveries whose message was lost.

The reaper's background thread also sends the job messages that are due
(``worker.pipeline.deliver``: the store's outbox) every ``DELIVER_EVERY_SECONDS``, so a message
that could not be sent while Redis was down goes out as soon as it is back.

Shutdown: a warm shutdown (SIGTERM to the main process, what ``docker stop`` sends) is forwarded
to the pool's processes as SIGTERM; a pool process running a job stops it at the next training
step (or COLMAP checkpoint), writes the checkpoint and hands the job on (its message is due
again), so the main process exits within seconds and the next worker resumes from that step.
A pool process with no job exits on SIGTERM as before.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
import time
from collections.abc import Callable

import billiard.process
from celery import Celery
from celery.signals import worker_init, worker_ready, worker_shutting_down

from cmc.data.images import MemoryBudget
from service.db.scenes import SceneStore
from service.jobs import TASK_NAMES, CeleryJobQueue, task_queues
from service.settings import Settings, load_settings
from service.storage import StorageError, open_storage
from worker.context import JobContext
from worker.pipeline import DELIVER_EVERY_SECONDS, deliver, requeue_stale_jobs, run_job, run_video
from worker.webhooks import deliver as deliver_webhook
from worker.webhooks import resend_overdue

log = logging.getLogger("cmc.worker")


def create_celery(settings: Settings) -> Celery:
    app = Celery("cmc-worker", broker=settings.broker_url or "redis://127.0.0.1:6379/0")
    longest = max(settings.poses_time_limit, settings.train_time_limit)
    queues = task_queues(settings.cpu_queue, settings.gpu_queue, settings.webhook_queue)
    app.conf.update(
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        worker_prefetch_multiplier=1,
        broker_transport_options={"visibility_timeout": int(longest + 3600)},
        broker_connection_retry_on_startup=True,
        task_routes={TASK_NAMES[task]: {"queue": queue} for task, queue in queues.items()},
        task_default_queue=settings.cpu_queue,
        task_ignore_result=True,
        worker_hijack_root_logger=False,
        worker_cancel_long_running_tasks_on_connection_loss=False,
    )
    return app


settings = load_settings(mode="celery")
app = create_celery(settings)
decode_memory = MemoryBudget(settings.decode_memory_bytes)  # photo decodes of pose estimation
_ctx: JobContext | None = None  # one per worker process, made after the fork
_ctx_lock = threading.Lock()  # the webhook worker runs tasks in threads
_shutdown = threading.Event()  # set: the job running in this process checkpoints and stops


def new_context() -> JobContext:
    queue = CeleryJobQueue.from_settings(settings)
    store = SceneStore(settings.resolved_database_url, migrate=settings.migrate_on_start)
    return JobContext(store, open_storage(settings), queue, settings, shutdown=_shutdown, decode_memory=decode_memory)


def context() -> JobContext:
    global _ctx
    with _ctx_lock:
        return _context()


def _context() -> JobContext:
    global _ctx
    if _ctx is None:
        _ctx = new_context()
    return _ctx


def _running(work: Callable[[], str]) -> str:
    """Run a job; in a prefork pool process, SIGTERM meanwhile stops it cleanly (``_shutdown``)
    instead of ending the process (billiard's handler, put back after)."""
    in_pool = billiard.process.current_process().name != "MainProcess"
    previous = None
    if in_pool and threading.current_thread() is threading.main_thread():
        _shutdown.clear()  # a stop of an earlier job (e.g. billiard's hard time limit) is not this one's
        previous = signal.signal(signal.SIGTERM, lambda *_: _shutdown.set())
    try:
        return work()
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


# Hard limits are a backstop: the pipeline stops a phase at its own (soft) limit first, cleanly.
@app.task(name=TASK_NAMES["poses"], time_limit=settings.poses_time_limit + 300)
def poses_task(scene_id: str) -> str:
    return _running(lambda: run_job(context(), scene_id, "poses"))


@app.task(name=TASK_NAMES["train"], time_limit=settings.train_time_limit + 300)
def train_task(scene_id: str) -> str:
    return _running(lambda: run_job(context(), scene_id, "train"))


@app.task(name=TASK_NAMES["video"], time_limit=3600)
def video_task(scene_id: str, path: str) -> str:
    return run_video(context(), scene_id, path)


@app.task(name=TASK_NAMES["webhook"], time_limit=settings.webhook_timeout_seconds + 60)
def webhook_task(delivery_id: str) -> str:
    """One try of a webhook delivery; after a failed try, the next one is sent with its backoff."""
    ctx = context()
    delay = deliver_webhook(ctx.store, settings, delivery_id)
    if delay is None:
        return "done"
    ctx.queue.submit_webhook(delivery_id, delay)
    return f"retry in {delay:.1f} s"


# -- background: the reaper and the outbox's sender (main process) --------------------------------


def _background(stop: threading.Event) -> None:
    ctx = new_context()
    next_reap = 0.0
    while True:
        try:
            if time.monotonic() >= next_reap:
                next_reap = time.monotonic() + settings.lease_seconds / 2
                requeue_stale_jobs(ctx)
                resend_overdue(ctx)
            deliver(ctx)
        except Exception:
            log.warning("background pass failed", exc_info=True)
        if stop.wait(DELIVER_EVERY_SECONDS):
            return


_background_stop = threading.Event()


@worker_init.connect
def _check_storage(**_: object) -> None:
    """Stop at start, saying why, when the artifact storage cannot be written (a bucket out of
    reach), rather than fail every job later."""
    try:
        open_storage(settings)
    except StorageError as e:
        log.critical("%s", e)
        raise SystemExit(f"cmc worker: {e}") from None


@worker_ready.connect
def _start_background(**_: object) -> None:
    threading.Thread(target=_background, args=(_background_stop,), name="cmc-background", daemon=True).start()


# -- shutdown: forwarded to the job ---------------------------------------------------------------


@worker_shutting_down.connect
def _on_shutdown(**_: object) -> None:
    """Main process, warm or cold shutdown: stop the background thread, and the running jobs:
    this process's own (solo and thread pools) and, by SIGTERM, the prefork pool's."""
    _background_stop.set()
    _shutdown.set()
    for child in billiard.process.active_children():
        try:
            os.kill(child.pid, signal.SIGTERM)
        except (ProcessLookupError, TypeError):  # gone already, or not started
            pass
