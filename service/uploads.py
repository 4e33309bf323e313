"""Scene uploads: a streaming multipart reader that enforces the limits as bytes arrive, and
the checks of what arrived (content-sniffed images, the cameras file, the options).

Parts of ``POST /v1/scenes`` (multipart/form-data):

* ``images`` (repeated): the photos. Written straight to a local folder under our own names
  (``00.jpg``...; the API then publishes it as ``{id}/uploads/``); the client's file name is
  kept as data only.
* ``cameras`` (optional): a transforms.json-style cameras file (see cmc.geometry.cameras).
* ``options`` (optional): JSON, :class:`service.schemas.SceneOptions`.
* ``callback_url`` (optional): where the scene's webhooks go (:mod:`service.webhooks`).

Limits (``Settings``): request bytes (checked against Content-Length, then counted), images per
request, bytes per image (counted while streaming: an oversized photo is cut off at the limit,
not after it arrived), bytes of the small parts; then pixels per image (from the header, before
decoding). Everything refused is answered 413 / 415 / 422 with the JSON error shape, and
nothing of a refused upload is kept.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO

from pydantic import ValidationError
from python_multipart.multipart import MultipartParser, parse_options_header
from starlette.requests import ClientDisconnect, Request

from service.errors import APIError, ErrorCode
from service.layout import ClientNames
from service.schemas import SceneOptions
from service.settings import Settings

if TYPE_CHECKING:
    from cmc.data.images import MemoryBudget

_EXTENSIONS = {"JPEG": ".jpg", "PNG": ".png", "WEBP": ".webp", "HEIF": ".heic"}


@dataclass
class ImagePart:
    filename: str  # the client's name (data, never a path)
    path: Path  # where we wrote it
    size: int = 0


@dataclass
class Upload:
    """What a scene upload carried (the photos written to the reader's folder)."""

    images: list[ImagePart] = field(default_factory=list)
    cameras: bytes | None = None
    options: bytes | None = None
    callback_url: bytes | None = None
    digest: str = ""  # SHA-256 over every part, for Idempotency-Key conflicts


class _Reader:
    """Callbacks for python-multipart's streaming parser, with the limits."""

    def __init__(self, settings: Settings, folder: Path):
        self.s, self.folder = settings, folder
        self.upload = Upload()
        self.sha = hashlib.sha256()
        self._header_field = b""
        self._header_value = b""
        self._headers: dict[bytes, bytes] = {}
        self._name = ""
        self._file: BinaryIO | None = None
        self._small: bytearray | None = None
        self._count = 0

    def callbacks(self) -> dict[str, Any]:
        return {
            "on_part_begin": self.on_part_begin,
            "on_header_field": lambda d, a, b: setattr(self, "_header_field", self._header_field + d[a:b]),
            "on_header_value": lambda d, a, b: setattr(self, "_header_value", self._header_value + d[a:b]),
            "on_header_end": self.on_header_end,
            "on_headers_finished": self.on_headers_finished,
            "on_part_data": self.on_part_data,
            "on_part_end": self.on_part_end,
        }

    def on_part_begin(self) -> None:
        self._headers, self._name, self._file, self._small, self._count = {}, "", None, None, 0

    def on_header_end(self) -> None:
        self._headers[self._header_field.lower()] = self._header_value
        self._header_field, self._header_value = b"", b""

    def on_headers_finished(self) -> None:
        _, params = parse_options_header(self._headers.get(b"content-disposition", b""))
        self._name = params.get(b"name", b"").decode("utf-8", "replace")
        self.sha.update(self._name.encode() + b"\0")
        if self._name == "images":
            images = self.upload.images
            if len(images) >= self.s.max_images:
                raise APIError(422, ErrorCode.too_many_images, f"send at most {self.s.max_images} images")
            filename = params.get(b"filename", b"").decode("utf-8", "replace")
            filename = Path(filename.replace("\\", "/")).name or f"image{len(images) + 1}"
            part = ImagePart(filename[:200], self.folder / f"{len(images):02d}.upload")
            images.append(part)
            self._file = part.path.open("wb")
        elif self._name in ("cameras", "options", "callback_url"):
            self._small = bytearray()
        # other parts are read (and counted) but ignored

    def on_part_data(self, data: bytes, start: int, end: int) -> None:
        chunk = data[start:end]
        self._count += len(chunk)
        self.sha.update(chunk)
        if self._file is not None:
            if self._count > self.s.max_image_bytes:
                name = self.upload.images[-1].filename
                raise APIError(413, ErrorCode.image_too_large, f"{name} is over {self.s.max_image_bytes} bytes")
            self._file.write(chunk)
        elif self._small is not None:
            if self._count > self.s.max_cameras_bytes:
                limit = self.s.max_cameras_bytes
                raise APIError(413, ErrorCode.payload_too_large, f"part {self._name!r} is over {limit} bytes")
            self._small += chunk

    def on_part_end(self) -> None:
        if self._file is not None:
            self._file.close()
            self.upload.images[-1].size = self._count
            self._file = None
        elif self._small is not None:
            setattr(self.upload, self._name, bytes(self._small))
            self._small = None

    def close(self) -> None:
        if self._file is not None:
            self._file.close()


async def receive_upload(request: Request, settings: Settings, folder: Path) -> Upload:
    """Stream the multipart body, the photos into ``folder``, enforcing the byte and count limits."""
    ctype, params = parse_options_header(request.headers.get("content-type", ""))
    if ctype != b"multipart/form-data" or b"boundary" not in params:
        raise APIError(415, ErrorCode.unsupported_media_type, "send the photos as multipart/form-data")
    limit = settings.max_request_bytes
    length = request.headers.get("content-length")
    if length is not None and length.isdigit() and int(length) > limit:
        raise APIError(413, ErrorCode.payload_too_large, f"the request is over {limit} bytes")
    reader = _Reader(settings, folder)
    parser = MultipartParser(params[b"boundary"], reader.callbacks())
    total = 0
    try:
        async for chunk in request.stream():
            total += len(chunk)
            if total > limit:
                raise APIError(413, ErrorCode.payload_too_large, f"the request is over {limit} bytes")
            parser.write(chunk)
        parser.finalize()
    except ClientDisconnect:
        raise APIError(400, ErrorCode.bad_request, "the upload was interrupted") from None
    except APIError:
        raise
    except Exception as e:  # malformed multipart
        raise APIError(400, ErrorCode.bad_request, f"malformed multipart body: {e}") from None
    finally:
        reader.close()
    reader.upload.digest = reader.sha.hexdigest()
    return reader.upload


def check_images(upload: Upload, settings: Settings, decode_memory: MemoryBudget | None = None) -> list[str]:
    """Sniff every photo by content, check pixels and that it decodes (waiting for its memory in
    ``decode_memory``, when given); rename each file to the extension of its real format.
    Returns the storage names. Raises APIError 413/415/422."""
    from cmc.data.datasets import SceneError
    from cmc.data.images import (
        ImageTooLargeError,
        UnsupportedImageError,
        accepted_formats,
        load_resized,
        read_photo_info,
        resized_size,
    )

    n = len(upload.images)
    if n < settings.min_images:
        raise APIError(
            422, ErrorCode.too_few_images, f"send at least {settings.min_images} images as 'images' parts, got {n}"
        )
    names, sizes = [], []
    for k, part in enumerate(upload.images):
        label = part.filename
        try:
            if part.size == 0:
                raise SceneError(f"{label} is empty")
            info = read_photo_info(part.path, settings.max_image_pixels)
            load_resized(info, [resized_size(info.width, info.height, 64)], settings.max_image_pixels, decode_memory)
        except UnsupportedImageError:
            raise APIError(415, ErrorCode.unsupported_image, f"{label} is not a {accepted_formats()} image") from None
        except ImageTooLargeError:
            raise APIError(
                413, ErrorCode.image_too_large, f"{label} has more than {settings.max_image_pixels} pixels"
            ) from None
        except SceneError as e:
            message = ClientNames([part.path.name], [label]).in_text(str(e))
            raise APIError(422, ErrorCode.invalid_images, message) from None
        final = part.path.with_name(f"{k:02d}{_EXTENSIONS.get(info.format, '.img')}")
        part.path.replace(final)
        part.path = final
        names.append(final.name)
        sizes.append((info.width, info.height))
    if len(set(sizes)) > 1:
        listing = ", ".join(f"{p.filename} {w}x{h}" for p, (w, h) in zip(upload.images, sizes, strict=True))
        raise APIError(
            422,
            ErrorCode.invalid_images,
            f"the photos must have one size and orientation, got {listing}",
        )
    return names


def parse_options(upload: Upload, settings: Settings) -> SceneOptions:
    if upload.options is None:
        return SceneOptions()
    try:
        opts = SceneOptions.model_validate_json(upload.options)
    except ValidationError as e:
        details = [{"field": ".".join(str(p) for p in err["loc"]), "problem": err["msg"]} for err in e.errors()]
        raise APIError(422, ErrorCode.invalid_options, "the 'options' part is not valid", details) from None
    if opts.steps is not None and opts.steps > settings.max_steps:
        raise APIError(422, ErrorCode.invalid_options, f"steps must be at most {settings.max_steps}")
    return opts


def parse_callback_url(upload: Upload, settings: Settings) -> str | None:
    """The ``callback_url`` part, checked (resolves to public addresses only, unless allowed)."""
    if upload.callback_url is None:
        return None
    from service.webhooks import CallbackRefused, resolve_callback

    if not settings.webhook_secret:
        raise APIError(
            422, ErrorCode.webhooks_not_configured, "this server sends no webhooks (CMC_WEBHOOK_SECRET is not set)"
        )
    try:
        url = upload.callback_url.decode("utf-8").strip()
        resolve_callback(url, settings.webhook_allow_private)
    except UnicodeDecodeError:
        raise APIError(422, ErrorCode.invalid_callback_url, "callback_url is not UTF-8 text") from None
    except CallbackRefused as e:
        raise APIError(422, ErrorCode.invalid_callback_url, str(e)) from None
    return url


def parse_cameras(upload: Upload, stored_names: list[str]) -> dict | None:
    """Validate the cameras part against the photos; returns it with every frame's
    ``file_path`` renamed to our storage name (the worker reads that copy)."""
    if upload.cameras is None:
        return None
    from cmc.geometry.cameras import CameraError, camera_file_from_dict, match_frames

    try:
        data = json.loads(upload.cameras)
        cf = camera_file_from_dict(data)
        aliases = [(p.filename, name) for p, name in zip(upload.images, stored_names, strict=True)]
        order = match_frames(cf.file_paths, aliases)
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise APIError(422, ErrorCode.invalid_cameras, f"the 'cameras' part is not valid JSON: {e}") from None
    except RecursionError:  # json refuses documents nested deeper than Python's recursion limit
        raise APIError(422, ErrorCode.invalid_cameras, "the 'cameras' part is nested too deeply") from None
    except CameraError as e:
        raise APIError(422, ErrorCode.invalid_cameras, str(e)) from None
    for k, f in enumerate(order):
        data["frames"][f]["file_path"] = stored_names[k]
    return data
