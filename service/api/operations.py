"""Operations routes: liveness, readiness (database, storage, queue) and Prometheus metrics."""

from __future__ import annotations

from fastapi import APIRouter, Response
from fastapi.responses import JSONResponse

from service.api.deps import Svc
from service.errors import APIError, ErrorCode
from service.schemas import ErrorBody, Health

router = APIRouter()


@router.get("/healthz", response_model=Health, summary="The process is alive")
async def healthz() -> Health:  # async: answers on the event loop, needing no thread
    return Health(status="ok")


@router.get(
    "/readyz",
    response_model=Health,
    responses={503: {"model": ErrorBody, "description": "a dependency is down"}},
    summary="Database, storage and job queue reachable",
)
def readyz(svc: Svc) -> Response:
    checks, failed = {}, []
    for name, probe in (("database", svc.store.ping), ("storage", svc.storage.check), ("queue", svc.queue.ping)):
        try:
            probe()
            checks[name] = "ok"
        except Exception as e:
            checks[name] = f"{type(e).__name__}: {e}"[:200]
            failed.append(name)
    if failed:
        raise APIError(503, ErrorCode.unavailable, f"not ready: {', '.join(failed)}", checks)
    return JSONResponse(Health(status="ready", checks=checks).model_dump())


@router.get(
    "/metrics",
    response_class=Response,
    responses={200: {"content": {"text/plain": {}}, "description": "Prometheus text format"}},
    summary="Prometheus metrics",
)
def metrics(svc: Svc) -> Response:
    return Response(svc.metrics.export(), media_type="text/plain; version=0.0.4; charset=utf-8")
