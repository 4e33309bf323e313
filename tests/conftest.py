"""Fixtures shared by several test files."""

from __future__ import annotations

import os
import shutil
import uuid
from collections.abc import Iterator

import pytest
from helpers import CHROMIUM_ARGS, REDIS_URL, browser_unavailable


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
