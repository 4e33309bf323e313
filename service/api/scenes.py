"""Scene routes: upload (and the job it starts), status, list, delete, cameras, webhooks."""

from __future__ import annotations

import asyncio
import base64
import json
import logging
import uuid
from functools import partial
from typing import Annotated, Literal

from fastapi import APIRouter, Header, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse

from service.api.deps import (
    ERRORS,
    ERRORS_READY,
    RATE_LIMIT_HEADERS,
    Owner,
    SceneId,
    Services,
    Svc,
    iso_time,
    owned_scene,
    serves_preview,
    too_many,
)
from service.db.rows import IdempotencyConflict, SceneRecord
from service.errors import APIError, ErrorCode
from service.layout import CAMERAS_UPLOAD, ClientNames, SceneLayout
from service.quotas import STATE_KEY, headers_of
from service.schemas import (
    ErrorBody,
    JobError,
    SceneLinks,
    SceneList,
    SceneOptions,
    SceneOut,
    WebhookAttempt,
    WebhookDelivery,
    WebhookLog,
    WebhookSecret,
)
from service.uploads import check_images, parse_callback_url, parse_cameras, parse_options, receive_upload

log = logging.getLogger("cmc.api")
router = APIRouter()


def scene_out(rec: SceneRecord) -> SceneOut:
    base = f"/v1/scenes/{rec.id}"
    error = JobError(code=rec.error_code, message=rec.error_message or "") if rec.error_code else None
    return SceneOut(
        id=rec.id,
        status=rec.status,
        progress=round(rec.progress, 4),
        eta_seconds=rec.eta_seconds,
        preview_ready=serves_preview(rec),
        preview_step=rec.stats["preview"]["step"] if serves_preview(rec) else None,
        detail=rec.detail,
        error=error,
        options=SceneOptions(**rec.options),
        images=rec.upload_names,
        created_at=iso_time(rec.created_at) or "",
        updated_at=iso_time(rec.updated_at) or "",
        started_at=iso_time(rec.started_at),
        finished_at=iso_time(rec.finished_at),
        links=SceneLinks(
            self=base,
            cameras=f"{base}/cameras",
            render=f"{base}/render",
            depth=f"{base}/depth",
            mpi=f"{base}/mpi",
            viewer=f"{base}/viewer",
            video=f"{base}/video",
            camera_path=f"{base}/camera-path",
            webhooks=f"{base}/webhooks",
            export_glb=f"{base}/export.glb",
        ),
    )


_UPLOAD_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["images"],
                    "properties": {
                        "images": {
                            "type": "array",
                            "items": {"type": "string", "format": "binary"},
                            "description": "the photos (JPEG, PNG, WebP or HEIC; detected by content)",
                        },
                        "cameras": {
                            "type": "string",
                            "format": "binary",
                            "description": "optional transforms.json-style cameras file (skips structure from motion)",
                        },
                        "options": {
                            "type": "string",
                            "description": 'optional JSON, e.g. {"preset": "fast", "steps": 400, '
                            '"resolution": 504, "seed": 0} (see SceneOptions)',
                        },
                        "callback_url": {
                            "type": "string",
                            "format": "uri",
                            "description": "optional http(s) URL for signed webhooks (scene.ready, scene.failed, "
                            "video.ready, video.failed); must resolve to public addresses",
                        },
                    },
                }
            }
        },
    }
}


@router.post(
    "/v1/scenes",
    status_code=202,
    response_model=SceneOut,
    summary="Upload photos and start a reconstruction",
    openapi_extra=_UPLOAD_BODY,
    responses={
        **ERRORS,
        202: {"description": "the scene, queued", "headers": RATE_LIMIT_HEADERS},
        400: {"model": ErrorBody, "description": "malformed or interrupted upload"},
        409: {"model": ErrorBody, "description": "Idempotency-Key reused for a different upload"},
        413: {"model": ErrorBody, "description": "request, image bytes or pixels over the limits"},
        415: {"model": ErrorBody, "description": "not multipart, or a photo that is not a supported image"},
        **too_many(
            "unfinished jobs (code too_many_concurrent_jobs) or new jobs in 24 hours (code daily_job_quota_exceeded); "
            "answered before the photos are read"
        ),
        503: {"model": ErrorBody, "description": "the job queue is unavailable; retry"},
    },
)
async def create_scene(
    request: Request,
    svc: Svc,
    owner: Owner,
    idempotency_key: Annotated[
        str | None,
        Header(alias="Idempotency-Key", max_length=200, description="retries with the same key make one scene"),
    ] = None,
) -> Response:
    scene_id = uuid.uuid4().hex
    # a place in the key's job quotas, held from before the body is read (a retry of an upload
    # that made its scene takes none: it is answered with that scene)
    standings = []
    if not (idempotency_key and await run_in_threadpool(svc.store.find_by_idempotency_key, owner, idempotency_key)):
        unfinished = partial(svc.store.unfinished, owner)
        standings = await run_in_threadpool(svc.quotas.reserve_job, owner, scene_id, unfinished)
    made = False
    try:
        response = await _create_scene(request, svc, owner, scene_id, idempotency_key)
        made = response.headers.get("Idempotent-Replayed") is None
    finally:
        if standings:
            if made:
                await run_in_threadpool(svc.quotas.job_created, owner, scene_id)
            else:
                await run_in_threadpool(svc.quotas.job_dropped, owner, scene_id)
    if made:
        setattr(request.state, STATE_KEY, headers_of(standings))
    return response


