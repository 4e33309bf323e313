"""The HTTP routes, versioned under ``/v1`` (thin: checks, then store / storage / renderer calls)."""

from __future__ import annotations

import asyncio
import base64
import json
import logging
import time
import uuid
from concurrent.futures import Executor
from dataclasses import dataclass
from datetime import UTC, datetime
from functools import cache, partial
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from fastapi import APIRouter, Depends, Header, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse, JSONResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.auth import KeyRing
from service.errors import APIError, not_found
from service.jobs import JobQueue
from service.metrics import Metrics
from service.quotas import STATE_KEY, Quotas, headers_of
from service.renders import (
    BakedCache,
    Rendered,
    RenderQueue,
    depth_scale,
    encode_depth_npy,
    encode_depth_png16,
    encode_depth_preview,
    encode_image,
)
from service.schemas import (
    CameraPath,
    ErrorBody,
    Health,
    JobError,
    PathName,
    RenderCamera,
    SceneLinks,
    SceneList,
    SceneOptions,
    SceneOut,
    VideoBuilding,
    WebhookAttempt,
    WebhookDelivery,
    WebhookLog,
    WebhookSecret,
)
from service.settings import Settings
from service.storage import Storage, file_response, video_keys
from service.store import IdempotencyConflict, SceneRecord, SceneStore
from service.uploads import check_images, parse_callback_url, parse_cameras, parse_options, receive_upload

log = logging.getLogger("cmc.api")


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


def _services(request: Request) -> Services:
    return request.app.state.services


_bearer = HTTPBearer(auto_error=False, description="API key (not needed when the server has none configured)")


def _owner(request: Request, _: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> str:
    return _services(request).keys.owner(request.headers.get("authorization"))


Svc = Annotated[Services, Depends(_services)]
Owner = Annotated[str, Depends(_owner)]
SceneId = Annotated[str, "scene id"]


def _render_quota(request: Request, owner: Owner) -> None:
    """Counts a render or depth request against the key's renders per second (429 over it)."""
    setattr(request.state, STATE_KEY, headers_of(_services(request).quotas.admit_render(owner)))


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
    **ERRORS_READY,
    **too_many("renders per second (code render_rate_limited)"),
    503: {"model": ErrorBody, "description": "all render slots taken (code renderer_busy): retry after Retry-After"},
}

router = APIRouter()


# -- helpers --------------------------------------------------------------------------------------


def _iso(t: float | None) -> str | None:
    return None if t is None else datetime.fromtimestamp(t, UTC).isoformat().replace("+00:00", "Z")


