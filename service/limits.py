"""Counting for quotas and rate limits: one primitive, two backends (memory and Redis).

A *bucket* holds *tokens*, each with a deadline; a token counts while its deadline is ahead.
:meth:`Limiter.acquire` adds one token to several buckets at once, all or none, and only when
every bucket counts fewer tokens than its limit; it answers with each bucket's count. That one
primitive gives every limit of :mod:`service.quotas`:

* a rolling window of W seconds (renders per second, jobs per day): a request is a token held
  for W seconds, so at most ``limit`` requests fall in any W seconds;
* a concurrency limit (unfinished jobs): the caller also names the tokens that are *live*
  whatever their deadline (the jobs the database lists as unfinished); a token is held while an
  upload streams, then briefly after its record exists (:meth:`Limiter.hold`), so two uploads
  that race are counted even when the database has not seen either yet.

:class:`MemoryLimiter` counts in this process (the embedded server). :class:`RedisLimiter`
counts in Redis, shared by every API replica (the deployed mode): a bucket is a sorted set
(token -> deadline in ms) and each acquire is one Lua script, so concurrent requests cannot both
take the last place; every key expires with its last deadline. Its clock is the Redis server's,
so replicas never disagree about time.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

log = logging.getLogger("cmc.api")


@dataclass(frozen=True)
class Claim:
    """One bucket an acquire must find room in."""

    bucket: str
    limit: int
    hold_s: float  # how long the new token counts
    live: Sequence[str] = ()  # tokens that count whatever their deadline (e.g. unfinished jobs)


@dataclass(frozen=True)
class Usage:
    """A bucket's count after the acquire: ``used`` includes the new token when granted;
    ``free_in_s``: seconds until the first held token stops counting (None: none held)."""

    used: int
    free_in_s: float | None


@dataclass(frozen=True)
class Outcome:
    granted: bool
    usage: list[Usage]  # one per claim, in order


class LimiterUnavailable(Exception):
    """The backend cannot count right now (Redis down)."""


class Limiter(Protocol):
    def acquire(self, token: str, claims: Sequence[Claim]) -> Outcome:
        """Add ``token`` to every claim's bucket if each counts fewer than its limit, else to none."""
        ...

    def hold(self, token: str, bucket: str, hold_s: float) -> None:
        """Make a held token count for ``hold_s`` seconds from now (no-op when absent)."""
        ...

    def release(self, token: str, buckets: Sequence[str]) -> None:
        """Stop counting ``token`` in ``buckets`` (a refused or failed request gives its place back)."""
        ...


class MemoryLimiter:
    """Buckets in this process's memory, under one lock. ``clock``: seconds (monotonic by default)."""

    def __init__(self, clock: Callable[[], float] = time.monotonic):
        self.clock = clock
        self._buckets: dict[str, dict[str, float]] = {}
        self._lock = threading.Lock()

    def _pruned(self, bucket: str, now: float) -> dict[str, float]:
        tokens = self._buckets.setdefault(bucket, {})
        for token in [t for t, deadline in tokens.items() if deadline <= now]:
            del tokens[token]
        return tokens

    def acquire(self, token: str, claims: Sequence[Claim]) -> Outcome:
        with self._lock:
            now = self.clock()
            counts = []
            for c in claims:
                tokens = self._pruned(c.bucket, now)
                used = len(tokens) + sum(1 for t in set(c.live) if t not in tokens)
                counts.append((used, min(tokens.values(), default=None)))
            granted = all(used < c.limit for (used, _), c in zip(counts, claims, strict=True))
            if granted:
                for c in claims:
                    self._buckets[c.bucket][token] = now + c.hold_s
            else:
                for c in claims:
                    if not self._buckets[c.bucket]:
                        del self._buckets[c.bucket]  # no memory kept for idle keys
            return Outcome(granted, _usages(granted, counts, claims, now))

    def hold(self, token: str, bucket: str, hold_s: float) -> None:
        with self._lock:
            tokens = self._buckets.get(bucket)
            if tokens is not None and token in tokens:
                tokens[token] = self.clock() + hold_s

    def release(self, token: str, buckets: Sequence[str]) -> None:
        with self._lock:
            for bucket in buckets:
                tokens = self._buckets.get(bucket)
                if tokens is not None:
                    tokens.pop(token, None)
                    if not tokens:
                        del self._buckets[bucket]


def _usages(granted: bool, counts: list[tuple[int, float | None]], claims: Sequence[Claim], now: float) -> list[Usage]:
    out = []
    for (used, earliest), c in zip(counts, claims, strict=True):
        if granted:
            used += 1
            earliest = now + c.hold_s if earliest is None else min(earliest, now + c.hold_s)
        out.append(Usage(used, None if earliest is None else max(0.0, earliest - now)))
    return out