async def _create_scene(
    request: Request, svc: Services, owner: str, scene_id: str, idempotency_key: str | None
) -> Response:
    """Receive, check and store the upload as scene ``scene_id`` and queue its job (or answer
    with the scene an earlier upload with the same Idempotency-Key made)."""
    s, layout = svc.settings, SceneLayout(scene_id)
    try:
        with svc.storage.scratch() as tmp:  # checked here, then published whole as layout.uploads
            staged = tmp / "uploads"
            staged.mkdir()
            upload = await receive_upload(request, s, staged)
            if idempotency_key:
                existing = await run_in_threadpool(svc.store.find_by_idempotency_key, owner, idempotency_key)
                if existing is not None:
                    if existing.request_digest != upload.digest:
                        raise APIError(
                            409, ErrorCode.idempotency_conflict, "this Idempotency-Key was used for a different upload"
                        )
                    return _created(existing, replayed=True)  # nothing of this upload was stored
            stored = await asyncio.wrap_future(svc.intake.submit(check_images, upload, s, svc.decode_memory))
            options = parse_options(upload, s)
            callback_url = await run_in_threadpool(parse_callback_url, upload, s)
            cameras = await run_in_threadpool(parse_cameras, upload, stored)
            if cameras is not None:
                (staged / CAMERAS_UPLOAD).write_text(json.dumps(cameras))
            await run_in_threadpool(svc.storage.publish, layout.uploads, staged)
        rec, created = await run_in_threadpool(
            lambda: svc.store.create(
                owner,
                options.model_dump(),
                [p.filename for p in upload.images],
                stored,
                cameras is not None,
                idempotency_key,
                upload.digest,
                scene_id,
                callback_url,
            )
        )
    except IdempotencyConflict as e:
        svc.storage.delete_scene(scene_id)
        raise APIError(409, ErrorCode.idempotency_conflict, str(e)) from None
    except BaseException:  # on the event loop: it must run even when the request is cancelled
        svc.storage.delete_scene(scene_id)
        raise
    if not created:  # a concurrent retry with the same key won the race
        await run_in_threadpool(svc.storage.delete_scene, scene_id)
        return _created(rec, replayed=True)
    await run_in_threadpool(_submit_or_undo, svc, rec)
    return _created(rec, replayed=False)


def _submit_or_undo(svc: Services, rec: SceneRecord) -> None:
    """Send the scene's first job message (a broker publish: blocking, so off the event loop);
    when the broker refuses it, remove the scene again and answer 503."""
    try:
        svc.queue.submit(rec.id, "poses")
    except Exception:
        log.exception("could not queue scene %s", rec.id)
        svc.store.purge(rec.id)
        svc.storage.delete_scene(rec.id)
        raise APIError(503, ErrorCode.queue_unavailable, "the job queue is unavailable; retry shortly") from None


def _created(rec: SceneRecord, replayed: bool) -> Response:
    headers = {"Location": f"/v1/scenes/{rec.id}"}
    if replayed:
        headers["Idempotent-Replayed"] = "true"
    return JSONResponse(scene_out(rec).model_dump(mode="json"), status_code=202, headers=headers)


@router.get("/v1/scenes/{scene_id}", response_model=SceneOut, responses=ERRORS, summary="Job status of a scene")
def get_scene(scene_id: SceneId, svc: Svc, owner: Owner) -> SceneOut:
    return scene_out(owned_scene(svc, scene_id, owner))


def _cursor(rec: SceneRecord) -> str:
    return base64.urlsafe_b64encode(json.dumps([rec.created_at, rec.id]).encode()).decode()


