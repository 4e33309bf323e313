"""The embedded job runner of ``cmc serve``: the same pipeline in a thread of the API process.

No Redis, no Celery: jobs run one at a time, in the order sent. It implements
:class:`service.jobs.JobQueue`, so the API sends jobs to it exactly as it would to Celery.
At start it re-runs every unfinished job of the database (a previous process stopped while
they were queued or running; training resumes from its checkpoint). At shutdown it asks the
running job to checkpoint and stop, leaving it for the next start. One ``cmc serve`` process
per data folder. Webhooks go out from a thread of their own (:class:`worker.webhooks.WebhookSender`),
never queued behind a job; deliveries still pending at a restart are sent by the next start.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable

from cmc.data.images import MemoryBudget
from service.db.rows import Phase
from service.db.scenes import SceneStore
from service.settings import Settings
from service.storage import Storage
from worker.context import JobContext
from worker.pipeline import run_job, run_video
from worker.webhooks import WebhookSender

log = logging.getLogger("cmc.worker")


class EmbeddedRunner:
    def __init__(self, store: SceneStore, storage: Storage, settings: Settings, decode_memory: MemoryBudget):
        self.ctx = JobContext(store, storage, self, settings, decode_memory=decode_memory)
        self._jobs: queue.Queue[tuple[str, Callable[[], object]] | None] = queue.Queue()
        self._thread = threading.Thread(target=self._loop, name="cmc-embedded-runner", daemon=True)
        self.webhooks = WebhookSender(store, settings)

    # -- JobQueue ------------------------------------------------------------------------------

    def submit(self, scene_id: str, phase: Phase) -> None:
        self._jobs.put((f"{scene_id} {phase}", lambda: run_job(self.ctx, scene_id, phase)))

    def submit_video(self, scene_id: str, path: str) -> None:
        self._jobs.put((f"{scene_id} video {path}", lambda: run_video(self.ctx, scene_id, path)))

    def submit_webhook(self, delivery_id: str, countdown: float = 0.0) -> None:
        del delivery_id, countdown  # the sender reads what is due from the database
        self.webhooks.wake()

    def depth(self) -> dict[str, int]:
        return {"embedded": self._jobs.qsize()}

    def ping(self) -> None:
        if not self._thread.is_alive():
            raise RuntimeError("the embedded job runner is not running")

    # -- life cycle ----------------------------------------------------------------------------

    def start(self) -> None:
        unfinished = self.ctx.store.unfinished_jobs()
        for rec in unfinished:
            if rec.lease_owner is not None:  # held by the previous process of this data folder
                self.ctx.store.release(rec.id, rec.lease_owner)
            self.submit(rec.id, rec.phase)  # type: ignore[arg-type]
        videos = self.ctx.store.videos.unfinished()
        for video in videos:
            if video.lease_owner is not None:
                self.ctx.store.videos.release(video.scene_id, video.path, video.lease_owner)
            self.submit_video(video.scene_id, video.path)
        if unfinished or videos:
            log.warning("resuming %d unfinished job(s), %d video(s) from the last run", len(unfinished), len(videos))
        self._thread.start()
        self.webhooks.start()

    def stop(self, timeout: float = 30.0) -> None:
        """Checkpoint and stop the running job (it stays queued for the next start)."""
        self.ctx.shutdown.set()
        self._jobs.put(None)
        self._thread.join(timeout)
        self.webhooks.stop()

    def _loop(self) -> None:
        while True:
            item = self._jobs.get()
            if item is None or self.ctx.shutdown.is_set():
                return
            name, work = item
            try:
                work()
            except Exception:  # never let one job end the runner (e.g. the database blinked)
                log.exception("job %s: runner error", name)
