"""Quotas and rate limits per API key: unfinished jobs, new jobs per day, renders per second.

The policy on top of :mod:`service.limits` (which counts, in memory or in Redis). Each limit is a
``CMC_*`` setting (0: none); without API keys (``cmc serve`` on localhost, one user) nothing is
limited. Over a limit a request is answered 429 with the JSON error shape, a code naming the
limit, ``Retry-After`` and the ``RateLimit-*`` fields; refusals are counted in
``cmc_rate_limited_total{limit}``.

* **renders per second** (``POST .../render`` and ``.../depth`` together): at most N requests in
  any one second, counted when the request arrives (whatever it is answered).
* **jobs per day**: at most N scenes created in any 24 hours (a rolling window; a refused or
  failed upload and an idempotent replay do not count, a deleted scene does).
* **concurrent jobs**: at most N unfinished scenes (queued or running). The database says which
  jobs are unfinished; an upload holds a place from its first byte (so the 429 comes before the
  photos are sent) and gives it back if it fails.

Headers follow draft-ietf-httpapi-ratelimit-headers-06 (the three separate fields):
``RateLimit-Limit`` (the limit), ``RateLimit-Remaining`` (requests left), ``RateLimit-Reset``
(seconds until more are allowed: for a window, until its oldest counted request leaves it; for
concurrent jobs, the shortest ETA of the key's unfinished jobs, an estimate). They are sent on
every response of a limited route that was counted, for the limit closest to refusing.
"""

from __future__ import annotations

import logging
import math
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.errors import APIError, ErrorCode
from service.limits import Claim, Limiter, LimiterUnavailable, Outcome
from service.settings import Settings

log = logging.getLogger("cmc.api")


@dataclass(frozen=True)
class Limit:
    name: str  # the setting is max_<name>; the metric label and details["limit"]
    code: ErrorCode  # the error code of its 429
    window_s: float | None  # None: a concurrency limit
    what: str  # for the error message


RENDERS = Limit("renders_per_second", ErrorCode.render_rate_limited, 1.0, "render and depth requests per second")
JOBS_PER_DAY = Limit("jobs_per_day", ErrorCode.daily_job_quota_exceeded, 86400.0, "new scenes in any 24 hours")
CONCURRENT_JOBS = Limit("concurrent_jobs", ErrorCode.too_many_concurrent_jobs, None, "unfinished scenes")
LIMITS = (CONCURRENT_JOBS, JOBS_PER_DAY, RENDERS)

UPLOAD_HOLD_S = 3600.0  # a place held while an upload streams (given back when it fails; outlives only a crash)
RECORD_HOLD_S = 10.0  # once the record exists: a racing upload's read of the database may predate it
CONCURRENT_RESET_S = 60  # RateLimit-Reset of the concurrency limit while no unfinished job has an ETA
STATE_KEY = "rate_limit_headers"  # request.state entry that RateLimitHeaders adds to the response


@dataclass(frozen=True)
class Standing:
    """Where one request left one limit."""

    limit: Limit
    maximum: int
    remaining: int
    reset_s: int

    def headers(self) -> dict[str, str]:
        return {
            "RateLimit-Limit": str(self.maximum),
            "RateLimit-Remaining": str(self.remaining),
            "RateLimit-Reset": str(self.reset_s),
        }


def headers_of(standings: Sequence[Standing]) -> dict[str, str]:
    """The fields of the limit closest to refusing (fewest left; then the longest wait)."""
    return min(standings, key=lambda s: (s.remaining, -s.reset_s)).headers() if standings else {}


