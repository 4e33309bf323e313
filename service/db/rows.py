"""The scene store's tables (SQLAlchemy rows), the plain snapshots it hands out, and its status
vocabulary (see :mod:`service.db.scenes` for the life cycle)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

from sqlalchemy import JSON, Boolean, Float, Integer, String, Text, UniqueConstraint
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column

Status = Literal["queued", "estimating_poses", "training", "baking", "ready", "failed", "cancelled"]
STATUSES: tuple[Status, ...] = ("queued", "estimating_poses", "training", "baking", "ready", "failed", "cancelled")
TERMINAL: tuple[Status, ...] = ("ready", "failed", "cancelled")
Phase = Literal["poses", "train", "done"]


class Base(DeclarativeBase):
    pass


class SceneRow(Base):
    __tablename__ = "scenes"
    __table_args__ = (UniqueConstraint("owner", "idempotency_key", name="uq_scene_idempotency"),)

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    owner: Mapped[str] = mapped_column(String(64), index=True)
    status: Mapped[str] = mapped_column(String(20), index=True)
    phase: Mapped[str] = mapped_column(String(10))
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    eta_seconds: Mapped[float | None] = mapped_column(Float, nullable=True)
    detail: Mapped[str | None] = mapped_column(String(200), nullable=True)
    error_code: Mapped[str | None] = mapped_column(String(40), nullable=True)
    error_message: Mapped[str | None] = mapped_column(String(2000), nullable=True)
    options: Mapped[dict[str, Any]] = mapped_column(JSON)
    upload_names: Mapped[list[str]] = mapped_column(JSON)  # the client's file names (data, never paths)
    upload_files: Mapped[list[str]] = mapped_column(JSON)  # our storage names, in the same order
    has_cameras: Mapped[bool] = mapped_column(Boolean, default=False)
    idempotency_key: Mapped[str | None] = mapped_column(String(200), nullable=True)
    request_digest: Mapped[str | None] = mapped_column(String(64), nullable=True)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    lease_owner: Mapped[str | None] = mapped_column(String(100), nullable=True)
    lease_expires_at: Mapped[float | None] = mapped_column(Float, nullable=True)
    cancel_requested: Mapped[bool] = mapped_column(Boolean, default=False)
    deleted: Mapped[bool] = mapped_column(Boolean, default=False, index=True)
    stats: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    created_at: Mapped[float] = mapped_column(Float)
    updated_at: Mapped[float] = mapped_column(Float)
    enqueued_at: Mapped[float | None] = mapped_column(Float, nullable=True)
    started_at: Mapped[float | None] = mapped_column(Float, nullable=True)
    finished_at: Mapped[float | None] = mapped_column(Float, nullable=True, index=True)  # the latest jobs' pace
    send_at: Mapped[float | None] = mapped_column(Float, nullable=True, index=True)  # outbox: message due


# Webhooks live in tables of their own: a scene's callback URL, and one row per event to deliver.
# A schema change here needs a revision in service/db/migrations/versions/ (tests/test_migrations.py).
class CallbackRow(Base):
    __tablename__ = "scene_callbacks"

    scene_id: Mapped[str] = mapped_column(String(32), primary_key=True)
    url: Mapped[str] = mapped_column(String(2000))


class DeliveryRow(Base):
    __tablename__ = "webhook_deliveries"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)  # the idempotency id in the body
    scene_id: Mapped[str] = mapped_column(String(32), index=True)
    owner: Mapped[str] = mapped_column(String(64))  # whose signing secret signs it
    event: Mapped[str] = mapped_column(String(40))
    url: Mapped[str] = mapped_column(String(2000))
    body: Mapped[str] = mapped_column(Text)  # the exact JSON sent, the same bytes on every attempt
    status: Mapped[str] = mapped_column(String(10), index=True)  # pending, delivered, failed
    attempts: Mapped[list[dict[str, Any]]] = mapped_column(JSON, default=list)
    next_attempt_at: Mapped[float | None] = mapped_column(Float, nullable=True, index=True)
    created_at: Mapped[float] = mapped_column(Float)
    updated_at: Mapped[float] = mapped_column(Float)
    delivered_at: Mapped[float | None] = mapped_column(Float, nullable=True)


class VideoRow(Base):
    """One camera-path video build of a scene (service/db/videos.py): record, lease, progress, error."""

    __tablename__ = "video_jobs"

    scene_id: Mapped[str] = mapped_column(String(32), primary_key=True)
    path: Mapped[str] = mapped_column(String(10), primary_key=True)  # spiral, orbit, dolly
    status: Mapped[str] = mapped_column(String(10), index=True)  # building, ready, failed, cancelled
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    error: Mapped[str | None] = mapped_column(String(2000), nullable=True)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    lease_owner: Mapped[str | None] = mapped_column(String(100), nullable=True)
    lease_expires_at: Mapped[float | None] = mapped_column(Float, nullable=True)
    cancel_requested: Mapped[bool] = mapped_column(Boolean, default=False)
    created_at: Mapped[float] = mapped_column(Float)
    updated_at: Mapped[float] = mapped_column(Float)


@dataclass(frozen=True)
class Delivery:
    """A snapshot of one webhook delivery: ``attempts`` lists ``{at, status_code, error,
    duration_ms}`` per try, oldest first; ``next_attempt_at`` is set while ``pending``."""

    id: str
    scene_id: str
    owner: str
    event: str
    url: str
    body: str
    status: str
    attempts: list[dict[str, Any]]
    next_attempt_at: float | None
    created_at: float
    updated_at: float
    delivered_at: float | None

    @staticmethod
    def of(row: DeliveryRow) -> Delivery:
        return Delivery(**{f: getattr(row, f) for f in Delivery.__dataclass_fields__})


@dataclass(frozen=True)
class SceneRecord:
    """A snapshot of one scene row (plain data, safe to use after the session closed)."""

    id: str
    owner: str
    status: Status
    phase: Phase
    progress: float
    eta_seconds: float | None
    detail: str | None
    error_code: str | None
    error_message: str | None
    options: dict[str, Any]
    upload_names: list[str]
    upload_files: list[str]
    has_cameras: bool
    idempotency_key: str | None
    request_digest: str | None
    attempts: int
    lease_owner: str | None
    lease_expires_at: float | None
    cancel_requested: bool
    deleted: bool
    stats: dict[str, Any]
    created_at: float
    updated_at: float
    enqueued_at: float | None
    started_at: float | None
    finished_at: float | None
    send_at: float | None

    @staticmethod
    def of(row: SceneRow) -> SceneRecord:
        return SceneRecord(**{f: getattr(row, f) for f in SceneRecord.__dataclass_fields__})


class IdempotencyConflict(Exception):
    """The Idempotency-Key was used before for a different request."""


@dataclass(frozen=True)
class Heartbeat:
    """What a renewing worker learns: whether it still holds the job and whether to stop."""

    holds_lease: bool
    cancel_requested: bool
