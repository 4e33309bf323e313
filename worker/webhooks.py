"""Webhook delivery: one try of a pending delivery (:func:`deliver`), and who calls it.

* Celery (``worker.celery_app``): the task ``cmc.webhook`` on ``CMC_WEBHOOK_QUEUE`` makes one
  try and, when it failed, sends itself again with a countdown (exponential backoff:
  ``webhook_backoff_seconds`` doubled after each try, at most ``webhook_backoff_max_seconds``).
  The reaper of every worker re-sends deliveries that are overdue (a message lost with its
  worker), see :func:`resend_overdue`.
* Embedded (``cmc serve``): :class:`WebhookSender`, a thread of the API process that tries every
  due delivery, so webhooks never wait behind a training job.

The database is the truth (:mod:`service.db`): a delivery is claimed before each try, so a
duplicate message does nothing, and its outcome (status code or error, duration) is appended to
the delivery log of ``GET /v1/scenes/{id}/webhooks``. A 2xx answer delivers it; anything else
(an error status, a redirect, a timeout, a refused address) is retried until
``webhook_max_attempts`` tries, then the delivery is ``failed``.
"""

from __future__ import annotations

import http.client
import logging
import socket
import ssl
import threading
import time
from datetime import UTC, datetime
from typing import TYPE_CHECKING

from service.db.scenes import SceneStore
from service.settings import Settings
from service.webhooks import (
    ID_HEADER,
    SIGNATURE_HEADER,
    TIMESTAMP_HEADER,
    CallbackRefused,
    IPAddress,
    owner_secret,
    resolve_callback,
    sign,
)

if TYPE_CHECKING:
    from worker.context import JobContext

log = logging.getLogger("cmc.webhooks")

OVERDUE_GRACE_S = 60.0  # a Celery delivery this late lost its message: the reaper sends it again


def backoff(settings: Settings, tries: int) -> float:
    """Seconds to wait after the ``tries``-th failed try."""
    return min(settings.webhook_backoff_seconds * 2 ** (tries - 1), settings.webhook_backoff_max_seconds)


class _PinnedHTTPConnection(http.client.HTTPConnection):
    """HTTP to the address that was checked, whatever the name resolves to now."""

    def __init__(self, host: str, ip: IPAddress, port: int, timeout: float):
        super().__init__(host, port, timeout=timeout)
        self._ip = ip

    def connect(self) -> None:
        self.sock = socket.create_connection((str(self._ip), self.port), self.timeout)


class _PinnedHTTPSConnection(http.client.HTTPSConnection):
    """HTTPS to the checked address; the certificate is verified against the URL's host name."""

    def __init__(self, host: str, ip: IPAddress, port: int, timeout: float):
        super().__init__(host, port, timeout=timeout, context=ssl.create_default_context())
        self._ip = ip

    def connect(self) -> None:
        sock = socket.create_connection((str(self._ip), self.port), self.timeout)
        self.sock = self._context.wrap_socket(sock, server_hostname=self.host)  # type: ignore[attr-defined]


def post(url: str, body: bytes, headers: dict[str, str], allow_private: bool, timeout: float) -> int:
    """POST ``body`` to ``url`` after the SSRF check, connected to a checked address; the status
    code (redirects are not followed). Raises CallbackRefused or OSError."""
    parts, addresses = resolve_callback(url, allow_private)
    assert parts.hostname is not None
    port = parts.port or (443 if parts.scheme == "https" else 80)
    cls = _PinnedHTTPSConnection if parts.scheme == "https" else _PinnedHTTPConnection
    conn = cls(parts.hostname, addresses[0], port, timeout)
    try:
        target = (parts.path or "/") + (f"?{parts.query}" if parts.query else "")
        conn.request("POST", target, body=body, headers={**headers, "Content-Type": "application/json"})
        return conn.getresponse().status
    finally:
        conn.close()