@router.get("/v1/scenes", response_model=SceneList, responses=ERRORS, summary="Your scenes, newest first")
def list_scenes(
    svc: Svc,
    owner: Owner,
    limit: Annotated[int, Query(ge=1, le=100)] = 20,
    cursor: Annotated[str | None, Query(description="next_cursor of the previous page")] = None,
) -> SceneList:
    before = None
    if cursor:
        try:
            t, i = json.loads(base64.urlsafe_b64decode(cursor.encode()))
            before = (float(t), str(i))
        except Exception:
            raise APIError(422, ErrorCode.invalid_cursor, "cursor is not one this API returned") from None
    recs = svc.store.list(owner, limit + 1, before)
    page = recs[:limit]
    return SceneList(items=[scene_out(r) for r in page], next_cursor=_cursor(page[-1]) if len(recs) > limit else None)


@router.delete(
    "/v1/scenes/{scene_id}",
    status_code=204,
    responses=ERRORS,
    summary="Cancel the job (within seconds) and delete the scene and all its data",
)
def delete_scene(scene_id: SceneId, svc: Svc, owner: Owner) -> Response:
    owned_scene(svc, scene_id, owner)
    svc.store.delete(scene_id)
    svc.renders.evict(scene_id)
    svc.storage.delete_scene(scene_id)
    return Response(status_code=204)


@router.get(
    "/v1/scenes/{scene_id}/cameras",
    responses={**ERRORS_READY, 200: {"description": "transforms.json-style cameras file"}},
    summary="Estimated intrinsics, poses and near/far, in the upload's cameras format",
)
def get_cameras(
    scene_id: SceneId,
    svc: Svc,
    owner: Owner,
    convention: Literal["opengl", "opencv"] = "opengl",
) -> dict:
    from cmc.geometry.cameras import CameraFile, camera_file_to_dict, load_camera_file

    rec = owned_scene(svc, scene_id, owner)
    with svc.storage.reading(SceneLayout(scene_id).cameras) as path:
        if rec.phase == "poses" or not path.exists():
            message = f"camera poses are not estimated yet ({rec.status})"
            raise APIError(409, ErrorCode.scene_not_ready, message, {"status": rec.status})
        cf = load_camera_file(path)
    names = [ClientNames(rec.upload_files, rec.upload_names).of(p) for p in cf.file_paths]  # the client's names
    return camera_file_to_dict(CameraFile(cf.cameras, names, cf.near_far), convention)


@router.get(
    "/v1/scenes/{scene_id}/webhooks",
    response_model=WebhookLog,
    responses=ERRORS,
    summary="The scene's webhook deliveries: every event, every try and its outcome",
)
def get_webhooks(scene_id: SceneId, svc: Svc, owner: Owner) -> WebhookLog:
    owned_scene(svc, scene_id, owner)
    deliveries = [
        WebhookDelivery(
            id=d.id,
            type=d.event,
            status=d.status,  # type: ignore[arg-type]
            url=d.url,
            created_at=iso_time(d.created_at) or "",
            delivered_at=iso_time(d.delivered_at),
            next_attempt_at=iso_time(d.next_attempt_at) if d.status == "pending" else None,
            attempts=[WebhookAttempt(**a) for a in d.attempts],
            body=json.loads(d.body),
        )
        for d in svc.store.deliveries(scene_id)
    ]
    return WebhookLog(callback_url=svc.store.callback_url(scene_id), deliveries=deliveries)


@router.get(
    "/v1/webhooks/secret",
    response_model=WebhookSecret,
    responses={**ERRORS, 404: {"model": ErrorBody, "description": "webhooks are off (CMC_WEBHOOK_SECRET unset)"}},
    summary="Your API key's webhook signing secret and how signatures are made",
)
def get_webhook_secret(svc: Svc, owner: Owner) -> WebhookSecret:
    from service.webhooks import ID_HEADER, SIGNATURE_HEADER, TIMESTAMP_HEADER, owner_secret

    if not svc.settings.webhook_secret:
        raise APIError(
            404, ErrorCode.webhooks_not_configured, "this server sends no webhooks (CMC_WEBHOOK_SECRET is not set)"
        )
    return WebhookSecret(
        secret=owner_secret(svc.settings.webhook_secret, owner),
        signature_header=SIGNATURE_HEADER,
        timestamp_header=TIMESTAMP_HEADER,
        id_header=ID_HEADER,
        scheme="v1=hex(HMAC-SHA256(secret, timestamp + '.' + raw body))",
    )
