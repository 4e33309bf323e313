"""ASGI middleware that judges a request by its head, before any route reads its body.

:class:`BodyGuard`: with API keys configured, a request that carries a body must carry a valid
key (401 before a byte of the body is read); and a body is at most ``max_json_bytes`` (413 as
soon as Content-Length or the bytes received say so), except on the routes that stream their
body under their own limits (the upload).

:class:`LocalOnly` (open mode, no API keys): the server answers only requests addressed to a
local host name (421 otherwise: a page that rebinds its own DNS name to 127.0.0.1 cannot use it)
and refuses state-changing requests that a page of another site sends (403).
"""

from __future__ import annotations

from urllib.parse import urlsplit

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.auth import KeyRing
from service.errors import APIError, ErrorCode, error_response


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
        return APIError(413, ErrorCode.payload_too_large, f"the request body is over {self.limit} bytes")


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


LOCAL_HOSTS = frozenset({"localhost", "127.0.0.1", "[::1]"})
STATE_CHANGING = frozenset({"POST", "PUT", "PATCH", "DELETE"})


def _hostname(netloc: str) -> str:
    """``host[:port]`` -> host, lower-case; IPv6 addresses keep their brackets."""
    netloc = netloc.strip().lower()
    if netloc.startswith("["):
        return netloc[: netloc.find("]") + 1]  # "" when the bracket is not closed
    return netloc.rsplit(":", 1)[0]


class LocalOnly:
    def __init__(self, app: ASGIApp, extra_hosts: set[str]):
        """``extra_hosts``: host names (no port) accepted besides :data:`LOCAL_HOSTS`."""
        self.app, self.hosts = app, LOCAL_HOSTS | {h.strip().lower() for h in extra_hosts if h.strip()}

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http":
            host = _header(scope, b"host") or ""
            if _hostname(host) not in self.hosts:
                message = f"without API keys this server answers only for localhost, not {host[:100]!r} "
                message += "(CMC_ALLOWED_HOSTS adds host names)"
                await _refuse(APIError(421, ErrorCode.host_not_allowed, message), scope, receive, send)
                return
            if scope["method"] in STATE_CHANGING and self._cross_site(scope):
                message = "without API keys this server refuses changes sent by another site's page"
                await _refuse(APIError(403, ErrorCode.cross_site_request, message), scope, receive, send)
                return
        await self.app(scope, receive, send)

    def _cross_site(self, scope: Scope) -> bool:
        if _header(scope, b"sec-fetch-site") == "cross-site":
            return True
        origin = _header(scope, b"origin")
        if origin is None:  # not sent by a browser page (curl, scripts)
            return False
        url = urlsplit(origin)
        return url.scheme not in ("http", "https") or _hostname(url.netloc) not in self.hosts