class Quotas:
    def __init__(self, settings: Settings, limiter: Limiter, enabled: bool, on_refused: Callable[[str], None]):
        """``enabled``: False without API keys. ``on_refused(limit name)``: counts a refusal."""
        self.limiter, self.on_refused = limiter, on_refused
        self.maximum = {lim: getattr(settings, f"max_{lim.name}") if enabled else 0 for lim in LIMITS}
        self._warned = 0.0

    def _active(self, *limits: Limit) -> list[Limit]:
        return [lim for lim in limits if self.maximum[lim] > 0]

    # -- the limited routes --------------------------------------------------------------------------

    def admit_render(self, owner: str) -> list[Standing]:
        """Count a render or depth request; raises the 429 when over the limit."""
        limits = self._active(RENDERS)
        if not limits:
            return []
        claims = [Claim(_bucket(owner, RENDERS), self.maximum[RENDERS], RENDERS.window_s or 1.0)]
        return self._admit(uuid.uuid4().hex, limits, claims, {})

    def reserve_job(
        self, owner: str, token: str, unfinished: Callable[[], list[tuple[str, float | None]]]
    ) -> list[Standing]:
        """Hold a place for the upload ``token`` (its scene id) in the job limits; raises the 429
        when over either. ``unfinished()``: (id, eta_seconds) of the owner's unfinished scenes.
        Then exactly one of :meth:`job_created` and :meth:`job_dropped`."""
        limits = self._active(CONCURRENT_JOBS, JOBS_PER_DAY)
        claims, etas = [], {}
        if CONCURRENT_JOBS in limits:
            live = unfinished()
            claims.append(
                Claim(
                    _bucket(owner, CONCURRENT_JOBS), self.maximum[CONCURRENT_JOBS], UPLOAD_HOLD_S, [i for i, _ in live]
                )
            )
            known = [eta for _, eta in live if eta is not None]
            etas[CONCURRENT_JOBS] = max(1, math.ceil(min(known))) if known else CONCURRENT_RESET_S
        if JOBS_PER_DAY in limits:
            claims.append(Claim(_bucket(owner, JOBS_PER_DAY), self.maximum[JOBS_PER_DAY], JOBS_PER_DAY.window_s or 0))
        return self._admit(token, limits, claims, etas) if limits else []

    def job_created(self, owner: str, token: str) -> None:
        """The upload's record exists: from now on the database counts it as unfinished."""
        if self._active(CONCURRENT_JOBS):
            self._guard(lambda: self.limiter.hold(token, _bucket(owner, CONCURRENT_JOBS), RECORD_HOLD_S))

    def job_dropped(self, owner: str, token: str) -> None:
        """The upload made no new scene (refused, failed, a replay): its places are given back."""
        buckets = [_bucket(owner, lim) for lim in self._active(CONCURRENT_JOBS, JOBS_PER_DAY)]
        if buckets:
            self._guard(lambda: self.limiter.release(token, buckets))

    # -- shared ----------------------------------------------------------------------------------------

    def _admit(self, token: str, limits: list[Limit], claims: list[Claim], etas: dict[Limit, int]) -> list[Standing]:
        outcome: Outcome | None = self._guard(lambda: self.limiter.acquire(token, claims))
        if outcome is None:  # the counter is unreachable: let the request through
            return []
        standings = []
        for lim, usage in zip(limits, outcome.usage, strict=True):
            if lim in etas:
                reset = etas[lim]
            else:
                reset = math.ceil(usage.free_in_s) if usage.free_in_s is not None else 0
            standings.append(Standing(lim, self.maximum[lim], max(0, self.maximum[lim] - usage.used), reset))
        if outcome.granted:
            return standings
        full = [s for s, u in zip(standings, outcome.usage, strict=True) if u.used >= s.maximum]
        worst = max(full, key=lambda s: s.reset_s)
        retry = max(1, max(s.reset_s for s in full))
        self.on_refused(worst.limit.name)
        headers = {**worst.headers(), "Retry-After": str(retry)}
        message = f"over the limit of {worst.maximum} {worst.limit.what} for this API key; retry after {retry} s"
        details = {"limit": worst.limit.name, "maximum": worst.maximum, "retry_after": retry}
        raise APIError(429, worst.limit.code, message, details, headers)

    def _guard(self, call: Callable[[], object]) -> object | None:
        """``call()``, or None when the counter is unreachable (limits are not enforced meanwhile)."""
        try:
            return call()
        except LimiterUnavailable as e:
            if time.monotonic() - self._warned > 60:
                self._warned = time.monotonic()
                log.warning("quotas not enforced: the rate-limit counter is unavailable (%s)", e)
            return None


def _bucket(owner: str, limit: Limit) -> str:
    return f"{owner}:{limit.name}"


class RateLimitHeaders:
    """Adds the ``RateLimit-*`` fields a route left in ``request.state`` to its response, whatever
    its status (a counted request that then fails still used its place)."""

    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        state = scope.setdefault("state", {})

        async def send_with_fields(message: Message) -> None:
            fields = state.get(STATE_KEY)
            if message["type"] == "http.response.start" and fields:
                raw = list(message.get("headers", []))
                present = {k.lower() for k, _ in raw}
                raw += [
                    (k.lower().encode(), v.encode()) for k, v in fields.items() if k.lower().encode() not in present
                ]
                message = {**message, "headers": raw}
            await send(message)

        await self.app(scope, receive, send_with_fields)
