"""The two backends of service.limits: in memory, and in the real Redis at 127.0.0.1:6379.

Every behaviour is checked on both backends with the same test and a clock the test moves (no
test sleeps through a window); the Redis-only tests use the server's own clock with a short
window, and check that keys expire, that concurrent acquires from several clients (API replicas)
never pass the limit, and that an unreachable Redis says so at once. Each Redis test counts under
a key prefix of its own and deletes its keys after.
"""

from __future__ import annotations

import threading
import time
import uuid

import pytest
from helpers import REDIS_URL

from service.limits import Claim, LimiterUnavailable, MemoryLimiter, RedisLimiter


class Clock:
    """Seconds that move only when a test says so."""

    def __init__(self) -> None:
        self.t = 1_000_000.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture(params=["memory", "redis"])
def backend(request) -> tuple:
    """(limiter, clock) of each backend, on a clock the test moves."""
    clock = Clock()
    if request.param == "memory":
        return MemoryLimiter(clock), clock
    return RedisLimiter(REDIS_URL, prefix=request.getfixturevalue("redis_prefix"), clock=clock), clock


def test_a_window_admits_its_limit_then_refuses_until_the_oldest_leaves(backend) -> None:
    limiter, clock = backend
    claim = [Claim("k:renders", limit=3, hold_s=1.0)]
    outcomes = []
    for _ in range(3):
        outcomes.append(limiter.acquire(uuid.uuid4().hex, claim))
        clock.t += 0.25
    assert [o.granted for o in outcomes] == [True, True, True]
    assert [o.usage[0].used for o in outcomes] == [1, 2, 3]
    assert outcomes[2].usage[0].free_in_s == pytest.approx(0.5)  # the first leaves 1 s after it came
    refused = limiter.acquire("late", claim)  # at +0.75 s
    assert not refused.granted and refused.usage[0].used == 3
    assert refused.usage[0].free_in_s == pytest.approx(0.25)
    clock.t += 0.25  # the first request's second is over: one place again, not three
    assert limiter.acquire("a", claim).granted
    assert not limiter.acquire("b", claim).granted
    clock.t += 1.0  # the window reset entirely
    assert [limiter.acquire(f"c{i}", claim).granted for i in range(4)] == [True, True, True, False]


def test_a_refused_acquire_takes_no_place_in_any_bucket(backend) -> None:
    limiter, _ = backend
    day, jobs = Claim("k:day", limit=5, hold_s=86400), Claim("k:jobs", limit=1, hold_s=3600)
    assert limiter.acquire("t1", [jobs, day]).granted
    for token in ("t2", "t3"):  # the jobs bucket is full: the day bucket must not count these
        out = limiter.acquire(token, [jobs, day])
        assert not out.granted and [u.used for u in out.usage] == [1, 1]
    limiter.release("t1", ["k:jobs", "k:day"])  # a failed upload gives both places back
    out = limiter.acquire("t4", [jobs, day])
    assert out.granted and [u.used for u in out.usage] == [1, 1]


def test_live_tokens_count_whatever_their_deadline(backend) -> None:
    limiter, clock = backend
    claim = Claim("k:jobs", limit=2, hold_s=3600)
    assert limiter.acquire("job-a", [claim]).granted
    limiter.hold("job-a", "k:jobs", 10)  # its record exists: the database lists it from now on
    clock.t += 11
    # job-a's hold is over, but the database still lists it as unfinished, and so does job-b
    refused = limiter.acquire("job-c", [Claim("k:jobs", 2, 3600, live=["job-a", "job-b"])])
    assert not refused.granted and refused.usage[0].used == 2
    # job-a finished: only job-b is live
    out = limiter.acquire("job-c", [Claim("k:jobs", 2, 3600, live=["job-b"])])
    assert out.granted and out.usage[0].used == 2
    # a live token that is also held counts once
    out = limiter.acquire("job-d", [Claim("k:jobs", 3, 3600, live=["job-b", "job-c"])])
    assert out.granted and out.usage[0].used == 3
    limiter.hold("no-such-token", "k:jobs", 3600)  # holding an absent token adds nothing
    out = limiter.acquire("job-e", [Claim("k:jobs", 3, 3600)])
    assert out.granted and out.usage[0].used == 3  # job-c, job-d, job-e


def test_buckets_are_independent(backend) -> None:
    limiter, _ = backend
    assert limiter.acquire("t", [Claim("a:renders", 1, 1.0)]).granted
    assert not limiter.acquire("u", [Claim("a:renders", 1, 1.0)]).granted
    assert limiter.acquire("u", [Claim("b:renders", 1, 1.0)]).granted  # another key's bucket


def _hammer(limiters: list, claim: Claim, threads: int, tries: int) -> int:
    """Acquires from ``threads`` threads at once (round robin over ``limiters``); the number granted."""
    granted, lock = [0], threading.Lock()
    start = threading.Barrier(threads)

    def work(n: int) -> None:
        limiter = limiters[n % len(limiters)]
        start.wait()
        for _ in range(tries):
            if limiter.acquire(uuid.uuid4().hex, [claim]).granted:
                with lock:
                    granted[0] += 1

    pool = [threading.Thread(target=work, args=(n,)) for n in range(threads)]
    for t in pool:
        t.start()
    for t in pool:
        t.join()
    return granted[0]


def test_concurrent_acquires_never_pass_the_limit_in_memory() -> None:
    assert _hammer([MemoryLimiter()], Claim("k:day", limit=25, hold_s=3600), threads=8, tries=20) == 25


def test_concurrent_acquires_from_several_replicas_never_pass_the_limit(redis_prefix: str) -> None:
    replicas = [RedisLimiter(REDIS_URL, prefix=redis_prefix) for _ in range(4)]  # 4 API processes' clients
    assert _hammer(replicas, Claim("k:day", limit=25, hold_s=3600), threads=8, tries=20) == 25
    # the same with live tokens from the database in the count
    live = Claim("k:jobs", limit=3, hold_s=3600, live=["running-1"])
    assert _hammer(replicas, live, threads=8, tries=5) == 2


def test_redis_counts_on_its_own_clock_and_keys_expire(redis_prefix: str) -> None:
    import redis

    limiter = RedisLimiter(REDIS_URL, prefix=redis_prefix)  # the server's clock
    claim = [Claim("k:renders", limit=2, hold_s=0.3)]
    assert [limiter.acquire(f"t{i}", claim).granted for i in range(3)] == [True, True, False]
    r = redis.Redis.from_url(REDIS_URL)
    ttl_ms = r.pttl(f"{redis_prefix}:k:renders")
    assert 0 < ttl_ms <= 300  # the key lives no longer than its last deadline
    time.sleep(0.35)
    assert limiter.acquire("t3", claim).granted  # the window passed
    time.sleep(0.35)
    assert not r.exists(f"{redis_prefix}:k:renders")  # nothing left behind
    r.close()


def test_unreachable_redis_says_so_at_once() -> None:
    limiter = RedisLimiter("redis://127.0.0.1:1/0", timeout_s=0.2, retry_s=30)
    with pytest.raises(LimiterUnavailable):
        limiter.acquire("t", [Claim("k:renders", 1, 1.0)])
    t0 = time.perf_counter()
    for _ in range(100):  # no connection attempts while it is known to be down
        with pytest.raises(LimiterUnavailable):
            limiter.acquire("t", [Claim("k:renders", 1, 1.0)])
    assert time.perf_counter() - t0 < 0.1
