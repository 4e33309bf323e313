"""The HTTP routes, versioned under ``/v1`` (thin: checks, then store / storage / renderer calls):
:mod:`.scenes` (upload, status, delete, cameras, webhooks), :mod:`.views` (render, depth, MPI,
glTF, camera paths, videos, viewer), :mod:`.operations` (health, readiness, metrics), and what they
share in :mod:`.deps`. Blocking work (database, storage, queue) runs in plain ``def`` routes or,
in ``async`` ones, in the thread pool, so the event loop never waits on Redis or the disk.
"""

from fastapi import APIRouter

from service.api import operations, scenes, views
from service.api.deps import Services

router = APIRouter()
for part in (scenes, views, operations):
    router.include_router(part.router)

__all__ = ["Services", "router"]
