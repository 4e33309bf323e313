"""Request and response bodies of the API (pydantic); internal record fields never leak."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from cmc.config import Preset, preset_config
from service.db.rows import Status
from service.errors import ErrorCode


class SceneOptions(BaseModel):
    """The optional ``options`` JSON part of an upload."""

    model_config = ConfigDict(extra="forbid")

    preset: Preset = Field(
        "fast",
        description=f"fast: {preset_config('fast').steps} steps, under 3 minutes on 2 CPU cores; paper: the "
        f"paper's MLP, {preset_config('paper').steps} steps, about 30 minutes on an H100",
    )
    steps: int | None = Field(None, ge=1, description="training steps (default: the preset's)")
    resolution: int = Field(504, ge=64, le=2016, description="long side of the working images, pixels")
    seed: int = Field(0, ge=0, le=2**31 - 1, description="random seed (poses and training)")


class ErrorDetail(BaseModel):
    code: ErrorCode = Field(description="stable, machine-readable")
    message: str = Field(description="for people")
    details: Any = None


class ErrorBody(BaseModel):
    error: ErrorDetail


class JobError(BaseModel):
    code: ErrorCode = Field(
        description="pose_estimation_failed, invalid_images, invalid_cameras, training_failed, "
        "time_limit_exceeded, worker_lost or internal_error"
    )
    message: str


class SceneLinks(BaseModel):
    self: str
    cameras: str
    render: str
    depth: str
    mpi: str
    viewer: str
    video: str
    camera_path: str
    webhooks: str
    export_glb: str


class SceneOut(BaseModel):
    id: str
    status: Status
    progress: float = Field(description="progress of the current stage, 0-1")
    eta_seconds: float | None = Field(
        description="estimated seconds until the scene is ready: what is left of the current stage plus the "
        "stages after it (null while queued; 0 when ready). Until training has run its first steps, training "
        "is estimated at a reference CPU's speed"
    )
    preview_ready: bool = Field(
        description="while the scene trains: render, depth, mpi and the viewer already answer from a preview "
        "its job baked part way through training (their Scene-Stage header says 'preview') until the final "
        "bake replaces it; false once the scene is ready (then they answer from the final bake)"
    )
    preview_step: int | None = Field(
        None,
        description="the training step of the preview they answer from (null without one): a job bakes one "
        "right after its model build and a sharper one a few steps later, each replacing the last, so a "
        "client showing a preview reloads the MPI when this changes",
    )
    detail: str | None = Field(description="what the job is doing, for people")
    error: JobError | None = Field(description="set when status is 'failed'")
    options: SceneOptions
    images: list[str] = Field(description="the uploaded photos' file names")
    created_at: str = Field(description="ISO 8601, UTC")
    updated_at: str
    started_at: str | None
    finished_at: str | None
    links: SceneLinks


class SceneList(BaseModel):
    items: list[SceneOut]
    next_cursor: str | None = Field(description="pass as ?cursor= for the next page; null on the last page")


class RenderCamera(BaseModel):
    """A camera to render, in the shape of one frame of the cameras file (transforms.json)."""

    model_config = ConfigDict(extra="forbid")

    transform_matrix: list[list[float]] = Field(description="4x4 (or 3x4) camera-to-world, row-major")
    fl_x: float = Field(gt=0, description="focal length in pixels")
    fl_y: float | None = Field(None, gt=0, description="default: fl_x")
    cx: float | None = Field(None, description="principal point, pixels from the left edge (default: w / 2)")
    cy: float | None = Field(None, description="pixels from the top edge (default: h / 2)")
    w: int = Field(gt=0, le=8192, description="image width, pixels")
    h: int = Field(gt=0, le=8192, description="image height, pixels")
    convention: Literal["opengl", "opencv"] = Field(
        "opengl", description="axes: opengl (x right, y up, z back; ARKit) or opencv (x right, y down, z forward)"
    )


# The camera paths of cmc.geometry.camera_paths (PathKind), spelled here so the API need not import cmc.
PathName = Literal["spiral", "orbit", "dolly"]


class CameraPath(BaseModel):
    path: PathName
    frames: list[RenderCamera] = Field(
        description="cameras along the path, in order; each is a body for /render and /depth as it is"
    )


class Health(BaseModel):
    status: str
    checks: dict[str, str] = Field(default_factory=dict)


class VideoBuilding(BaseModel):
    status: Literal["building"] = "building"
    progress: float = Field(description="frames rendered so far, 0-1")


class WebhookAttempt(BaseModel):
    at: str = Field(description="ISO 8601, UTC")
    status_code: int | None = Field(description="the receiver's HTTP status; null when no answer came")
    error: str | None = Field(description="why the try did not count (null: delivered)")
    duration_ms: float


class WebhookDelivery(BaseModel):
    id: str = Field(description="the idempotency id: the body's id and the CMC-Webhook-Id header")
    type: str = Field(description="scene.ready, scene.failed, video.ready or video.failed")
    status: Literal["pending", "delivered", "failed"] = Field(
        description="pending: tried again at next_attempt_at; failed: every try failed, given up"
    )
    url: str
    created_at: str
    delivered_at: str | None
    next_attempt_at: str | None
    attempts: list[WebhookAttempt] = Field(description="every try, oldest first")
    body: dict[str, Any] = Field(description="the JSON body sent on every try")


class WebhookLog(BaseModel):
    callback_url: str | None = Field(description="where the scene's webhooks go (null: none)")
    deliveries: list[WebhookDelivery] = Field(description="oldest first")


class WebhookSecret(BaseModel):
    secret: str = Field(description="HMAC-SHA256 key of this API key's webhook signatures")
    signature_header: str
    timestamp_header: str
    id_header: str
    scheme: str = Field(description="how the signature is made")
