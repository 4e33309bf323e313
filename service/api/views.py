"""View routes of a scene: render and depth from any camera, the baked MPI and camera paths (of a
ready scene, or of the preview its job publishes while it trains: ``Scene-Stage`` says which);
glTF export and videos (ready scenes only); the viewer page."""

from __future__ import annotations

import json
import logging
from functools import cache
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from fastapi import APIRouter, Header, Query, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import HTMLResponse, JSONResponse

from service.api.deps import (
    ERRORS_READY,
    ERRORS_RENDER,
    ERRORS_VIEWABLE,
    FROM_BUCKET,
    RATE_LIMIT_HEADERS,
    STAGE_HEADER,
    Owner,
    RenderQuota,
    SceneId,
    Services,
    Svc,
    ready_scene,
    stage_of,
    viewable_scene,
)
from service.errors import APIError, ErrorCode, not_found
from service.layout import SceneLayout
from service.negotiation import negotiate
from service.renders import (
    Rendered,
    depth_scale,
    encode_depth_npy,
    encode_depth_png16,
    encode_depth_preview,
    encode_image,
)
from service.schemas import (
    CameraPath,
    ErrorBody,
    PathName,
    RenderCamera,
    VideoBuilding,
)
from service.settings import Settings
from service.storage import StorageError, file_response

log = logging.getLogger("cmc.api")
router = APIRouter()

Coverage = Annotated[
    bool,
    Query(
        description="mark the pixels whose point no input photo saw (the view extrapolates there): an alpha "
        "channel in PNGs (0 there), NaN in .npy depth; not with JPEG"
    ),
]


def _camera(body: RenderCamera, settings: Settings) -> tuple[np.ndarray, np.ndarray, int, int]:
    """K [3, 3] and world_from_cam [4, 4] in the OpenCV convention, width, height."""
    from cmc.geometry.cameras import CameraError, camera_from_frame

    if body.w * body.h > settings.max_render_pixels:
        raise APIError(422, ErrorCode.render_too_large, f"w * h must be at most {settings.max_render_pixels} pixels")
    try:
        cams = camera_from_frame(body.model_dump(exclude_none=True))
    except CameraError as e:
        raise APIError(422, ErrorCode.invalid_cameras, str(e)) from None
    return cams.K[0], cams.world_from_cam[0], body.w, body.h


@router.get(
    "/v1/scenes/{scene_id}/camera-path",
    response_model=CameraPath,
    responses=ERRORS_VIEWABLE,
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
    from cmc.geometry.camera_paths import baked_path_cameras
    from cmc.geometry.cameras import CameraFile, camera_file_to_dict

    manifest = json.loads(_manifest(svc, scene_id, owner)[1])  # a preview's cameras are the final's
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
            "headers": {**RATE_LIMIT_HEADERS, **STAGE_HEADER},
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
    coverage: Coverage = False,
    accept: Annotated[str | None, Header()] = None,
) -> Response:
    media = negotiate(accept, ["image/png"] if coverage else ["image/png", "image/jpeg"])
    if media is None:
        formats = "image/png (with coverage=true)" if coverage else "image/png or image/jpeg"
        raise APIError(406, ErrorCode.not_acceptable, f"this endpoint returns {formats}")
    folder = await run_in_threadpool(viewable_scene, svc, scene_id, owner)
    K, pose, w, h = _camera(camera, svc.settings)

    def draw() -> tuple[str, bytes]:
        used, out = _render(svc, scene_id, owner, folder, K, pose, w, h, coverage)
        return used, encode_image(out.rgb, media, out.coverage)

    used, body = await svc.render_queue.run(draw)
    return Response(body, media_type=media, headers={"Cache-Control": "no-store", "Scene-Stage": stage_of(used)})


