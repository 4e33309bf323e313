"""Fixtures shared by several test files."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
import urllib.request
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
from helpers import CHROMIUM_ARGS, REDIS_URL, S3_CREDENTIALS, browser_unavailable, free_port


@pytest.fixture
def redis_prefix() -> Iterator[str]:
    """A key prefix of this test's own in the real Redis (``REDIS_URL``); its keys are deleted
    after. Skips when Redis cannot be reached, except under CI, where it fails."""
    import redis

    r = redis.Redis.from_url(REDIS_URL, socket_connect_timeout=2)
    try:
        r.ping()
    except redis.RedisError as e:
        if os.environ.get("CI"):
            raise
        pytest.skip(f"no Redis at {REDIS_URL}: {e}")
    prefix = f"cmc-test:{uuid.uuid4().hex}"
    try:
        yield prefix
    finally:
        keys = list(r.scan_iter(f"{prefix}:*"))
        if keys:
            r.delete(*keys)
        r.close()


@pytest.fixture(scope="module")
def browser():
    """A headless Chromium (Debian's, or ``CMC_CHROMIUM``) driven by Playwright, one per module."""
    chromium = os.environ.get("CMC_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        browser_unavailable("Debian's chromium is not installed (apt-get install -y chromium)")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        browser_unavailable("playwright is not installed (pip install -e '.[dev]')")
    with sync_playwright() as p:
        # Playwright starts every launch with a fresh temporary profile (user data dir).
        b = p.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS, headless=True)
        yield b
        b.close()


@pytest.fixture(scope="module")
def s3() -> Iterator[str]:
    """The endpoint URL of an S3 server of this module's own: moto's standalone server (an
    emulator, ``moto[server]`` of the dev extras) as a subprocess; its credentials
    (``S3_CREDENTIALS``) are in the environment meanwhile."""
    port = free_port()
    server = Path(sys.executable).parent / "moto_server"
    proc = subprocess.Popen(
        [str(server), "-H", "127.0.0.1", "-p", str(port)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    url = f"http://127.0.0.1:{port}"
    try:
        t0 = time.time()
        while True:
            try:
                urllib.request.urlopen(f"{url}/moto-api/", timeout=1).close()
                break
            except OSError:
                assert proc.poll() is None and time.time() - t0 < 30, "moto_server did not start"
                time.sleep(0.1)
        with pytest.MonkeyPatch.context() as mp:
            for k, v in S3_CREDENTIALS.items():
                mp.setenv(k, v)
            yield url
    finally:
        proc.terminate()
        proc.wait(10)
