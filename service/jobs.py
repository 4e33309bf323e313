"""Sending jobs to workers: one small interface, a Celery implementation.

The API never imports worker code: Celery tasks are sent *by name* (``cmc.poses`` on the CPU
queue, ``cmc.train`` and ``cmc.serving.video`` on the GPU queue, ``cmc.webhook`` on the webhook queue)
with the scene id (and the video's path kind) or the delivery id as arguments; the database and
storage hold everything else. The embedded runner
(``worker.embedded``) implements the same interface in-process for ``cmc serve``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

from service.db.rows import Phase

if TYPE_CHECKING:
    from service.settings import Settings

TASK_NAMES: dict[str, str] = {
    "poses": "cmc.poses",
    "train": "cmc.train",
    "video": "cmc.serving.video",
    "webhook": "cmc.webhook",
}

# Task key -> the queue it goes to, by the Settings field that names the queue: the one queue map,
# read by the API when it sends (CeleryJobQueue) and by the workers' task routes (worker.celery_app).
TASK_QUEUES: dict[str, str] = {
    "poses": "cpu_queue",
    "train": "gpu_queue",
    "video": "gpu_queue",
    "webhook": "webhook_queue",
}


def task_queues(cpu_queue: str = "cpu", gpu_queue: str = "gpu", webhook_queue: str = "webhooks") -> dict[str, str]:
    """Task key -> Celery queue name, for the given queue names (:data:`TASK_QUEUES`)."""
    names = {"cpu_queue": cpu_queue, "gpu_queue": gpu_queue, "webhook_queue": webhook_queue}
    return {task: names[field] for task, field in TASK_QUEUES.items()}


class JobQueue(Protocol):
    def submit(self, scene_id: str, phase: Phase) -> None:
        """Ask a worker to run ``phase`` of the scene's job (duplicates are harmless)."""
        ...

    def submit_video(self, scene_id: str, path: str) -> None:
        """Ask a worker to render the camera-path video ``path`` of a ready scene."""
        ...

    def submit_webhook(self, delivery_id: str, countdown: float = 0.0) -> None:
        """Ask for a try of a webhook delivery in ``countdown`` seconds (duplicates are harmless)."""
        ...

    def depth(self) -> dict[str, int]:
        """Messages waiting, by queue name."""
        ...

    def ping(self) -> None:
        """Raise if jobs cannot be sent (readiness probe)."""
        ...


class CeleryJobQueue:
    """Sends tasks by name through a Celery client (no worker code imported)."""

    def __init__(
        self, broker_url: str, cpu_queue: str = "cpu", gpu_queue: str = "gpu", webhook_queue: str = "webhooks"
    ):
        from celery import Celery

        self.queues = task_queues(cpu_queue, gpu_queue, webhook_queue)  # task key -> queue
        self.app = Celery("cmc-api", broker=broker_url)
        self.app.conf.broker_connection_retry_on_startup = True
        self.app.conf.broker_transport_options = {"max_retries": 3, "interval_start": 0.2, "interval_step": 0.5}
        self.broker_url = broker_url

    @staticmethod
    def from_settings(settings: Settings) -> CeleryJobQueue:
        return CeleryJobQueue(settings.broker_url, settings.cpu_queue, settings.gpu_queue, settings.webhook_queue)

    def submit(self, scene_id: str, phase: Phase) -> None:
        self.app.send_task(TASK_NAMES[phase], args=[scene_id], queue=self.queues[phase])

    def submit_video(self, scene_id: str, path: str) -> None:
        self.app.send_task(TASK_NAMES["video"], args=[scene_id, path], queue=self.queues["video"])

    def submit_webhook(self, delivery_id: str, countdown: float = 0.0) -> None:
        queue = self.queues["webhook"]
        self.app.send_task(TASK_NAMES["webhook"], args=[delivery_id], queue=queue, countdown=countdown or None)

    def _redis(self):
        import redis

        return redis.Redis.from_url(self.broker_url, socket_timeout=2, socket_connect_timeout=2)

    def depth(self) -> dict[str, int]:
        """Length of each queue's Redis list (Celery's Redis transport keeps a queue in one list)."""
        r = self._redis()
        try:
            return {q: int(r.llen(q)) for q in sorted(set(self.queues.values()))}
        finally:
            r.close()

    def ping(self) -> None:
        r = self._redis()
        try:
            r.ping()
        finally:
            r.close()