def deliver(store: SceneStore, settings: Settings, delivery_id: str) -> float | None:
    """One try of a delivery, if it is pending and due. Returns the seconds until its next try,
    or None when there is nothing more to do (delivered, given up, or not ours to try now)."""
    d = store.claim_delivery(delivery_id, hold_seconds=settings.webhook_timeout_seconds + 30)
    if d is None:
        return None
    t0 = time.time()
    status_code, error = None, None
    try:
        if not settings.webhook_secret:
            raise CallbackRefused("CMC_WEBHOOK_SECRET is not set where the webhook is sent: nothing to sign with")
        ts = int(t0)
        body = d.body.encode()
        headers = {
            ID_HEADER: d.id,
            TIMESTAMP_HEADER: str(ts),
            SIGNATURE_HEADER: sign(owner_secret(settings.webhook_secret, d.owner), ts, body),
            "User-Agent": "cmc-webhooks/1",
        }
        status_code = post(d.url, body, headers, settings.webhook_allow_private, settings.webhook_timeout_seconds)
        if not 200 <= status_code < 300:
            error = f"HTTP {status_code}" + (" (redirects are not followed)" if 300 <= status_code < 400 else "")
    except CallbackRefused as e:
        error = str(e)
    except (OSError, http.client.HTTPException) as e:
        error = f"{type(e).__name__}: {e}"[:500]
    tries = len(d.attempts) + 1
    attempt = {
        "at": datetime.fromtimestamp(t0, UTC).isoformat().replace("+00:00", "Z"),
        "status_code": status_code,
        "error": error,
        "duration_ms": round((time.time() - t0) * 1000, 1),
    }
    if error is None:
        store.record_attempt(d.id, attempt, "delivered", None)
        log.info("webhook %s (%s of %s) delivered", d.id, d.event, d.scene_id)
        return None
    if tries >= settings.webhook_max_attempts:
        store.record_attempt(d.id, attempt, "failed", None)
        log.warning("webhook %s (%s of %s): giving up after %d tries: %s", d.id, d.event, d.scene_id, tries, error)
        return None
    delay = backoff(settings, tries)
    store.record_attempt(d.id, attempt, "pending", time.time() + delay)
    log.info("webhook %s try %d failed (%s); next in %.1f s", d.id, tries, error, delay)
    return delay


def kick(ctx: JobContext, scene_id: str) -> None:
    """Send the scene's due deliveries now (after an event was recorded). Never raises: the
    reaper (Celery) or the sender's next pass (embedded) picks up whatever this misses."""
    try:
        for delivery_id in ctx.store.due_deliveries(time.time(), scene_id):
            ctx.queue.submit_webhook(delivery_id, 0.0)
    except Exception:
        log.warning("sending the webhooks of %s failed; they are retried later", scene_id, exc_info=True)


def resend_overdue(ctx: JobContext) -> list[str]:
    """Celery: send again the deliveries whose try is overdue by ``OVERDUE_GRACE_S`` (the message
    was lost, or its worker died mid-try). A duplicate does nothing (deliveries are claimed)."""
    ids = ctx.store.due_deliveries(time.time() - OVERDUE_GRACE_S)
    for delivery_id in ids:
        ctx.queue.submit_webhook(delivery_id, 0.0)
    return ids


class WebhookSender:
    """The embedded mode's sender: a thread that tries every due delivery, oldest first, and
    sleeps until the next one is due (at most ``poll_s``) or :meth:`wake` is called."""

    def __init__(self, store: SceneStore, settings: Settings, poll_s: float = 1.0):
        self.store, self.settings, self.poll_s = store, settings, poll_s
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="cmc-webhooks", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def wake(self) -> None:
        self._wake.set()

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout)

    def _loop(self) -> None:
        while not self._stop.is_set():
            self._wake.clear()
            try:
                for delivery_id in self.store.due_deliveries(time.time()):
                    if self._stop.is_set():
                        return
                    deliver(self.store, self.settings, delivery_id)
                nxt = self.store.next_delivery_at()
            except Exception:  # the database may blink: try again at the next pass
                log.warning("webhook pass failed", exc_info=True)
                nxt = None
            wait = self.poll_s if nxt is None else min(self.poll_s, max(0.0, nxt - time.time()))
            self._wake.wait(wait)
