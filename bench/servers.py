"""What the service benchmarks share: a free port, waiting for a started server, the report.

Imported by the bench/ scripts that start the API (run as ``python bench/NAME.py``, so this
folder is on ``sys.path``); tests/helpers.py takes :func:`free_port` from here too.
"""

from __future__ import annotations

import json
import os
import random
import signal
import socket
import subprocess
import time
from collections.abc import Iterable
from pathlib import Path

import httpx2


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now, drawn below the kernel's range of
    ephemeral ports (``/proc/sys/net/ipv4/ip_local_port_range``; 32768 and up by default): a port
    from that range can be taken by any outgoing connection (to Redis, PostgreSQL, S3) between
    this check and the bind of the server it is for."""
    try:
        low = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        low = 32768
    first = max(1024, low - 12000)
    for _ in range(200):
        port = random.randrange(first, low)
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise RuntimeError(f"no free port in {first}-{low - 1}")


def wait_ready(
    url: str, path: str = "/readyz", tries: int = 300, proc: subprocess.Popen | None = None, log: Path | None = None
) -> None:
    """Poll ``url + path`` every 0.2 s until it answers 200; RuntimeError (with the end of
    ``log``) when ``proc`` exits first or after ``tries`` polls."""
    tail = lambda: log.read_text()[-3000:] if log is not None and log.exists() else ""  # noqa: E731
    for _ in range(tries):
        if proc is not None and proc.poll() is not None:
            raise RuntimeError(f"the server at {url} exited:\n{tail()}")
        try:
            if httpx2.get(url + path, timeout=2).status_code == 200:
                return
        except httpx2.HTTPError:
            pass
        time.sleep(0.2)
    raise RuntimeError(f"no answer from {url}{path}:\n{tail()}")


def stop_process_groups(procs: Iterable[subprocess.Popen], grace_s: float = 15) -> None:
    """Stop processes each started in a process group of its own (``start_new_session=True``):
    SIGTERM every group, wait up to ``grace_s`` seconds in all, then SIGKILL the group of any
    process still running. A group already gone is skipped."""

    def signal_group(p: subprocess.Popen, sig: signal.Signals) -> None:
        try:
            os.killpg(p.pid, sig)
        except ProcessLookupError:
            pass

    procs = list(procs)
    for p in procs:
        signal_group(p, signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    for p in procs:
        try:
            p.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            signal_group(p, signal.SIGKILL)
            p.wait()


def flush_redis(redis_url: str) -> None:
    """Empty the benchmark's own Redis database (its ``--redis`` URL names one apart)."""
    import redis

    redis.Redis.from_url(redis_url).flushdb()


def write_report(report: dict, out: str | Path) -> None:
    """Write ``report`` as indented JSON to ``out``."""
    out = Path(out)
    out.write_text(json.dumps(report, indent=1) + "\n")
    print(f"wrote {out}")
