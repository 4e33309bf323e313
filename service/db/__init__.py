"""Persistence of scene records: the tables (:mod:`service.db.rows`), the store every API process
and worker uses (:mod:`service.db.scenes`, with video builds in :mod:`service.db.videos`), and
the schema's migrations (:mod:`service.db.migrate`, revisions in ``migrations/``)."""

from service.db.rows import (
    STATUSES,
    TERMINAL,
    Delivery,
    Heartbeat,
    IdempotencyConflict,
    Phase,
    SceneRecord,
    Status,
)
from service.db.scenes import SceneStore

__all__ = [
    "STATUSES",
    "TERMINAL",
    "Delivery",
    "Heartbeat",
    "IdempotencyConflict",
    "Phase",
    "SceneRecord",
    "SceneStore",
    "Status",
]
