"""A Redis outage at the hand-off from pose estimation to training (issue 15, item 6).

The test starts its own redis-server (persistence on, a free port), runs the pose phase of a
job in this process with the real Celery client, and kills Redis the moment the phase hands the
job to training. The job must say that it waits for a worker and why, and its training message
must reach the restarted Redis as soon as it is back (the outbox), not after the reaper's
``CMC_REQUEUE_AFTER_SECONDS`` (two hours by default).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import time
from pathlib import Path

import pytest
from helpers import synthetic_upload

pytestmark = pytest.mark.skipif(
    shutil.which("redis-server") is None and not os.environ.get("CI"), reason="needs the redis-server binary"
)


class RedisServer:
    """redis-server on a free port of 127.0.0.1, its data (append-only file) in ``folder``."""

    def __init__(self, folder: Path):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            self.port = s.getsockname()[1]
        self.folder = folder
        self.url = f"redis://127.0.0.1:{self.port}/0"
        self.proc: subprocess.Popen | None = None

    def start(self) -> None:
        args = ["redis-server", "--port", str(self.port), "--bind", "127.0.0.1", "--dir", str(self.folder)]
        args += ["--appendonly", "yes", "--appendfsync", "always", "--save", ""]
        self.proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
        t0 = time.time()
        while True:
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=1).close()
                return
            except OSError:
                assert time.time() - t0 < 20 and self.proc.poll() is None, "redis-server did not start"
                time.sleep(0.05)

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)  # a crash: only what it persisted survives
            self.proc.wait(10)


def test_training_message_is_sent_as_soon_as_redis_is_back(tmp_path: Path, monkeypatch) -> None:
    import redis
    from fastapi.testclient import TestClient

    import worker.pipeline as pipeline
    from service.app import create_app
    from service.settings import load_settings
    from worker.context import JobContext
    from worker.pipeline import run_job

    server = RedisServer(tmp_path)
    server.start()
    try:
        settings = load_settings(
            data_dir=tmp_path / "data", mode="celery", broker_url=server.url, api_keys="", api_keys_file=None
        )
        app = create_app(settings)
        parts, _, _ = synthetic_upload(steps=5)  # with its cameras: no structure from motion
        api = TestClient(app, base_url="http://localhost")
        sid = api.post("/v1/scenes", files=parts).json()["id"]
        svc = app.state.services
        ctx = JobContext(svc.store, svc.storage, svc.queue, settings)

        advance = svc.store.advance

        def redis_dies_at_the_hand_off(*args, **kwargs):
            server.kill()
            return advance(*args, **kwargs)

        monkeypatch.setattr(svc.store, "advance", redis_dies_at_the_hand_off)
        monkeypatch.setattr(pipeline, "SEND_RETRY_SECONDS", 1.0, raising=False)
        t0 = time.time()
        assert run_job(ctx, sid, "poses") == "done"
        assert time.time() - t0 < 30  # one try, not a wait for the broker
        waiting = api.get(f"/v1/scenes/{sid}").json()
        assert waiting["status"] == "training" and waiting["progress"] == 0.0
        assert waiting["detail"].startswith("waiting for a worker: the job queue cannot be reached")

        server.start()  # same port, same data: Redis restarted with persistence on
        sent: list[str] = []
        t0 = time.time()
        while not sent and time.time() - t0 < 20:  # what every Celery worker runs each second
            sent = pipeline.deliver(ctx)
            time.sleep(0.2)
        assert sent == [sid], f"not sent {time.time() - t0:.0f} s after Redis came back"
        r = redis.Redis.from_url(server.url)
        messages = [json.loads(m) for m in r.lrange(settings.gpu_queue, 0, -1)]
        r.close()
        assert [(m["headers"]["task"], m["headers"]["argsrepr"]) for m in messages] == [("cmc.train", f"['{sid}']")]
        assert api.get(f"/v1/scenes/{sid}").json()["detail"] == "waiting for a worker"
        assert pipeline.deliver(ctx) == []  # sent once
    finally:
        server.kill()
