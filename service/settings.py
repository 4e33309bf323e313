"""Service configuration: one ``Settings`` object, read from ``CMC_*`` environment variables.

Built by :func:`load_settings` when an app or worker starts (never at import time), so tests
and processes each get their own. Every field's env var is ``CMC_`` + the field name in
capitals, e.g. ``CMC_DATABASE_URL``; ``.env.example`` lists the ones deployments set.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

MB = 1 << 20


class Settings(BaseSettings):
    """Settings shared by the API, the Celery workers and the embedded runner."""

    model_config = SettingsConfigDict(env_prefix="CMC_", extra="ignore")

    # -- where things live ------------------------------------------------------------------
    data_dir: Path = Field(Path("cmc-data"), description="root for the default database and storage")
    database_url: str = Field("", description="SQLAlchemy URL; default: SQLite file in data_dir")
    migrate_on_start: bool = Field(
        True,
        description="migrate the database schema when the API or a worker starts (service.db.migrate); the "
        "deployment turns this off and runs the compose service 'migrate' once instead",
    )
    storage_dir: Path | None = Field(None, description="artifact storage root; default data_dir/storage")
    storage: str = Field(
        "",
        description="s3://bucket/prefix: artifacts in an S3-compatible bucket (credentials from the usual AWS_* "
        "variables), working copies in data_dir/work; empty: the local folder storage_dir",
    )
    s3_endpoint_url: str = Field("", description="S3 API endpoint (MinIO, other clouds); empty: AWS's")
    s3_public_endpoint_url: str = Field(
        "", description="endpoint in the presigned download URLs clients get; empty: s3_endpoint_url"
    )
    s3_region: str = Field("", description="bucket region; empty: from AWS_REGION / AWS_DEFAULT_REGION or us-east-1")
    s3_url_seconds: int = Field(3600, ge=60, le=7 * 24 * 3600, description="lifetime of presigned download URLs")
    s3_multipart_bytes: int = Field(
        16 * MB, ge=5 * MB, description="files from this size up are uploaded in parts of this size (checkpoints)"
    )
    broker_url: str = Field("", description="Celery broker (redis://...); empty: no Celery (embedded runner)")
    cpu_queue: str = Field("cpu", description="Celery queue of pose estimation")
    gpu_queue: str = Field("gpu", description="Celery queue of training and baking")

    # -- auth -------------------------------------------------------------------------------
    api_keys: str = Field("", description="comma-separated API keys (hashed on load, never stored)")
    api_keys_file: Path | None = Field(None, description="file of SHA-256 hex digests of API keys, one a line")
    allowed_hosts: str = Field(
        "", description="without API keys: host names accepted besides localhost, 127.0.0.1, [::1] (comma-separated)"
    )

    # -- upload limits ----------------------------------------------------------------------
    min_images: int = Field(3, ge=2, le=20)
    max_images: int = Field(3, ge=2, le=20)
    max_image_bytes: int = Field(25 * MB, ge=1024, description="bytes per uploaded image")
    max_image_pixels: int = Field(
        50_000_000,
        ge=1,
        description="pixels per uploaded image: a phone's 48 or 50 MP photo passes (8064 x 6048, 8160 x 6120); "
        "larger ones (the 108 and 200 MP modes of some phones) must be scaled down by the app",
    )
    decode_memory_bytes: int = Field(
        512 * MB,
        ge=16 * MB,
        description="bytes that photo decodes in one process may hold at once (upload checks, pose estimation): "
        "a decode waits until its estimate fits (cmc.data.images.decode_bytes: 4 to 20 bytes per pixel by format and "
        "mode, JPEGs decoded at reduced size); one larger than this runs alone",
    )
    max_cameras_bytes: int = Field(1 * MB, ge=1024, description="bytes of the optional cameras / options parts")
    max_json_bytes: int = Field(64 * 1024, ge=1024, description="bytes of any other request body (a render camera)")

    # -- jobs -------------------------------------------------------------------------------
    device: str = Field("auto", description="torch device for training: auto, cpu, cuda, cuda:N")
    max_steps: int = Field(50_000, ge=1, description="largest 'steps' option accepted")
    checkpoint_every: int = Field(0, ge=0, description="training steps between checkpoints; 0: the preset's")
    checkpoint_seconds: float = Field(
        60.0,
        gt=0,
        description="seconds of training between checkpoints at most (besides every checkpoint_every steps): "
        "a worker killed without warning loses no more than this",
    )
    preview_at: Annotated[list[float], NoDecode] = Field(
        [0.0, 0.1],
        description="shares of the training steps after which a job bakes a preview (at half the texel "
        "resolution) that render, depth, mpi and the viewer serve until a later preview or the final bake "
        "replaces it, comma-separated in the environment (0: right after the model build, from the plane "
        "sweep's start; 1 or more: none; empty: no preview)",
    )
    lease_seconds: float = Field(60.0, gt=0, description="a job whose worker is silent this long is re-queued")
    heartbeat_seconds: float = Field(1.0, gt=0, description="how often a running job reports and checks cancel")
    requeue_after_seconds: float = Field(
        7200.0, gt=0, description="re-send a queued job whose message no worker took for this long"
    )
    max_attempts: int = Field(3, ge=1, description="worker losses after which a job fails")
    poses_time_limit: float = Field(900.0, gt=0, description="seconds for pose estimation")
    train_time_limit: float = Field(6 * 3600.0, gt=0, description="seconds for training + baking")

    # -- rendering --------------------------------------------------------------------------
    render_cache_bytes: int = Field(
        2 << 30,
        ge=1,
        description="memory for loaded baked scenes (8-bit textures: about 195 MB each at 504x378 with 3 x 56 "
        "planes); the least recently used are dropped beyond it, never the one just loaded",
    )
    render_concurrency: int = Field(2, ge=1, description="renders computed at once (others wait)")
    render_threads: int = Field(
        1,
        ge=1,
        description="CPU threads per render; render_concurrency x render_threads should not exceed the cores "
        "(on 2 busy cores, 2 renders of 1 thread each served 15 % more renders per second than 1 of 2 threads)",
    )
    render_queue: int = Field(
        32,
        ge=0,
        description="renders waiting for one of those; more get 503 + Retry-After (32: about 2 s of renders "
        "on 2 cores; a shorter queue sends clients away to come back later, which stretched the tail)",
    )
    max_render_pixels: int = Field(4_000_000, ge=1, description="largest render (width x height)")

    # -- webhooks (service/webhooks.py) -----------------------------------------------------
    webhook_secret: str = Field(
        "",
        description="master secret of webhook signatures: each API key signs with its own secret derived from it "
        "(GET /v1/webhooks/secret); empty: uploads with a callback_url are refused",
    )
    webhook_allow_private: bool = Field(
        False,
        description="accept callback URLs that resolve to loopback, private, link-local or other non-public "
        "addresses (off: refused, against SSRF; on for tests and private deployments)",
    )
    webhook_max_attempts: int = Field(10, ge=1, le=50, description="tries of a webhook delivery before giving up")
    webhook_backoff_seconds: float = Field(
        10.0, gt=0, description="wait before the second try; doubled after each failed try"
    )
    webhook_backoff_max_seconds: float = Field(3600.0, gt=0, description="longest wait between two tries")
    webhook_timeout_seconds: float = Field(10.0, gt=0, description="seconds a receiver has to answer one try")
    webhook_queue: str = Field("webhooks", description="Celery queue of webhook deliveries")

    # -- quotas and rate limits, per API key (0: no limit; nothing is limited without API keys) ------
    # Over a limit: 429 with Retry-After and RateLimit-* (service/quotas.py). Counted in Redis
    # (broker_url) in celery mode, shared by every API replica; in this process's memory embedded.
    max_concurrent_jobs: int = Field(
        4, ge=0, description="unfinished scenes (queued or running) per API key; a further upload gets 429"
    )
    max_jobs_per_day: int = Field(100, ge=0, description="scenes an API key may create in any 24 hours (rolling)")
    max_renders_per_second: int = Field(
        10, ge=0, description="render and depth requests per API key in any one second (together)"
    )

    # -- embedded mode ----------------------------------------------------------------------
    mode: Literal["embedded", "celery"] = Field(
        "embedded", description="embedded: jobs run in the API process; celery: sent to workers"
    )

    @field_validator("preview_at", mode="before")
    @classmethod
    def _shares(cls, value: object) -> object:
        """A number or a comma-separated string (the environment's form) as a list."""
        if isinstance(value, str):
            return value.replace(",", " ").split()
        if isinstance(value, int | float):
            return [value]
        return value

    @field_validator("preview_at")
    @classmethod
    def _sorted_shares(cls, shares: list[float]) -> list[float]:
        if any(not share >= 0 for share in shares):
            raise ValueError(f"preview shares must be >= 0, got {shares}")
        return sorted(set(shares))

    @model_validator(mode="after")
    def _check(self) -> Settings:
        if self.min_images > self.max_images:
            raise ValueError(f"min_images ({self.min_images}) > max_images ({self.max_images})")
        if self.mode == "celery" and not self.broker_url:
            raise ValueError("CMC_MODE=celery needs CMC_BROKER_URL")
        if self.storage and not re.fullmatch(r"s3://[a-z0-9][a-z0-9.-]{1,61}[a-z0-9](/[^/]+)*/?", self.storage):
            raise ValueError(f"CMC_STORAGE must be empty or s3://bucket[/prefix], got {self.storage!r}")
        return self

    @property
    def resolved_database_url(self) -> str:
        return self.database_url or f"sqlite:///{(self.data_dir / 'cmc.db').resolve()}"

    @property
    def resolved_storage_dir(self) -> Path:
        return (self.storage_dir or self.data_dir / "storage").resolve()

    @property
    def work_dir(self) -> Path:
        """Local working copies of artifacts kept in S3 (per job, removed after it)."""
        return (self.data_dir / "work").resolve()

    @property
    def max_request_bytes(self) -> int:
        """Largest upload request: every image at its limit plus the small parts."""
        return self.max_images * self.max_image_bytes + 2 * self.max_cameras_bytes + 64 * 1024


def load_settings(**overrides: object) -> Settings:
    """Settings from the environment, with keyword overrides (tests, command-line flags)."""
    return Settings(**overrides)  # type: ignore[arg-type]
