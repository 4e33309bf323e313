"""Signed webhooks: what a receiver gets, how it is signed, which callback URLs are accepted.

A scene uploaded with a ``callback_url`` gets a POST there when it becomes ``ready``
(``scene.ready``), when it fails (``scene.failed``) and when a camera-path video is built or
fails (``video.ready``, ``video.failed``). The body is JSON::

    {"id": "<32 hex: the delivery's idempotency id>", "type": "scene.ready",
     "created_at": "2026-01-01T12:00:00.123456Z", "scene_id": "<32 hex>", "data": {...}}

with the headers ``CMC-Webhook-Id`` (the same id), ``CMC-Webhook-Timestamp`` (UNIX seconds of
this try) and ``CMC-Webhook-Signature: v1=<hex HMAC-SHA256(secret, timestamp + "." + body)>``.
Each API key has its own secret, derived from ``CMC_WEBHOOK_SECRET`` (:func:`owner_secret`,
served at ``GET /v1/webhooks/secret``), so no client can sign another's events. A receiver
checks the signature over the raw body bytes, refuses old timestamps (replays) and drops ids
it has seen: delivery is at least once (:mod:`worker.webhooks` retries until a 2xx answer).

Callback URLs must be http(s) and resolve only to public addresses (against server-side
request forgery), unless ``CMC_WEBHOOK_ALLOW_PRIVATE`` is set; the check is made at upload and
again at every try, and the try connects to the address that was checked (DNS rebinding).
"""

from __future__ import annotations

import hashlib
import hmac
import ipaddress
import socket
import time
from urllib.parse import SplitResult, urlsplit

ID_HEADER = "CMC-Webhook-Id"
TIMESTAMP_HEADER = "CMC-Webhook-Timestamp"
SIGNATURE_HEADER = "CMC-Webhook-Signature"
EVENTS = ("scene.ready", "scene.failed", "video.ready", "video.failed")
MAX_URL_LENGTH = 2000

IPAddress = ipaddress.IPv4Address | ipaddress.IPv6Address


class CallbackRefused(ValueError):
    """A callback URL that is malformed, does not resolve, or points at a refused address."""


def owner_secret(master: str, owner: str) -> str:
    """The signing secret of one API key's webhooks (``owner``: the key's owner id)."""
    return "whsec_" + hmac.new(master.encode(), b"cmc-webhook:" + owner.encode(), hashlib.sha256).hexdigest()


def sign(secret: str, timestamp: int, body: bytes) -> str:
    """The signature header's value: ``v1=`` + hex HMAC-SHA256 of ``"<timestamp>." + body``."""
    return "v1=" + hmac.new(secret.encode(), f"{timestamp}.".encode() + body, hashlib.sha256).hexdigest()


def verify(secret: str, body: bytes, timestamp: str, signature: str, tolerance_s: float = 300) -> bool:
    """The receiver's check (the README's recipe): a fresh timestamp and a matching signature."""
    try:
        ts = int(timestamp)
    except ValueError:
        return False
    if abs(time.time() - ts) > tolerance_s:
        return False
    return hmac.compare_digest(sign(secret, ts, body), signature)


def _refused(ip: IPAddress) -> bool:
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
        ip = ip.ipv4_mapped
    return not ip.is_global or ip.is_multicast


def resolve_callback(url: str, allow_private: bool) -> tuple[SplitResult, list[IPAddress]]:
    """Check a callback URL and resolve its host: (the parsed URL, its addresses). Raises
    CallbackRefused when it is not http(s), does not resolve, or any address it resolves to is
    loopback, private, link-local, multicast or otherwise not public (unless ``allow_private``)."""
    if len(url) > MAX_URL_LENGTH:
        raise CallbackRefused(f"callback_url is longer than {MAX_URL_LENGTH} characters")
    try:
        parts = urlsplit(url)
        port = parts.port or (443 if parts.scheme == "https" else 80)
    except ValueError as e:
        raise CallbackRefused(f"callback_url is not a valid URL: {e}") from None
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise CallbackRefused("callback_url must be an http:// or https:// URL with a host")
    if parts.username is not None or parts.password is not None:
        raise CallbackRefused("callback_url must not carry credentials (user:password@)")
    try:
        infos = socket.getaddrinfo(parts.hostname, port, type=socket.SOCK_STREAM)
    except (OSError, UnicodeError) as e:
        raise CallbackRefused(f"the host of callback_url does not resolve: {parts.hostname} ({e})") from None
    addresses = list(dict.fromkeys(ipaddress.ip_address(str(info[4][0]).split("%")[0]) for info in infos))
    if not addresses:
        raise CallbackRefused(f"the host of callback_url does not resolve: {parts.hostname}")
    if not allow_private:
        for ip in addresses:
            if _refused(ip):
                raise CallbackRefused(
                    f"callback_url resolves to {ip}, a loopback, private or otherwise non-public address; "
                    "only public hosts are called (CMC_WEBHOOK_ALLOW_PRIVATE allows others)"
                )
    return parts, addresses
