"""What the routes share: the services of the app, the caller's API key (owner), scene lookup,
the render quota, and the error responses the OpenAPI spec lists."""

from __future__ import annotations

from concurrent.futures import Executor
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Annotated, Any

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from cmc.data.images import MemoryBudget
from service.auth import KeyRing
from service.db.rows import SceneRecord
from service.db.scenes import SceneStore
from service.errors import APIError, ErrorCode, not_found
from service.jobs import JobQueue
from service.layout import SceneLayout
from service.metrics import Metrics
from service.quotas import STATE_KEY, Quotas, headers_of
from service.renders import BakedCache, RenderQueue
from service.schemas import ErrorBody
from service.settings import Settings
from service.storage import Storage


@dataclass
class Services:
    """Everything a route needs; built once per app by service.app.create_app."""

    settings: Settings
    store: SceneStore
    storage: Storage
    queue: JobQueue
    keys: KeyRing
    renders: BakedCache
    metrics: Metrics
    render_queue: RenderQueue
    quotas: Quotas
    intake: Executor  # checks of uploaded photos (service.app.INTAKE_THREADS)
    decode_memory: MemoryBudget  # what their decodes (and an embedded runner's) may hold at once


def get_services(request: Request) -> Services:
    return request.app.state.services


_bearer = HTTPBearer(auto_error=False, description="API key (not needed when the server has none configured)")


def get_owner(request: Request, _: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> str:
    return get_services(request).keys.owner(request.headers.get("authorization"))


Svc = Annotated[Services, Depends(get_services)]
Owner = Annotated[str, Depends(get_owner)]
SceneId = Annotated[str, "scene id"]


def _render_quota(request: Request, owner: Owner) -> None:
    """Counts a render or depth request against the key's renders per second (429 over it)."""
    setattr(request.state, STATE_KEY, headers_of(get_services(request).quotas.admit_render(owner)))


RenderQuota = Depends(_render_quota)

ERRORS: dict[int | str, dict[str, Any]] = {
    code: {"model": ErrorBody, "description": text}
    for code, text in {
        401: "missing or unknown API key",
        404: "no such scene (or not yours)",
        422: "invalid request",
    }.items()
}
ERRORS_READY: dict[int | str, dict[str, Any]] = {
    **ERRORS,
    409: {"model": ErrorBody, "description": "the scene is not ready yet (code scene_not_ready)"},
}
ERRORS_VIEWABLE: dict[int | str, dict[str, Any]] = {
    **ERRORS,
    409: {
        "model": ErrorBody,
        "description": "the scene is neither ready nor has a preview yet (code scene_not_ready)",
    },
}
STAGE_HEADER = {
    "Scene-Stage": {
        "schema": {"type": "string", "enum": ["preview", "final"]},
        "description": "preview: from the bake a job publishes part way through training; final: the ready scene",
    }
}
_INT = {"schema": {"type": "integer"}}
FROM_BUCKET: dict[int | str, dict[str, Any]] = {  # service.storage.file_response
    307: {
        "description": "with S3 storage (CMC_STORAGE=s3://...): the file is downloaded from the bucket at the "
        "presigned URL in Location (valid CMC_S3_URL_SECONDS)",
        "headers": {"Location": {"schema": {"type": "string"}, "description": "presigned GET URL"}},
    }
}
RATE_LIMIT_HEADERS = {
    "RateLimit-Limit": {
        **_INT,
        "description": "the API key's limit closest to refusing (draft-ietf-httpapi-ratelimit-headers-06); "
        "sent only when the server has API keys",
    },
    "RateLimit-Remaining": {**_INT, "description": "requests (or jobs) left under that limit"},
    "RateLimit-Reset": {
        **_INT,
        "description": "seconds until that limit allows more (for concurrent jobs: the shortest ETA of the "
        "key's unfinished jobs, an estimate)",
    },
}


def too_many(limits: str) -> dict[int | str, dict[str, Any]]:
    """The 429 response of a route limited per API key (``limits``: which limits, for people)."""
    headers = {"Retry-After": {**_INT, "description": "seconds to wait before asking again"}, **RATE_LIMIT_HEADERS}
    text = f"over the API key's {limits}: retry after Retry-After seconds"
    return {429: {"model": ErrorBody, "description": text, "headers": headers}}


ERRORS_RENDER: dict[int | str, dict[str, Any]] = {
    **ERRORS_VIEWABLE,
    **too_many("renders per second (code render_rate_limited)"),
    503: {"model": ErrorBody, "description": "all render slots taken (code renderer_busy): retry after Retry-After"},
}


def iso_time(t: float | None) -> str | None:
    return None if t is None else datetime.fromtimestamp(t, UTC).isoformat().replace("+00:00", "Z")


def owned_scene(svc: Services, scene_id: str, owner: str) -> SceneRecord:
    rec = svc.store.get(scene_id, owner)
    if rec is None:
        raise not_found()
    return rec


def serves_preview(rec: SceneRecord) -> bool:
    """Whether the scene's views come from the preview its job published (it trains on)."""
    return rec.status in ("training", "baking") and "preview" in rec.stats


def viewable_scene(svc: Services, scene_id: str, owner: str) -> str:
    """The storage folder the scene's views come from: the final bake of a ready scene, or the
    preview its job published while it trains (409 scene_not_ready when there is neither)."""
    rec = owned_scene(svc, scene_id, owner)
    layout = SceneLayout(scene_id)
    if rec.status == "ready":
        return layout.baked()
    if serves_preview(rec):
        return layout.preview(rec.stats["preview"]["step"])
    detail = f"the scene is {rec.status}" + ("; no preview yet" if rec.status in ("training", "baking") else "")
    raise APIError(409, ErrorCode.scene_not_ready, detail, {"status": rec.status})


def stage_of(folder: str) -> str:
    """``preview`` or ``final``: which bake the folder from :func:`viewable_scene` holds."""
    return "preview" if SceneLayout(folder.split("/", 1)[0]).is_preview(folder) else "final"


def ready_scene(svc: Services, scene_id: str, owner: str) -> SceneRecord:
    rec = owned_scene(svc, scene_id, owner)
    if rec.status != "ready":
        raise APIError(409, ErrorCode.scene_not_ready, f"the scene is {rec.status}", {"status": rec.status})
    return rec
