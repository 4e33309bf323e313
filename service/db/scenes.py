"""Durable scene records in SQL (SQLAlchemy): SQLite embedded, PostgreSQL in docker-compose.

Why SQL: a scene record (owner, status, progress, error, artifacts) must survive a restart of
the API, a worker or Redis. Redis here is only the job transport; the database is the truth.
Every state change is one short transaction, and the ones that race (claiming a job, renewing
a lease, an idempotent create) are single conditional statements, so concurrent API processes
and workers need no other locking.

Times are UNIX seconds (float, UTC) so SQLite and PostgreSQL behave the same.

Job life cycle (``phase`` says which task runs next; ``status`` is what clients see)::

    queued --poses task--> estimating_poses --> training --train task--> baking --> ready
                                   \\-----------------\\--------------------\\--> failed
    DELETE at any point: cancelled (the record is hidden, artifacts removed)

A worker *claims* a job for a phase by taking its lease (``lease_owner``, ``lease_expires_at``)
and renews it while it runs. A lease that expires means the worker died: the reaper
(:meth:`SceneStore.stale_jobs`) hands the job to the queue again, and the next worker resumes
from the last checkpoint.

Outbox: a job's message to the queue is recorded as due (``send_at``) in the same statement
that makes it necessary (the next phase, a re-queue, a worker stopping), and cleared once the
broker took it (:meth:`SceneStore.message_sent`) or a worker claimed the job. A message that
could not be sent stays due, so whoever sends due messages (``worker.pipeline.deliver``) sends
it as soon as the broker is back, instead of the job waiting for the reaper's long timeout.

New columns are added to an existing database when the store opens it (nullable, no default).
"""

from __future__ import annotations

import json
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import func, or_, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from service.db.engine import open_engine
from service.db.migrate import upgrade
from service.db.rows import (
    STATUSES,
    TERMINAL,
    CallbackRow,
    Delivery,
    DeliveryRow,
    Heartbeat,
    IdempotencyConflict,
    Phase,
    SceneRecord,
    SceneRow,
    Status,
    VideoRow,
)
from service.db.videos import VideoJobs
from service.errors import ErrorCode