# Both scripts' ARGV[1]: now in ms, or negative for the Redis server's clock; sets ``now``.
_NOW = """
local now = tonumber(ARGV[1])
if now < 0 then
  local t = redis.call('TIME')
  now = tonumber(t[1]) * 1000 + math.floor(tonumber(t[2]) / 1000)
end
"""

# KEYS: one sorted set per claim (member: token, score: deadline in ms).
# ARGV: now in ms (negative: the server's clock), token, then per key: limit, hold_ms, n_live,
# the n_live live tokens. Returns {granted, now_ms, then per key: used, earliest deadline or -1}.
_ACQUIRE = (
    _NOW
    + """local token = ARGV[2]
local at, granted, out, holds = 3, 1, {0, now}, {}
for k, key in ipairs(KEYS) do
  local limit, hold, nlive = tonumber(ARGV[at]), tonumber(ARGV[at + 1]), tonumber(ARGV[at + 2])
  at = at + 3
  redis.call('ZREMRANGEBYSCORE', key, '-inf', now)
  local used = redis.call('ZCARD', key)
  for j = at, at + nlive - 1 do
    if not redis.call('ZSCORE', key, ARGV[j]) then used = used + 1 end
  end
  at = at + nlive
  local first = redis.call('ZRANGE', key, 0, 0, 'WITHSCORES')
  if used >= limit then granted = 0 end
  holds[k] = hold
  out[#out + 1] = used
  out[#out + 1] = first[2] and tonumber(first[2]) or -1
end
if granted == 1 then
  for k, key in ipairs(KEYS) do
    redis.call('ZADD', key, now + holds[k], token)
    if redis.call('PTTL', key) < holds[k] then redis.call('PEXPIRE', key, holds[k]) end
  end
end
out[1] = granted
return out
"""
)

# KEYS[1]: the bucket; ARGV: now in ms (negative: the server's clock), token, hold_ms.
_HOLD = (
    _NOW
    + """local hold = tonumber(ARGV[3])
if redis.call('ZADD', KEYS[1], 'XX', 'CH', now + hold, ARGV[2]) == 1 then
  if redis.call('PTTL', KEYS[1]) < hold then redis.call('PEXPIRE', KEYS[1], hold) end
end
return 1
"""
)


class RedisLimiter:
    """Buckets in Redis, keys ``{prefix}:{bucket}``. ``clock``: seconds, for tests; by default the
    server's clock. While Redis cannot be reached every call raises :class:`LimiterUnavailable`
    at once for ``retry_s`` seconds, so an outage costs one short timeout, not one per request."""

    def __init__(
        self,
        url: str,
        prefix: str = "cmc:limits",
        clock: Callable[[], float] | None = None,
        timeout_s: float = 0.5,
        retry_s: float = 5.0,
    ):
        import redis

        self.prefix, self.clock, self.retry_s = prefix, clock, retry_s
        self.redis = redis.Redis.from_url(url, socket_timeout=timeout_s, socket_connect_timeout=timeout_s)
        self._acquire = self.redis.register_script(_ACQUIRE)
        self._hold = self.redis.register_script(_HOLD)
        self._down_until = 0.0

    def _key(self, bucket: str) -> str:
        return f"{self.prefix}:{bucket}"

    def _now_ms(self) -> int:
        return -1 if self.clock is None else int(self.clock() * 1000)

    def _call(self, fn: Callable[[], object]) -> object:
        import redis

        if time.monotonic() < self._down_until:
            raise LimiterUnavailable("Redis was unreachable moments ago")
        try:
            return fn()
        except (redis.RedisError, OSError) as e:
            self._down_until = time.monotonic() + self.retry_s
            raise LimiterUnavailable(f"{type(e).__name__}: {e}") from e

    def acquire(self, token: str, claims: Sequence[Claim]) -> Outcome:
        args: list[object] = [self._now_ms(), token]
        for c in claims:
            live = sorted(set(c.live))
            args += [c.limit, math.ceil(c.hold_s * 1000), len(live), *live]
        keys = [self._key(c.bucket) for c in claims]
        out = [int(v) for v in self._call(lambda: self._acquire(keys=keys, args=args))]  # type: ignore[union-attr]
        granted, now = out[0] == 1, out[1] / 1000
        counts = [(out[i], None if out[i + 1] < 0 else out[i + 1] / 1000) for i in range(2, len(out), 2)]
        return Outcome(granted, _usages(granted, counts, claims, now))

    def hold(self, token: str, bucket: str, hold_s: float) -> None:
        args = [self._now_ms(), token, math.ceil(hold_s * 1000)]
        self._call(lambda: self._hold(keys=[self._key(bucket)], args=args))

    def release(self, token: str, buckets: Sequence[str]) -> None:
        def zrem() -> None:
            with self.redis.pipeline(transaction=False) as p:
                for b in buckets:
                    p.zrem(self._key(b), token)
                p.execute()

        self._call(zrem)

    def close(self) -> None:
        self.redis.close()
