"""ASGI middleware that judges a request by its head, before any route reads its body.

:class:`BodyGuard`: with API keys configured, a request that carries a body must carry a valid
key (401 before a byte of the body is read); and a body is at most ``max_json_bytes`` (413 as
soon as Content-Length or the bytes received say so), except on the routes that stream their
body under their own limits (the upload).
"""

from __future__ import annotations

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.auth import KeyRing
from service.errors import APIError, error_response


def _header(scope: Scope, name: bytes) -> str | None:
    for key, value in scope["headers"]:
        if key == name:
            return value.decode("latin-1")
    return None


async def _refuse(e: APIError, scope: Scope, receive: Receive, send: Send) -> None:
    await error_response(e.status, e.code, e.message, e.details, e.headers)(scope, receive, send)


class BodyGuard:
    def __init__(self, app: ASGIApp, keys: KeyRing, max_json_bytes: int, streamed: set[tuple[str, str]]):
        """``streamed``: (method, path) of the routes that read and bound their own bodies."""
        self.app, self.keys, self.limit, self.streamed = app, keys, max_json_bytes, streamed

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        length = _header(scope, b"content-length")
        if length in (None, "0") and _header(scope, b"transfer-encoding") is None:  # no body
            await self.app(scope, receive, send)
            return
        streamed = (scope["method"], scope["path"]) in self.streamed
        try:
            if not self.keys.open:
                self.keys.owner(_header(scope, b"authorization"))
            if not streamed and length is not None and length.isdigit() and int(length) > self.limit:
                raise self._too_large()
            body = None if streamed else await self._read(receive)
        except APIError as e:
            await _refuse(e, scope, receive, send)
            return
        if streamed:
            await self.app(scope, receive, send)
        elif body is not None:  # None: the client went away
            await self.app(scope, _replay(body, receive), send)

    async def _read(self, receive: Receive) -> bytes | None:
        """The whole body (None if the client went away), refused as soon as it crosses the limit."""
        body = bytearray()
        while True:
            message = await receive()
            if message["type"] != "http.request":
                return None
            body += message.get("body", b"")
            if len(body) > self.limit:
                raise self._too_large()
            if not message.get("more_body", False):
                return bytes(body)

    def _too_large(self) -> APIError:
        return APIError(413, "payload_too_large", f"the request body is over {self.limit} bytes")


def _replay(body: bytes, receive: Receive) -> Receive:
    """A receive that gives ``body`` in one message, then whatever the connection says next."""
    sent = False

    async def replay() -> Message:
        nonlocal sent
        if sent:
            return await receive()
        sent = True
        return {"type": "http.request", "body": body, "more_body": False}

    return replay