def scene_out(rec: SceneRecord) -> SceneOut:
    base = f"/v1/scenes/{rec.id}"
    error = JobError(code=rec.error_code, message=rec.error_message or "") if rec.error_code else None
    return SceneOut(
        id=rec.id,
        status=rec.status,
        progress=round(rec.progress, 4),
        eta_seconds=rec.eta_seconds,
        detail=rec.detail,
        error=error,
        options=SceneOptions(**rec.options),
        images=rec.upload_names,
        created_at=_iso(rec.created_at) or "",
        updated_at=_iso(rec.updated_at) or "",
        started_at=_iso(rec.started_at),
        finished_at=_iso(rec.finished_at),
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


def _scene(svc: Services, scene_id: str, owner: str) -> SceneRecord:
    rec = svc.store.get(scene_id, owner)
    if rec is None:
        raise not_found()
    return rec


def _ready_scene(svc: Services, scene_id: str, owner: str) -> SceneRecord:
    rec = _scene(svc, scene_id, owner)
    if rec.status != "ready":
        raise APIError(409, "scene_not_ready", f"the scene is {rec.status}", {"status": rec.status})
    return rec


def negotiate(accept: str | None, offered: list[str]) -> str | None:
    """The offered media type the Accept header prefers (q-values, type/* and */*; ties go to
    the earlier offer), or None when it accepts none of them."""
    if not accept:
        return offered[0]
    prefs = []
    for entry in accept.split(","):
        kind, *params = (p.strip() for p in entry.split(";"))
        q = 1.0
        for p in params:
            if p.startswith("q="):
                try:
                    q = float(p[2:])
                except ValueError:
                    q = 0.0
        prefs.append((kind.lower(), q))
    best, best_q = None, 0.0
    for media in offered:
        q = max((q for kind, q in prefs if kind in (media, media.split("/")[0] + "/*", "*/*")), default=0.0)
        if q > best_q:
            best, best_q = media, q
    return best


def _camera(body: RenderCamera, settings: Settings) -> tuple[np.ndarray, np.ndarray, int, int]:
    """K [3, 3] and world_from_cam [4, 4] in the OpenCV convention, width, height."""
    from cmc.cameras import CameraError, camera_file_from_dict

    if body.w * body.h > settings.max_render_pixels:
        raise APIError(422, "render_too_large", f"w * h must be at most {settings.max_render_pixels} pixels")
    frame = body.model_dump(exclude_none=True)
    data = {k: v for k, v in frame.items() if k != "transform_matrix"}
    data["frames"] = [{"file_path": "render", "transform_matrix": frame["transform_matrix"]}]
    try:
        cams = camera_file_from_dict(data).cameras
    except CameraError as e:
        raise APIError(422, "invalid_camera", str(e).replace("frame 0: ", "")) from None
    return cams.K[0], cams.world_from_cam[0], body.w, body.h


# -- scenes ---------------------------------------------------------------------------------------

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
                            "description": "optional JSON, e.g. {\"preset\": \"fast\", \"steps\": 400, "
                            "\"resolution\": 504, \"seed\": 0} (see SceneOptions)",
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
    s = svc.settings
    try:
        with svc.storage.scratch() as tmp:  # checked here, then stored as {scene_id}/uploads/
            staged = tmp / "uploads"
            staged.mkdir()
            upload = await receive_upload(request, s, staged)
            if idempotency_key:
                existing = await run_in_threadpool(svc.store.find_by_idempotency_key, owner, idempotency_key)
                if existing is not None:
                    if existing.request_digest != upload.digest:
                        raise APIError(
                            409, "idempotency_conflict", "this Idempotency-Key was used for a different upload"
                        )
                    return _created(existing, replayed=True)
            stored = await asyncio.wrap_future(svc.intake.submit(check_images, upload, s))
            options = parse_options(upload, s)
            callback_url = await run_in_threadpool(parse_callback_url, upload, s)
            cameras = await run_in_threadpool(parse_cameras, upload, stored)
            if cameras is not None:
                (staged / "cameras.json").write_text(json.dumps(cameras))
            await run_in_threadpool(svc.storage.publish, f"{scene_id}/uploads", staged)
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
        raise APIError(409, "idempotency_conflict", str(e)) from None
    except BaseException:
        svc.storage.delete_scene(scene_id)
        raise
    if not created:  # a concurrent retry with the same key won the race
        svc.storage.delete_scene(scene_id)
        return _created(rec, replayed=True)
    try:
        svc.queue.submit(rec.id, "poses")
    except Exception:
        log.exception("could not queue scene %s", rec.id)
        svc.store.purge(rec.id)
        svc.storage.delete_scene(rec.id)
        raise APIError(503, "queue_unavailable", "the job queue is unavailable; retry shortly") from None
    return _created(rec, replayed=False)


def _created(rec: SceneRecord, replayed: bool) -> Response:
    headers = {"Location": f"/v1/scenes/{rec.id}"}
    if replayed:
        headers["Idempotent-Replayed"] = "true"
    return JSONResponse(scene_out(rec).model_dump(mode="json"), status_code=202, headers=headers)


@router.get("/v1/scenes/{scene_id}", response_model=SceneOut, responses=ERRORS, summary="Job status of a scene")
def get_scene(scene_id: SceneId, svc: Svc, owner: Owner) -> SceneOut:
    return scene_out(_scene(svc, scene_id, owner))


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
            raise APIError(422, "invalid_cursor", "cursor is not one this API returned") from None
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
    _scene(svc, scene_id, owner)
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
    from cmc.cameras import CameraFile, camera_file_to_dict, load_camera_file

    rec = _scene(svc, scene_id, owner)
    with svc.storage.reading(f"{scene_id}/scene/cameras.json") as path:
        if rec.phase == "poses" or not path.exists():
            message = f"camera poses are not estimated yet ({rec.status})"
            raise APIError(409, "scene_not_ready", message, {"status": rec.status})
        cf = load_camera_file(path)
    # working images are named after our storage names; answer with the client's names
    by_stem = {f.rsplit(".", 1)[0]: name for f, name in zip(rec.upload_files, rec.upload_names, strict=True)}
    names = [by_stem.get(p.rsplit("/", 1)[-1].rsplit(".", 1)[0], p) for p in cf.file_paths]
    return camera_file_to_dict(CameraFile(cf.cameras, names, cf.near_far), convention)


@router.get(
    "/v1/scenes/{scene_id}/camera-path",
    response_model=CameraPath,
    responses=ERRORS_READY,
    summary="Novel cameras along a path through the capture (the videos' paths), each a render body",
)
def get_camera_path(
    scene_id: SceneId,
    svc: Svc,
    owner: Owner,
    path: PathName = "orbit",
    frames: Annotated[int, Query(ge=1, le=1000, description="cameras along the closed path")] = 30,
    convention: Literal["opengl", "opencv"] = "opengl",
) -> CameraPath:
    from cmc.camera_paths import baked_path_cameras
    from cmc.cameras import CameraFile, camera_file_to_dict

    _ready_scene(svc, scene_id, owner)
    manifest = json.loads(svc.storage.read_bytes(f"{scene_id}/baked/mpi.json"))
    cams = baked_path_cameras(manifest, path, frames)
    data = camera_file_to_dict(CameraFile(cams, [path] * len(cams)), convention)
    size = {"w": data["w"], "h": data["h"], "convention": convention}
    bodies = [RenderCamera(**{k: v for k, v in f.items() if k != "file_path"}, **size) for f in data["frames"]]
    return CameraPath(path=path, frames=bodies)


@router.post(
    "/v1/scenes/{scene_id}/render",
    responses={
        **ERRORS_RENDER,
        406: {"model": ErrorBody, "description": "Accept names neither image/png nor image/jpeg"},
        200: {
            "content": {"image/png": {}, "image/jpeg": {}},
            "description": "the rendered view",
            "headers": RATE_LIMIT_HEADERS,
        },
    },
    response_class=Response,
    summary="Render the scene from any camera (PNG or JPEG by Accept)",
)
async def render_view(
    scene_id: SceneId,
    camera: RenderCamera,
    svc: Svc,
    owner: Owner,
    _: Annotated[None, RenderQuota],
    accept: Annotated[str | None, Header()] = None,
) -> Response:
    media = negotiate(accept, ["image/png", "image/jpeg"])
    if media is None:
        raise APIError(406, "not_acceptable", "this endpoint returns image/png or image/jpeg")
    await run_in_threadpool(_ready_scene, svc, scene_id, owner)
    K, pose, w, h = _camera(camera, svc.settings)
    body = await svc.render_queue.run(lambda: encode_image(svc.renders.render(scene_id, K, pose, w, h).rgb, media))
    return Response(body, media_type=media, headers={"Cache-Control": "no-store"})


@router.post(
    "/v1/scenes/{scene_id}/depth",
    responses={
        **ERRORS_RENDER,
        406: {"model": ErrorBody, "description": "Accept names neither image/png nor application/x-npy"},
        200: {
            "content": {"image/png": {}, "application/x-npy": {}},
            "description": "16-bit PNG (depth = value x Depth-Scale header, scene units, 0 = no surface), "
            "float32 .npy (scene units), or with preview=true an 8-bit colour map",
            "headers": RATE_LIMIT_HEADERS,
        },
    },
    response_class=Response,
    summary="Depth map (target-camera z, scene units) for any camera",
)
async def render_depth(
    scene_id: SceneId,
    camera: RenderCamera,
    svc: Svc,
    owner: Owner,
    _: Annotated[None, RenderQuota],
    preview: Annotated[bool, Query(description="an 8-bit colour map for people instead of the data")] = False,
    accept: Annotated[str | None, Header()] = None,
) -> Response:
    media = "image/png" if preview else negotiate(accept, ["image/png", "application/x-npy"])
    if media is None:
        raise APIError(406, "not_acceptable", "this endpoint returns image/png or application/x-npy")
    await run_in_threadpool(_ready_scene, svc, scene_id, owner)
    K, pose, w, h = _camera(camera, svc.settings)

    def draw() -> tuple[Rendered, bytes]:
        out = svc.renders.render(scene_id, K, pose, w, h)
        if preview:
            return out, encode_depth_preview(out.depth, out.near, out.far)
        if media == "image/png":
            return out, encode_depth_png16(out.depth, out.far)
        return out, encode_depth_npy(out.depth)

    out, body = await svc.render_queue.run(draw)
    headers = {"Cache-Control": "no-store", "Depth-Units": "scene"}
    headers.update({"Depth-Near": f"{out.near:.9g}", "Depth-Far": f"{out.far:.9g}"})
    if media == "image/png" and not preview:
        headers["Depth-Scale"] = f"{depth_scale(out.far):.9g}"
    return Response(body, media_type=media, headers=headers)


@router.get(
    "/v1/scenes/{scene_id}/mpi",
    responses={**ERRORS_READY, 200: {"description": "mpi.json of the baked cmc-mpi folder"}},
    summary="The baked MPI's manifest (atlases at /v1/scenes/{id}/mpi/{atlas})",
)
def get_mpi(scene_id: SceneId, svc: Svc, owner: Owner) -> Response:
    _ready_scene(svc, scene_id, owner)
    return Response(svc.storage.read_bytes(f"{scene_id}/baked/mpi.json"), media_type="application/json")


@router.get(
    "/v1/scenes/{scene_id}/mpi/{name}",
    responses={
        **ERRORS_READY,
        **FROM_BUCKET,
        200: {"content": {"image/png": {}, "application/json": {}}, "description": "a file"},
    },
    summary="A file of the baked MPI: mpi.json or an atlas it names",
)
def get_mpi_file(scene_id: SceneId, name: str, svc: Svc, owner: Owner) -> Response:
    _ready_scene(svc, scene_id, owner)
    manifest = svc.storage.read_bytes(f"{scene_id}/baked/mpi.json")
    if name == "mpi.json":
        return Response(manifest, media_type="application/json")
    atlases = {m["atlas"] for m in json.loads(manifest)["mpis"]}
    if name not in atlases:  # only names the manifest lists; never a client-built path
        raise not_found("file")
    return file_response(svc.storage, f"{scene_id}/baked/{name}", "image/png")


@router.get(
    "/v1/scenes/{scene_id}/export.glb",
    responses={
        **ERRORS_READY,
        **FROM_BUCKET,
        200: {"content": {"model/gltf-binary": {}}, "description": "glTF 2.0 binary: textured planes and cameras"},
    },
    response_class=Response,
    summary="The scene as glTF (.glb): one MPI's planes as alpha-blended textured quads, and the input cameras",
)
async def export_glb(
    scene_id: SceneId,
    svc: Svc,
    owner: Owner,
    mpi: Annotated[
        int | None, Query(ge=0, description="which input view's MPI (default: the one nearest the mean camera)")
    ] = None,
) -> Response:
    from cmc.gltf import export_glb as build
    from cmc.gltf import nearest_mpi

    rec = await run_in_threadpool(_ready_scene, svc, scene_id, owner)
    manifest = json.loads(svc.storage.read_bytes(f"{scene_id}/baked/mpi.json"))
    count = len(manifest["mpis"])
    if mpi is not None and mpi >= count:
        raise APIError(422, "invalid_mpi", f"mpi must be 0 to {count - 1}: the scene has {count} input views")
    index = nearest_mpi(manifest) if mpi is None else mpi
    key = f"{scene_id}/exports/mpi_{index:02d}.glb"
    if not svc.storage.exists(key):  # built once per MPI, then served from storage

        def write() -> None:
            names = rec.upload_names if len(rec.upload_names) == count else None  # the photos' names
            with svc.storage.reading(f"{scene_id}/baked") as folder:
                data, _ = build(folder, index, names)
            svc.storage.write_bytes(key, data)

        await svc.render_queue.run(write)
    headers = {"Cache-Control": "private"}
    return file_response(svc.storage, key, "model/gltf-binary", f"{scene_id}.glb", headers)


VIDEO_RESEND_AFTER_S = 600  # a build whose state was not updated for this long died: send it again


@router.get(
    "/v1/scenes/{scene_id}/video",
    responses={
        **ERRORS_READY,
        **FROM_BUCKET,
        200: {"content": {"video/mp4": {}}, "description": "H.264 MP4 of the camera path"},
        202: {"model": VideoBuilding, "description": "being rendered: ask again after Retry-After seconds"},
        500: {"model": ErrorBody, "description": "rendering failed (code video_failed); asking again retries"},
    },
    response_class=Response,
    summary="A camera-path video (spiral, orbit or dolly through the capture), built once and cached",
)
def get_video(
    scene_id: SceneId,
    svc: Svc,
    owner: Owner,
    path: PathName = "spiral",
) -> Response:
    _ready_scene(svc, scene_id, owner)
    mp4, state_key = video_keys(scene_id, path)
    if svc.storage.exists(mp4):
        return file_response(svc.storage, mp4, "video/mp4", headers={"Cache-Control": "private"})
    state = json.loads(svc.storage.read_bytes(state_key)) if svc.storage.exists(state_key) else None
    if state is not None and "error" in state:
        svc.storage.delete(state_key)  # the next request tries again
        raise APIError(500, "video_failed", f"rendering the {path} video failed: {state['error']}")
    if state is None or time.time() - state["updated_at"] > VIDEO_RESEND_AFTER_S:
        state = {"progress": 0.0, "updated_at": time.time()}
        svc.storage.write_bytes(state_key, json.dumps(state).encode())
        svc.queue.submit_video(scene_id, path)
    body = VideoBuilding(progress=round(float(state["progress"]), 3))
    return JSONResponse(body.model_dump(), status_code=202, headers={"Retry-After": "5"})


@router.get(
    "/v1/scenes/{scene_id}/webhooks",
    response_model=WebhookLog,
    responses=ERRORS,
    summary="The scene's webhook deliveries: every event, every try and its outcome",
)
def get_webhooks(scene_id: SceneId, svc: Svc, owner: Owner) -> WebhookLog:
    _scene(svc, scene_id, owner)
    deliveries = [
        WebhookDelivery(
            id=d.id,
            type=d.event,
            status=d.status,  # type: ignore[arg-type]
            url=d.url,
            created_at=_iso(d.created_at) or "",
            delivered_at=_iso(d.delivered_at),
            next_attempt_at=_iso(d.next_attempt_at) if d.status == "pending" else None,
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
        raise APIError(404, "webhooks_not_configured", "this server sends no webhooks (CMC_WEBHOOK_SECRET is not set)")
    return WebhookSecret(
        secret=owner_secret(svc.settings.webhook_secret, owner),
        signature_header=SIGNATURE_HEADER,
        timestamp_header=TIMESTAMP_HEADER,
        id_header=ID_HEADER,
        scheme="v1=hex(HMAC-SHA256(secret, timestamp + '.' + raw body))",
    )


@cache
def _viewer_html() -> str:
    return (Path(__file__).resolve().parent / "static" / "viewer.html").read_text()


@router.get(
    "/v1/scenes/{scene_id}/viewer",
    response_class=HTMLResponse,
    summary="The WebGL2 viewer page (holds no data and needs no key; give one as #key=... in the URL)",
)
def viewer(scene_id: SceneId) -> Response:
    del scene_id  # the page reads it from its own URL
    csp = "default-src 'none'; script-src 'unsafe-inline'; style-src 'unsafe-inline'; connect-src 'self'; img-src data:"
    return HTMLResponse(_viewer_html(), headers={"Content-Security-Policy": csp, "Cache-Control": "no-cache"})


# -- operations -------------------------------------------------------------------------------------


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
        raise APIError(503, "unavailable", f"not ready: {', '.join(failed)}", checks)
    return JSONResponse(Health(status="ready", checks=checks).model_dump())


@router.get(
    "/metrics",
    response_class=Response,
    responses={200: {"content": {"text/plain": {}}, "description": "Prometheus text format"}},
    summary="Prometheus metrics",
)
def metrics(svc: Svc) -> Response:
    return Response(svc.metrics.export(), media_type="text/plain; version=0.0.4; charset=utf-8")