def _render(
    svc: Services,
    scene_id: str,
    owner: str,
    folder: str,
    K: np.ndarray,
    pose: np.ndarray,
    w: int,
    h: int,
    coverage: bool,
) -> tuple[str, Rendered]:
    """Render from storage folder ``folder``, or from the scene's current one if that folder
    went (a preview removed as a later preview or the final bake replaced it); returns the folder
    used and the render."""
    try:
        return folder, svc.renders.render(folder, K, pose, w, h, coverage)
    except FileNotFoundError:
        folder = viewable_scene(svc, scene_id, owner)
    try:
        return folder, svc.renders.render(folder, K, pose, w, h, coverage)
    except FileNotFoundError:
        raise APIError(409, ErrorCode.scene_not_ready, "the scene's bake is being replaced; retry") from None


@router.post(
    "/v1/scenes/{scene_id}/depth",
    responses={
        **ERRORS_RENDER,
        406: {"model": ErrorBody, "description": "Accept names neither image/png nor application/x-npy"},
        200: {
            "content": {"image/png": {}, "application/x-npy": {}},
            "description": "16-bit PNG (depth = value x Depth-Scale header, scene units, 0 = no surface), "
            "float32 .npy (scene units), or with preview=true an 8-bit colour map",
            "headers": {**RATE_LIMIT_HEADERS, **STAGE_HEADER},
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
    coverage: Coverage = False,
    accept: Annotated[str | None, Header()] = None,
) -> Response:
    media = "image/png" if preview else negotiate(accept, ["image/png", "application/x-npy"])
    if media is None:
        raise APIError(406, ErrorCode.not_acceptable, "this endpoint returns image/png or application/x-npy")
    folder = await run_in_threadpool(viewable_scene, svc, scene_id, owner)
    K, pose, w, h = _camera(camera, svc.settings)

    def draw() -> tuple[str, Rendered, bytes]:
        used, out = _render(svc, scene_id, owner, folder, K, pose, w, h, coverage)
        if preview:
            return used, out, encode_depth_preview(out.depth, out.near, out.far, out.coverage)
        if media == "image/png":
            return used, out, encode_depth_png16(out.depth, out.far, out.coverage)
        return used, out, encode_depth_npy(out.depth, out.coverage)

    used, out, body = await svc.render_queue.run(draw)
    headers = {"Cache-Control": "no-store", "Depth-Units": "scene", "Scene-Stage": stage_of(used)}
    headers.update({"Depth-Near": f"{out.near:.9g}", "Depth-Far": f"{out.far:.9g}"})
    if media == "image/png" and not preview:
        headers["Depth-Scale"] = f"{depth_scale(out.far):.9g}"
    return Response(body, media_type=media, headers=headers)


@router.get(
    "/v1/scenes/{scene_id}/mpi",
    responses={
        **ERRORS_VIEWABLE,
        200: {"description": "mpi.json of the baked cmc-mpi folder", "headers": STAGE_HEADER},
    },
    summary="The baked MPI's manifest (atlases at /v1/scenes/{id}/mpi/{atlas}); a preview's while the scene trains",
)
def get_mpi(scene_id: SceneId, svc: Svc, owner: Owner) -> Response:
    folder, manifest = _manifest(svc, scene_id, owner)
    return Response(manifest, media_type="application/json", headers={"Scene-Stage": stage_of(folder)})


def _manifest(svc: Services, scene_id: str, owner: str) -> tuple[str, bytes]:
    """The folder a scene's views come from (:func:`viewable_scene`) and its mpi.json."""
    for _ in range(2):  # a preview removed in between: the scene is ready now
        folder = viewable_scene(svc, scene_id, owner)
        try:
            return folder, svc.storage.read_bytes(f"{folder}/mpi.json")
        except StorageError:
            continue
    raise APIError(409, ErrorCode.scene_not_ready, "the scene's bake is being replaced; retry")


@router.get(
    "/v1/scenes/{scene_id}/mpi/{name}",
    responses={
        **ERRORS_VIEWABLE,
        **FROM_BUCKET,
        200: {
            "content": {"image/png": {}, "application/json": {}},
            "description": "a file",
            "headers": STAGE_HEADER,
        },
    },
    summary="A file of the baked MPI: mpi.json or an atlas it names; a preview's while the scene trains",
)
def get_mpi_file(scene_id: SceneId, name: str, svc: Svc, owner: Owner) -> Response:
    folder, manifest = _manifest(svc, scene_id, owner)
    stage = {"Scene-Stage": stage_of(folder)}
    if stage_of(folder) == "preview":  # the final bake's files will have these names: revalidate
        stage["Cache-Control"] = "no-cache"
    if name == "mpi.json":
        return Response(manifest, media_type="application/json", headers=stage)
    atlases = {m["atlas"] for m in json.loads(manifest)["mpis"]}
    if name not in atlases:  # only names the manifest lists; never a client-built path
        raise not_found("file")
    if stage_of(folder) == "preview" and not svc.storage.exists(f"{folder}/{name}"):
        raise APIError(409, ErrorCode.scene_not_ready, "a later bake replaced the preview; reload mpi.json")
    return file_response(svc.storage, f"{folder}/{name}", "image/png", headers=stage)


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
    from cmc.serving.gltf import export_glb as build
    from cmc.serving.gltf import nearest_mpi

    rec = await run_in_threadpool(ready_scene, svc, scene_id, owner)
    layout = SceneLayout(scene_id)
    manifest = json.loads(await run_in_threadpool(svc.storage.read_bytes, layout.manifest))
    count = len(manifest["mpis"])
    if mpi is not None and mpi >= count:
        raise APIError(422, ErrorCode.invalid_mpi, f"mpi must be 0 to {count - 1}: the scene has {count} input views")
    index = nearest_mpi(manifest) if mpi is None else mpi
    key = layout.export_glb(index)
    if not await run_in_threadpool(svc.storage.exists, key):  # built once per MPI, then served from storage

        def write() -> None:
            names = rec.upload_names if len(rec.upload_names) == count else None  # the photos' names
            with svc.storage.reading(layout.baked()) as folder:
                data, _ = build(folder, index, names)
            svc.storage.write_bytes(key, data)

        await svc.render_queue.run(write)
    headers = {"Cache-Control": "private"}
    return file_response(svc.storage, key, "model/gltf-binary", f"{scene_id}.glb", headers)


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
    ready_scene(svc, scene_id, owner)
    mp4 = SceneLayout(scene_id).video(path)
    job = svc.store.videos.get(scene_id, path)
    if (job is None or job.status == "ready") and svc.storage.exists(mp4):
        return file_response(svc.storage, mp4, "video/mp4", headers={"Cache-Control": "private"})
    if job is not None and job.status == "failed":
        svc.store.videos.forget(scene_id, path)  # the next request tries again
        raise APIError(500, ErrorCode.video_failed, f"rendering the {path} video failed: {job.error}")
    if job is None or job.status != "building":
        job, started = svc.store.videos.request(scene_id, path)
        if started:
            try:
                svc.queue.submit_video(scene_id, path)
            except Exception:  # the broker is down: the reaper sends it once the message is overdue
                log.warning("could not send video %s of %s", path, scene_id, exc_info=True)
    body = VideoBuilding(progress=round(float(job.progress), 3))
    return JSONResponse(body.model_dump(), status_code=202, headers={"Retry-After": "5"})


@cache
def _viewer_html() -> str:
    return (Path(__file__).resolve().parents[1] / "static" / "viewer.html").read_text()


@router.get(
    "/v1/scenes/{scene_id}/viewer",
    response_class=HTMLResponse,
    summary="The WebGL2 viewer page (holds no data and needs no key; give one as #key=... in the URL)",
)
def viewer(scene_id: SceneId) -> Response:
    del scene_id  # the page reads it from its own URL
    csp = "default-src 'none'; script-src 'unsafe-inline'; style-src 'unsafe-inline'; connect-src 'self'; img-src data:"
    return HTMLResponse(_viewer_html(), headers={"Content-Security-Policy": csp, "Cache-Control": "no-cache"})
