"""One JSON error shape everywhere: ``{"error": {"code", "message", "details"}}``.

``code`` is stable (clients branch on it), ``message`` is for people, ``details`` is optional
structured context (e.g. the invalid fields of a 422).
"""

from __future__ import annotations

import logging
from enum import StrEnum
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

log = logging.getLogger("cmc.api")


class ErrorCode(StrEnum):
    """Every ``code`` a client can see, in an API error or in a failed job's ``error`` (OpenAPI
    lists them). Stable: clients branch on them; add, never rename."""

    # generic HTTP answers
    bad_request = "bad_request"
    unauthorized = "unauthorized"
    forbidden = "forbidden"
    not_found = "not_found"
    method_not_allowed = "method_not_allowed"
    not_acceptable = "not_acceptable"
    conflict = "conflict"
    payload_too_large = "payload_too_large"
    unsupported_media_type = "unsupported_media_type"
    validation_error = "validation_error"
    too_many_requests = "too_many_requests"
    unavailable = "unavailable"
    internal_error = "internal_error"
    error = "error"  # an HTTP status without a code of its own
    # requests
    cross_site_request = "cross_site_request"
    host_not_allowed = "host_not_allowed"
    idempotency_conflict = "idempotency_conflict"
    invalid_callback_url = "invalid_callback_url"
    webhooks_not_configured = "webhooks_not_configured"
    invalid_cursor = "invalid_cursor"
    invalid_options = "invalid_options"
    queue_unavailable = "queue_unavailable"
    # uploads (and the jobs that read them)
    too_few_images = "too_few_images"
    too_many_images = "too_many_images"
    unsupported_image = "unsupported_image"
    image_too_large = "image_too_large"
    invalid_images = "invalid_images"
    invalid_cameras = "invalid_cameras"
    # views
    scene_not_ready = "scene_not_ready"
    invalid_mpi = "invalid_mpi"
    render_too_large = "render_too_large"
    renderer_busy = "renderer_busy"
    video_failed = "video_failed"
    # quotas and rate limits (429)
    render_rate_limited = "render_rate_limited"
    daily_job_quota_exceeded = "daily_job_quota_exceeded"
    too_many_concurrent_jobs = "too_many_concurrent_jobs"
    # failed jobs
    pose_estimation_failed = "pose_estimation_failed"
    training_failed = "training_failed"
    time_limit_exceeded = "time_limit_exceeded"
    worker_lost = "worker_lost"


_HTTP_CODES = {
    400: ErrorCode.bad_request,
    401: ErrorCode.unauthorized,
    403: ErrorCode.forbidden,
    404: ErrorCode.not_found,
    405: ErrorCode.method_not_allowed,
    406: ErrorCode.not_acceptable,
    409: ErrorCode.conflict,
    413: ErrorCode.payload_too_large,
    415: ErrorCode.unsupported_media_type,
    422: ErrorCode.validation_error,
    429: ErrorCode.too_many_requests,
    503: ErrorCode.unavailable,
}


class APIError(Exception):
    """Raise from a route to answer with the JSON error shape."""

    def __init__(self, status: int, code: ErrorCode, message: str, details: Any = None, headers: dict | None = None):
        super().__init__(message)
        self.status, self.code, self.message, self.details, self.headers = status, code, message, details, headers


def error_response(status: int, code: ErrorCode, message: str, details: Any = None, headers: dict | None = None):
    body = {"error": {"code": code, "message": message, "details": details}}
    return JSONResponse(body, status_code=status, headers=headers)


def not_found(what: str = "scene") -> APIError:
    return APIError(404, ErrorCode.not_found, f"no such {what}")


def install_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(APIError)
    async def _api_error(_: Request, e: APIError):
        return error_response(e.status, e.code, e.message, e.details, e.headers)

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(_: Request, e: StarletteHTTPException):
        code = _HTTP_CODES.get(e.status_code, ErrorCode.error)
        message = e.detail if isinstance(e.detail, str) else code.replace("_", " ")
        return error_response(e.status_code, code, message, None, getattr(e, "headers", None))

    @app.exception_handler(RequestValidationError)
    async def _validation_error(request: Request, e: RequestValidationError):
        details = [
            {"field": ".".join(str(p) for p in err.get("loc", ())), "problem": err.get("msg", "")} for err in e.errors()
        ]
        message = "the request is not valid"
        body_not_json = any(tuple(err.get("loc", ()))[:1] == ("body",) for err in e.errors()) and not (
            request.headers.get("content-type", "").split(";")[0].strip().lower().endswith("json")
        )
        if body_not_json:  # FastAPI reads a body it was not told is JSON as a string
            message = "the request body must be JSON, sent with Content-Type: application/json"
        return error_response(422, ErrorCode.validation_error, message, details)

    @app.exception_handler(Exception)
    async def _internal_error(request: Request, e: Exception):
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return error_response(500, ErrorCode.internal_error, "internal server error")