class SceneStore:
    """All reads and writes of scene records. Thread-safe (one engine, a session per call)."""

    def __init__(self, url: str, migrate: bool = True):
        """Open the database at SQLAlchemy ``url``; with ``migrate``, first bring its schema to
        the newest revision (:mod:`service.db.migrate`)."""
        self.engine = open_engine(url)
        if migrate:
            upgrade(self.engine)
        self._sessions = sessionmaker(self.engine, expire_on_commit=False)
        self.videos = VideoJobs(self._session)  # camera-path video builds

    @contextmanager
    def _session(self) -> Iterator[Session]:
        with self._sessions() as s, s.begin():
            yield s

    def ping(self) -> None:
        """Raise if the database cannot be reached."""
        with self._session() as s:
            s.execute(select(1))

    def close(self) -> None:
        self.engine.dispose()

    # -- create / read ------------------------------------------------------------------------

    def create(
        self,
        owner: str,
        options: dict[str, Any],
        upload_names: list[str],
        upload_files: list[str],
        has_cameras: bool,
        idempotency_key: str | None = None,
        request_digest: str | None = None,
        scene_id: str | None = None,
        callback_url: str | None = None,
    ) -> tuple[SceneRecord, bool]:
        """Insert a queued scene; returns (record, created).

        With an ``idempotency_key`` already used by ``owner``, returns the existing scene and
        False when ``request_digest`` matches, and raises IdempotencyConflict when it does not.
        ``callback_url`` (checked by the caller) receives the scene's webhooks.
        """
        now = time.time()
        row = SceneRow(
            id=scene_id or uuid.uuid4().hex,
            owner=owner,
            status="queued",
            phase="poses",
            progress=0.0,
            options=options,
            upload_names=upload_names,
            upload_files=upload_files,
            has_cameras=has_cameras,
            idempotency_key=idempotency_key,
            request_digest=request_digest,
            attempts=0,
            cancel_requested=False,
            deleted=False,
            stats={},
            created_at=now,
            updated_at=now,
            enqueued_at=now,
        )
        try:
            with self._session() as s:
                s.add(row)
                if callback_url:
                    s.flush()  # the scene first: a duplicate Idempotency-Key fails here
                    s.add(CallbackRow(scene_id=row.id, url=callback_url))
            return SceneRecord.of(row), True
        except IntegrityError:
            if idempotency_key is None:
                raise
        existing = self.find_by_idempotency_key(owner, idempotency_key)
        if existing is None:  # deleted between the insert and this read
            raise IdempotencyConflict("the scene made with this Idempotency-Key was deleted")
        if existing.request_digest != request_digest:
            raise IdempotencyConflict("this Idempotency-Key was used for a different upload")
        return existing, False

    def find_by_idempotency_key(self, owner: str, key: str) -> SceneRecord | None:
        with self._session() as s:
            row = s.scalar(select(SceneRow).where(SceneRow.owner == owner, SceneRow.idempotency_key == key))
            return None if row is None or row.deleted else SceneRecord.of(row)

    def get(self, scene_id: str, owner: str | None = None, include_deleted: bool = False) -> SceneRecord | None:
        """The scene, or None when absent, deleted (unless asked for) or owned by someone else."""
        with self._session() as s:
            row = s.get(SceneRow, scene_id)
            if row is None or (row.deleted and not include_deleted) or (owner is not None and row.owner != owner):
                return None
            return SceneRecord.of(row)

    def list(self, owner: str, limit: int, before: tuple[float, str] | None = None) -> list[SceneRecord]:
        """The owner's scenes, newest first; ``before`` = (created_at, id) of the last one seen."""
        q = select(SceneRow).where(SceneRow.owner == owner, SceneRow.deleted.is_(False))
        if before is not None:
            t, i = before
            q = q.where(or_(SceneRow.created_at < t, (SceneRow.created_at == t) & (SceneRow.id < i)))
        q = q.order_by(SceneRow.created_at.desc(), SceneRow.id.desc()).limit(limit)
        with self._session() as s:
            return [SceneRecord.of(r) for r in s.scalars(q)]

    def unfinished(self, owner: str) -> list[tuple[str, float | None]]:
        """(id, eta_seconds) of the owner's scenes whose job has not ended (the concurrency quota)."""
        q = select(SceneRow.id, SceneRow.eta_seconds).where(
            SceneRow.owner == owner, SceneRow.deleted.is_(False), SceneRow.status.not_in(TERMINAL)
        )
        with self._session() as s:
            return [(i, eta) for i, eta in s.execute(q)]

    def count_by_status(self) -> dict[str, int]:
        with self._session() as s:
            rows = s.execute(
                select(SceneRow.status, func.count()).where(SceneRow.deleted.is_(False)).group_by(SceneRow.status)
            )
            counts = {st: 0 for st in STATUSES}
            counts.update({st: n for st, n in rows})
            return counts

    def finished_durations(self) -> list[tuple[str, float]]:
        """(status, seconds from upload to the end) of every finished job."""
        with self._session() as s:
            rows = s.execute(
                select(SceneRow.status, SceneRow.finished_at - SceneRow.created_at).where(
                    SceneRow.finished_at.is_not(None)
                )
            )
            return [(st, float(d)) for st, d in rows]

    def latest_ready(self, limit: int) -> list[SceneRecord]:
        """Up to ``limit`` scenes whose job finished ready, the latest first, deleted ones included
        (what the worker measured on them, ``stats``, outlives the scene)."""
        q = select(SceneRow).where(SceneRow.status == "ready", SceneRow.finished_at.is_not(None))
        q = q.order_by(SceneRow.finished_at.desc()).limit(limit)
        with self._session() as s:
            return [SceneRecord.of(r) for r in s.scalars(q)]

    # -- changes by the API ---------------------------------------------------------------------

    def delete(self, scene_id: str) -> None:
        """Hide the scene and ask a running job to stop (the record stays as a tombstone)."""
        now = time.time()
        with self._session() as s:
            row = s.get(SceneRow, scene_id)
            if row is None:
                return
            row.deleted, row.cancel_requested, row.updated_at = True, True, now
            if row.status not in TERMINAL:
                row.status, row.finished_at = "cancelled", now
            s.execute(  # and its video builds
                update(VideoRow)
                .where(VideoRow.scene_id == scene_id, VideoRow.status == "building")
                .values(status="cancelled", cancel_requested=True, updated_at=now)
            )

    def purge(self, scene_id: str) -> None:
        """Remove a record outright (a scene whose job could not even be queued)."""
        with self._session() as s:
            row = s.get(SceneRow, scene_id)
            if row is not None:
                s.delete(row)

    # -- changes by workers ---------------------------------------------------------------------

    def claim(self, scene_id: str, phase: Phase, worker: str, lease_seconds: float) -> SceneRecord | None:
        """Take the job for ``phase`` unless it is finished, cancelled, in another phase or held
        by a live worker. Returns the claimed record, or None (a duplicate delivery: drop it)."""
        now = time.time()
        stmt = (
            update(SceneRow)
            .where(
                SceneRow.id == scene_id,
                SceneRow.phase == phase,
                SceneRow.status.not_in(TERMINAL),
                SceneRow.cancel_requested.is_(False),
                or_(SceneRow.lease_expires_at.is_(None), SceneRow.lease_expires_at < now),
            )
            .values(lease_owner=worker, lease_expires_at=now + lease_seconds, updated_at=now, send_at=None)
        )
        with self._session() as s:
            if s.execute(stmt).rowcount != 1:
                return None
            row = s.get(SceneRow, scene_id)
            if row is not None and row.started_at is None:
                row.started_at = now
            return None if row is None else SceneRecord.of(row)

    def heartbeat(self, scene_id: str, worker: str, lease_seconds: float, **fields: Any) -> Heartbeat:
        """Renew the lease and write progress ``fields`` if ``worker`` still holds the job."""
        now = time.time()
        stmt = (
            update(SceneRow)
            .where(SceneRow.id == scene_id, SceneRow.lease_owner == worker, SceneRow.status.not_in(TERMINAL))
            .values(lease_expires_at=now + lease_seconds, updated_at=now, **fields)
        )
        with self._session() as s:
            held = s.execute(stmt).rowcount == 1
            cancel = s.scalar(select(SceneRow.cancel_requested).where(SceneRow.id == scene_id))
        return Heartbeat(held, bool(cancel) if cancel is not None else True)

    def advance(self, scene_id: str, worker: str, phase: Phase, status: Status, **fields: Any) -> bool:
        """Finish the held phase: move to ``phase``/``status``, drop the lease, and unless the job
        ended, make the next phase's message due (the outbox). False if not held."""
        now = time.time()
        values: dict[str, Any] = dict(
            phase=phase, status=status, lease_owner=None, lease_expires_at=None, updated_at=now, **fields
        )
        if status in TERMINAL:
            values["finished_at"] = now
        else:
            values.update(enqueued_at=now, send_at=now)
        stmt = (
            update(SceneRow)
            .where(SceneRow.id == scene_id, SceneRow.lease_owner == worker, SceneRow.status.not_in(TERMINAL))
            .values(**values)
        )
        with self._session() as s:
            done = s.execute(stmt).rowcount == 1
            if done and status in ("ready", "failed"):
                _add_event(s, scene_id, f"scene.{status}", {"status": status}, now)
            return done

    def release(self, scene_id: str, worker: str, resend: bool = False, **fields: Any) -> None:
        """Give the lease back without changing the phase; with ``resend`` the job's message is
        made due again (a worker stopping for shutdown hands its job to the next one)."""
        now = time.time()
        values: dict[str, Any] = dict(lease_owner=None, lease_expires_at=None, updated_at=now, **fields)
        if resend:
            values.update(enqueued_at=now, send_at=now)
        with self._session() as s:
            s.execute(update(SceneRow).where(SceneRow.id == scene_id, SceneRow.lease_owner == worker).values(**values))

    def fail(self, scene_id: str, code: ErrorCode, message: str) -> None:
        """Mark a job failed (whoever holds it); no-op when it already ended."""
        now = time.time()
        with self._session() as s:
            result = s.execute(
                update(SceneRow)
                .where(SceneRow.id == scene_id, SceneRow.status.not_in(TERMINAL))
                .values(
                    status="failed",
                    error_code=code,
                    error_message=message[:2000],
                    lease_owner=None,
                    lease_expires_at=None,
                    eta_seconds=None,
                    updated_at=now,
                    finished_at=now,
                )
            )
            if result.rowcount == 1:
                error = {"code": code, "message": message[:2000]}
                _add_event(s, scene_id, "scene.failed", {"status": "failed", "error": error}, now)

    def stale_jobs(self, requeue_after_seconds: float) -> list[SceneRecord]:
        """Unfinished jobs whose worker's lease expired, or that waited in a queue so long
        that their message was probably lost (e.g. a Redis restart without persistence)."""
        now = time.time()
        q = select(SceneRow).where(
            SceneRow.status.not_in(TERMINAL),
            SceneRow.cancel_requested.is_(False),
            or_(
                SceneRow.lease_expires_at < now,
                SceneRow.lease_expires_at.is_(None) & (SceneRow.enqueued_at < now - requeue_after_seconds),
            ),
        )
        with self._session() as s:
            return [SceneRecord.of(r) for r in s.scalars(q)]

    def unfinished_jobs(self) -> list[SceneRecord]:
        """Every job that is not finished nor cancelled (the embedded runner's restart list)."""
        q = select(SceneRow).where(SceneRow.status.not_in(TERMINAL), SceneRow.cancel_requested.is_(False))
        with self._session() as s:
            return [SceneRecord.of(r) for r in s.scalars(q.order_by(SceneRow.created_at))]

    def requeue(self, scene: SceneRecord, max_attempts: int, **fields: Any) -> bool:
        """Drop an expired lease, count the attempt and make the job's message due; fails the job
        after ``max_attempts`` lost workers. True when the job is to be sent again."""
        now = time.time()
        lost = scene.lease_owner is not None
        attempts = scene.attempts + (1 if lost else 0)
        with self._session() as s:
            stmt = (
                update(SceneRow)
                .where(
                    SceneRow.id == scene.id,
                    SceneRow.status.not_in(TERMINAL),
                    # unchanged since it was read: nobody claimed or renewed it meanwhile
                    SceneRow.updated_at == scene.updated_at,
                )
                .values(
                    lease_owner=None,
                    lease_expires_at=None,
                    attempts=attempts,
                    enqueued_at=now,
                    send_at=now,
                    updated_at=now,
                    **fields,
                )
            )
            if s.execute(stmt).rowcount != 1:
                return False
        if attempts >= max_attempts:
            self.fail(scene.id, ErrorCode.worker_lost, f"the job's worker stopped {attempts} times; giving up")
            return False
        return True

    # -- webhooks -------------------------------------------------------------------------------
    #
    # An event is written in the same transaction as the change it reports (a ready or failed
    # scene), so it exists exactly when the change does; senders (worker.webhooks) then deliver
    # each pending row at least once, claiming it first so that two senders rarely both try.

    def add_event(self, scene_id: str, event: str, data: dict[str, Any]) -> None:
        """Record an event of the scene for its callback URL (no-op without one)."""
        with self._session() as s:
            _add_event(s, scene_id, event, data, time.time())

    def callback_url(self, scene_id: str) -> str | None:
        with self._session() as s:
            row = s.get(CallbackRow, scene_id)
            return None if row is None else row.url

    def deliveries(self, scene_id: str) -> list[Delivery]:
        """The scene's webhook deliveries, oldest first."""
        q = select(DeliveryRow).where(DeliveryRow.scene_id == scene_id)
        with self._session() as s:
            return [Delivery.of(r) for r in s.scalars(q.order_by(DeliveryRow.created_at, DeliveryRow.id))]

    def delivery(self, delivery_id: str) -> Delivery | None:
        with self._session() as s:
            row = s.get(DeliveryRow, delivery_id)
            return None if row is None else Delivery.of(row)

    def due_deliveries(self, before: float, scene_id: str | None = None, limit: int = 100) -> list[str]:
        """Ids of pending deliveries whose next attempt is due at ``before``, the oldest first."""
        q = select(DeliveryRow.id).where(DeliveryRow.status == "pending", DeliveryRow.next_attempt_at <= before)
        if scene_id is not None:
            q = q.where(DeliveryRow.scene_id == scene_id)
        with self._session() as s:
            return list(s.scalars(q.order_by(DeliveryRow.next_attempt_at).limit(limit)))

    def next_delivery_at(self) -> float | None:
        """When the earliest pending delivery is due (None: nothing pending)."""
        with self._session() as s:
            return s.scalar(select(func.min(DeliveryRow.next_attempt_at)).where(DeliveryRow.status == "pending"))

    def claim_delivery(self, delivery_id: str, hold_seconds: float, early: float = 1.0) -> Delivery | None:
        """Take a pending delivery that is due (within ``early`` seconds) for one attempt: its
        next attempt moves ``hold_seconds`` ahead, so other senders leave it alone meanwhile
        (and pick it up again after that if this one dies). None: not pending, or not due."""
        now = time.time()
        stmt = (
            update(DeliveryRow)
            .where(
                DeliveryRow.id == delivery_id,
                DeliveryRow.status == "pending",
                DeliveryRow.next_attempt_at <= now + early,
            )
            .values(next_attempt_at=now + hold_seconds, updated_at=now)
        )
        with self._session() as s:
            if s.execute(stmt).rowcount != 1:
                return None
            row = s.get(DeliveryRow, delivery_id)
            return None if row is None else Delivery.of(row)

    def record_attempt(
        self, delivery_id: str, attempt: dict[str, Any], status: str, next_attempt_at: float | None
    ) -> None:
        """Append one attempt's outcome; ``status`` pending (retry at ``next_attempt_at``),
        delivered or failed (given up)."""
        now = time.time()
        with self._session() as s:
            row = s.get(DeliveryRow, delivery_id)
            if row is None:
                return
            row.attempts = [*row.attempts, attempt]
            row.status, row.updated_at = status, now
            row.next_attempt_at = next_attempt_at if status == "pending" else None
            if status == "delivered":
                row.delivered_at = now

    # -- the outbox ---------------------------------------------------------------------------

    def due_messages(self, scene_id: str | None = None) -> list[SceneRecord]:
        """Unfinished jobs whose message is due (all, or the one scene's), oldest first."""
        q = select(SceneRow).where(
            SceneRow.send_at <= time.time(),
            SceneRow.status.not_in(TERMINAL),
            SceneRow.cancel_requested.is_(False),
        )
        if scene_id is not None:
            q = q.where(SceneRow.id == scene_id)
        with self._session() as s:
            return [SceneRecord.of(r) for r in s.scalars(q.order_by(SceneRow.send_at))]

    def take_message(self, scene: SceneRecord, retry_at: float) -> bool:
        """Take a due message for sending: it falls due again at ``retry_at`` unless
        :meth:`message_sent` clears it first. False when another sender took it (or it changed)."""
        stmt = (
            update(SceneRow)
            .where(SceneRow.id == scene.id, SceneRow.send_at == scene.send_at, SceneRow.phase == scene.phase)
            .values(send_at=retry_at)
        )
        with self._session() as s:
            return s.execute(stmt).rowcount == 1

    def message_sent(self, scene_id: str, taken: float, **fields: Any) -> None:
        """The broker took the message taken with ``retry_at=taken``: nothing more to send (unless
        it was made due again meanwhile). ``fields`` are written while no worker holds the job."""
        with self._session() as s:
            s.execute(update(SceneRow).where(SceneRow.id == scene_id, SceneRow.send_at == taken).values(send_at=None))
            if fields:
                self._set_while_waiting(s, scene_id, fields)

    def message_failed(self, scene_id: str, **fields: Any) -> None:
        """The broker could not be reached: the message stays due; ``fields`` (the detail the
        client sees) are written while no worker holds the job."""
        with self._session() as s:
            self._set_while_waiting(s, scene_id, fields)

    @staticmethod
    def _set_while_waiting(s: Session, scene_id: str, fields: dict[str, Any]) -> None:
        s.execute(
            update(SceneRow)
            .where(SceneRow.id == scene_id, SceneRow.lease_owner.is_(None), SceneRow.status.not_in(TERMINAL))
            .values(updated_at=time.time(), **fields)
        )


def _add_event(s: Session, scene_id: str, event: str, data: dict[str, Any], now: float) -> None:
    """In session ``s``: a pending delivery of ``event`` to the scene's callback URL, if any.
    The body's ``id`` is the delivery's id: receivers drop a repeated one (at-least-once)."""
    callback = s.get(CallbackRow, scene_id)
    scene = s.get(SceneRow, scene_id)
    if callback is None or scene is None:
        return
    delivery_id = uuid.uuid4().hex
    created = datetime.fromtimestamp(now, UTC).isoformat().replace("+00:00", "Z")
    body = {"id": delivery_id, "type": event, "created_at": created, "scene_id": scene_id, "data": data}
    s.add(
        DeliveryRow(
            id=delivery_id,
            scene_id=scene_id,
            owner=scene.owner,
            event=event,
            url=callback.url,
            body=json.dumps(body, separators=(",", ":")),
            status="pending",
            attempts=[],
            next_attempt_at=now,
            created_at=now,
            updated_at=now,
        )
    )
