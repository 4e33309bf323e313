"""Camera-path video builds as jobs: a record per (scene, path) with the same lease, progress,
error and cancel as scene jobs. The API asks for a video (:meth:`VideoJobs.request`) and sends
the message when a build starts; a worker claims it, renews its lease with each progress report
and ends it ready or failed; deleting the scene cancels it; the reaper sends a build again whose
worker went silent (:meth:`VideoJobs.stale`, :func:`worker.pipeline.requeue_stale_jobs`).

Statuses: ``building`` (queued or rendering), ``ready``, ``failed`` (kept until the client has
seen the error once: asking again starts over), ``cancelled``. Times are UNIX seconds.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass

from sqlalchemy import or_, select, update
from sqlalchemy.orm import Session

from service.db.rows import Heartbeat, VideoRow


@dataclass(frozen=True)
class VideoJob:
    scene_id: str
    path: str
    status: str
    progress: float
    error: str | None
    attempts: int
    lease_owner: str | None
    updated_at: float

    @staticmethod
    def of(row: VideoRow) -> VideoJob:
        return VideoJob(**{f: getattr(row, f) for f in VideoJob.__dataclass_fields__})


class VideoJobs:
    """The ``video_jobs`` table; every change is one statement or one short transaction."""

    def __init__(self, session: Callable[[], AbstractContextManager[Session]]):
        self._session = session

    def get(self, scene_id: str, path: str) -> VideoJob | None:
        with self._session() as s:
            row = s.get(VideoRow, (scene_id, path))
            return None if row is None else VideoJob.of(row)

    def request(self, scene_id: str, path: str) -> tuple[VideoJob, bool]:
        """The build of video ``path``: the running one, or a new one (none yet, or the last one
        ended: the caller found no file); True when this call started it (the caller sends its
        message)."""
        now = time.time()
        with self._session() as s:
            row = s.get(VideoRow, (scene_id, path), with_for_update=True)
            if row is not None and row.status == "building":
                return VideoJob.of(row), False
            if row is None:
                row = VideoRow(scene_id=scene_id, path=path, created_at=now)
                s.add(row)
            row.status, row.progress, row.error, row.attempts = "building", 0.0, None, 0
            row.lease_owner, row.lease_expires_at, row.cancel_requested, row.updated_at = None, None, False, now
            s.flush()
            return VideoJob.of(row), True

    def forget(self, scene_id: str, path: str) -> None:
        """Drop a finished record (a failed build whose error the client saw: the next request retries)."""
        with self._session() as s:
            row = s.get(VideoRow, (scene_id, path))
            if row is not None and row.status != "building":
                s.delete(row)

    def claim(self, scene_id: str, path: str, worker: str, lease_seconds: float) -> bool:
        """Take a build that is not finished, cancelled or held by a live worker."""
        now = time.time()
        stmt = (
            update(VideoRow)
            .where(
                VideoRow.scene_id == scene_id,
                VideoRow.path == path,
                VideoRow.status == "building",
                VideoRow.cancel_requested.is_(False),
                or_(VideoRow.lease_owner.is_(None), VideoRow.lease_expires_at < now),
            )
            .values(lease_owner=worker, lease_expires_at=now + lease_seconds, updated_at=now)
        )
        with self._session() as s:
            return s.execute(stmt).rowcount == 1

    def heartbeat(self, scene_id: str, path: str, worker: str, lease_seconds: float, progress: float) -> Heartbeat:
        """Renew the lease and write ``progress`` (0-1) if ``worker`` still holds the build."""
        now = time.time()
        stmt = (
            update(VideoRow)
            .where(VideoRow.scene_id == scene_id, VideoRow.path == path, VideoRow.lease_owner == worker)
            .values(lease_expires_at=now + lease_seconds, progress=progress, updated_at=now)
        )
        with self._session() as s:
            held = s.execute(stmt).rowcount == 1
            row = s.get(VideoRow, (scene_id, path))
            return Heartbeat(held and row is not None and row.status == "building", bool(row and row.cancel_requested))

    def finish(self, scene_id: str, path: str, worker: str, error: str | None = None) -> bool:
        """End the build ``worker`` holds: ready, or failed with ``error``. False: not held."""
        now = time.time()
        values = {"status": "failed", "error": error[:2000]} if error else {"status": "ready", "progress": 1.0}
        stmt = (
            update(VideoRow)
            .where(
                VideoRow.scene_id == scene_id,
                VideoRow.path == path,
                VideoRow.lease_owner == worker,
                VideoRow.status == "building",
            )
            .values(lease_owner=None, lease_expires_at=None, updated_at=now, **values)
        )
        with self._session() as s:
            return s.execute(stmt).rowcount == 1

    def stale(self, requeue_after_seconds: float) -> list[VideoJob]:
        """Builds whose worker's lease expired, or whose message waited so long it was probably lost."""
        now = time.time()
        q = select(VideoRow).where(
            VideoRow.status == "building",
            VideoRow.cancel_requested.is_(False),
            or_(
                VideoRow.lease_expires_at < now,
                VideoRow.lease_owner.is_(None) & (VideoRow.updated_at < now - requeue_after_seconds),
            ),
        )
        with self._session() as s:
            return [VideoJob.of(r) for r in s.scalars(q)]

    def requeue(self, job: VideoJob, max_attempts: int) -> bool:
        """Drop an expired lease and count the attempt (the caller sends the message again); fails
        the build after ``max_attempts``. True when it is to be sent again."""
        now = time.time()
        with self._session() as s:
            row = s.get(VideoRow, (job.scene_id, job.path), with_for_update=True)
            if row is None or row.status != "building" or row.updated_at != job.updated_at:
                return False  # changed meanwhile: another reaper or the worker got there first
            row.lease_owner, row.lease_expires_at, row.updated_at = None, None, now
            row.attempts += 1
            if row.attempts > max_attempts:
                row.status, row.error = "failed", f"the video's worker stopped {max_attempts} times; giving up"
                return False
            return True

    def release(self, scene_id: str, path: str, worker: str) -> None:
        """Give up the lease ``worker`` holds (the build stays to be sent again)."""
        stmt = (
            update(VideoRow)
            .where(VideoRow.scene_id == scene_id, VideoRow.path == path, VideoRow.lease_owner == worker)
            .values(lease_owner=None, lease_expires_at=None, updated_at=time.time())
        )
        with self._session() as s:
            s.execute(stmt)

    def unfinished(self) -> list[VideoJob]:
        """Builds not finished nor cancelled (the embedded runner's restart list)."""
        q = select(VideoRow).where(VideoRow.status == "building", VideoRow.cancel_requested.is_(False))
        with self._session() as s:
            return [VideoJob.of(r) for r in s.scalars(q)]
