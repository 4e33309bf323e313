"""Signed webhooks, delivered to a real HTTP receiver on 127.0.0.1 (allowed here by
CMC_WEBHOOK_ALLOW_PRIVATE): the signature checks out with the README's recipe, a 500 is retried
with exponential backoff and the same idempotency id, a receiver that never succeeds is given
up after ``webhook_max_attempts`` tries, callback URLs to private addresses are refused. Both
senders: the embedded mode's thread (a real job that fails, and a scene made ready) and the
Celery task in a real worker on the real Redis."""

from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from helpers import REDIS_URL, synthetic_upload
from test_service_api import RecordingQueue, png, settings_for, wait_for

from service.app import create_app
from service.db.scenes import SceneStore
from service.settings import load_settings
from service.webhooks import CallbackRefused, owner_secret, resolve_callback, sign, verify
from worker.webhooks import backoff, deliver

ROOT = Path(__file__).resolve().parents[1]
SECRET = "test-master-secret"


class Receiver:
    """An HTTP server on 127.0.0.1 answering POSTs with the given status codes in turn (the last
    one from then on), recording (monotonic time, headers, raw body) of each."""

    def __init__(self, statuses: list[int]):
        self.statuses, self.calls = list(statuses), []
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:  # noqa: N802 - http.server's name
                body = self.rfile.read(int(self.headers["Content-Length"]))
                receiver.calls.append((time.monotonic(), dict(self.headers), body))
                status = receiver.statuses[min(len(receiver.calls), len(receiver.statuses)) - 1]
                self.send_response(status)
                self.send_header("Content-Length", "0")
                self.end_headers()

            def log_message(self, *args: object) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/hooks/cmc?source=test"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)

    def wait(self, n: int, timeout: float = 30) -> None:
        t0 = time.time()
        while len(self.calls) < n:
            assert time.time() - t0 < timeout, f"{len(self.calls)} of {n} calls after {timeout} s"
            time.sleep(0.05)


@pytest.fixture
def receiver() -> Iterator[callable]:
    made: list[Receiver] = []

    def make(*statuses: int) -> Receiver:
        r = Receiver(list(statuses))
        r.thread.start()
        made.append(r)
        return r

    yield make
    for r in made:
        r.server.shutdown()
        r.server.server_close()


def hook_settings(tmp: Path, **overrides):
    base = dict(webhook_secret=SECRET, webhook_allow_private=True, webhook_backoff_seconds=0.3, webhook_max_attempts=3)
    return settings_for(tmp, **{**base, **overrides})


def wait_delivery(client: TestClient, sid: str, status: str, timeout: float = 30) -> dict:
    t0 = time.time()
    while True:
        log = client.get(f"/v1/scenes/{sid}/webhooks").json()
        if log["deliveries"] and all(d["status"] == status for d in log["deliveries"]):
            return log
        assert time.time() - t0 < timeout, log
        time.sleep(0.1)


def _readme_recipe():
    """The README's verification recipe, run as it stands (a receiver's code, none of ours)."""
    section = (ROOT / "README.md").read_text().split("### Webhooks", 1)[1]
    (code,) = [b for b in re.findall(r"```python\n(.*?)```", section, flags=re.S) if "def verify_cmc_webhook" in b]
    namespace: dict = {}
    exec(code, namespace)
    return namespace["verify_cmc_webhook"]


readme_verify = _readme_recipe()


# -- signing and URL checks --------------------------------------------------------------------------


def test_signature_and_per_key_secrets() -> None:
    body, ts = b'{"id":"x","type":"scene.ready"}', int(time.time())
    secret = owner_secret(SECRET, "owner-a")
    assert secret.startswith("whsec_") and secret != owner_secret(SECRET, "owner-b")
    assert secret != owner_secret("another-master", "owner-a")
    signature = sign(secret, ts, body)
    assert verify(secret, body, str(ts), signature)
    assert readme_verify(secret, {"CMC-Webhook-Timestamp": str(ts), "CMC-Webhook-Signature": signature}, body)
    assert not verify(secret, body + b" ", str(ts), signature)  # another body
    assert not verify(owner_secret(SECRET, "owner-b"), body, str(ts), signature)  # another key's secret
    assert not verify(secret, body, str(ts + 1), signature)  # another timestamp
    old = ts - 3600
    assert not verify(secret, body, str(old), sign(secret, old, body))  # a replay of an old try


@pytest.mark.parametrize(
    "url",
    [
        "http://127.0.0.1:9/hook",
        "http://localhost/hook",
        "http://[::1]/hook",
        "http://[::ffff:127.0.0.1]/hook",
        "http://10.0.0.7/hook",
        "http://192.168.1.20:8080/",
        "http://169.254.169.254/latest/meta-data",
        "http://100.64.0.1/",
        "http://0.0.0.0/",
    ],
)
def test_private_callback_addresses_are_refused(url: str) -> None:
    with pytest.raises(CallbackRefused, match="non-public"):
        resolve_callback(url, allow_private=False)


def test_callback_url_shape() -> None:
    for bad in ("ftp://8.8.8.8/x", "8.8.8.8/hook", "http:///hook", "http://user:pw@8.8.8.8/", "http://8.8.8.8:99999/"):
        with pytest.raises(CallbackRefused):
            resolve_callback(bad, allow_private=True)
    parts, addresses = resolve_callback("https://8.8.8.8/hook?x=1", allow_private=False)  # public: accepted
    assert parts.hostname == "8.8.8.8" and [str(a) for a in addresses] == ["8.8.8.8"]
    assert [str(a) for a in resolve_callback("http://127.0.0.1/", allow_private=True)[1]] == ["127.0.0.1"]


def test_upload_with_a_refused_callback_url_keeps_nothing(tmp_path: Path, receiver) -> None:
    parts, _, _ = synthetic_upload()
    queue = RecordingQueue()
    r = receiver(200)

    def upload(callback: str, **overrides) -> dict:
        app = create_app(settings_for(tmp_path, **overrides), queue=queue)
        with TestClient(app) as client:
            return client.post("/v1/scenes", files=[*parts, ("callback_url", (None, callback))]).json()

    refused = upload(r.url, webhook_secret=SECRET)  # 127.0.0.1 without CMC_WEBHOOK_ALLOW_PRIVATE
    assert refused["error"]["code"] == "invalid_callback_url" and "127.0.0.1" in refused["error"]["message"]
    off = upload(r.url, webhook_allow_private=True)  # no secret: nothing could be signed
    assert off["error"]["code"] == "webhooks_not_configured"
    assert queue.sent == [] and [p.name for p in (tmp_path / "storage").iterdir() if p.name[0] != "."] == []
    accepted = upload(r.url, webhook_secret=SECRET, webhook_allow_private=True)
    assert accepted["status"] == "queued" and accepted["links"]["webhooks"].endswith("/webhooks")


def test_delivery_checks_the_address_again(tmp_path: Path, receiver) -> None:
    """A URL accepted earlier (say, before its DNS name moved to a private address) is checked at
    every try: the receiver is never called and the refusal is in the log."""
    r = receiver(200)
    store = SceneStore(f"sqlite:///{tmp_path / 'db.sqlite'}")
    rec, _ = store.create("local", {}, ["a.png"], ["00.png"], False, callback_url=r.url)
    store.add_event(rec.id, "video.ready", {"path": "orbit"})
    (d,) = store.deliveries(rec.id)
    s = load_settings(data_dir=tmp_path, webhook_secret=SECRET, webhook_backoff_seconds=5)
    assert deliver(store, s, d.id) == 5
    assert deliver(store, s, d.id) is None  # not due yet: claimed by nobody
    (d,) = store.deliveries(rec.id)
    assert d.status == "pending" and "non-public" in d.attempts[0]["error"] and d.attempts[0]["status_code"] is None
    assert r.calls == []


def test_a_delivery_is_claimed_once() -> None:
    """Two senders (a duplicate Celery message) do not both try the same delivery."""
    store = SceneStore("sqlite://")
    rec, _ = store.create("local", {}, ["a.png"], ["00.png"], False, callback_url="http://8.8.8.8/")
    store.add_event(rec.id, "scene.ready", {"status": "ready"})
    (d,) = store.deliveries(rec.id)
    assert store.claim_delivery(d.id, 30) is not None
    assert store.claim_delivery(d.id, 30) is None
    assert store.due_deliveries(time.time()) == []
    bare, _ = store.create("local", {}, ["a.png"], ["00.png"], False)  # no callback: no events
    store.add_event(bare.id, "scene.ready", {"status": "ready"})
    assert store.deliveries(bare.id) == []


# -- the embedded sender ------------------------------------------------------------------------------


def test_failed_job_webhook_is_signed_and_retried_after_a_500(tmp_path: Path, receiver) -> None:
    """A real job that fails (photos without texture: pose estimation fails) calls back; the
    first try gets a 500, the second (after the backoff) a 200, with the same id and body."""
    r = receiver(500, 200)
    blank = png(np.full((72, 96, 3), 0.5))
    parts = [("images", (f"IMG_{i}.png", blank, "image/png")) for i in range(3)]
    with TestClient(create_app(hook_settings(tmp_path))) as client:
        sid = client.post("/v1/scenes", files=[*parts, ("callback_url", (None, r.url))]).json()["id"]
        body = wait_for(client, sid, ("failed", "ready"), timeout=120)
        assert body["status"] == "failed"
        log = wait_delivery(client, sid, "delivered")
        secret = client.get("/v1/webhooks/secret").json()
    assert secret["secret"] == owner_secret(SECRET, "local") and secret["signature_header"] == "CMC-Webhook-Signature"
    assert len(r.calls) == 2
    (t1, h1, b1), (t2, h2, b2) = r.calls
    assert b1 == b2 and h1["CMC-Webhook-Id"] == h2["CMC-Webhook-Id"]  # one event, tried twice
    assert t2 - t1 >= 0.3  # the backoff
    event = json.loads(b2)
    assert event["id"] == h2["CMC-Webhook-Id"] and event["type"] == "scene.failed" and event["scene_id"] == sid
    assert event["data"]["error"] == body["error"] and event["data"]["status"] == "failed"
    assert h2["Content-Type"] == "application/json"
    for headers, raw in ((h1, b1), (h2, b2)):
        assert readme_verify(secret["secret"], headers, raw)
        assert not readme_verify(owner_secret(SECRET, "someone-else"), headers, raw)
    assert log["callback_url"] == r.url
    (delivery,) = log["deliveries"]
    assert delivery["id"] == event["id"] and delivery["type"] == "scene.failed" and delivery["body"] == event
    assert [a["status_code"] for a in delivery["attempts"]] == [500, 200]
    assert delivery["attempts"][0]["error"] == "HTTP 500" and delivery["attempts"][1]["error"] is None
    assert delivery["delivered_at"] and delivery["next_attempt_at"] is None


def test_ready_webhook_gives_up_after_n_tries(tmp_path: Path, receiver) -> None:
    """A scene made ready the way the pipeline does it (store.advance) records its event in the
    same transaction; a receiver that always answers 500 is tried max_attempts times with
    doubling waits, then the delivery is failed and nobody calls again."""
    r = receiver(500)
    app = create_app(hook_settings(tmp_path, webhook_max_attempts=3, webhook_backoff_seconds=0.4))
    store = app.state.services.store
    with TestClient(app) as client:
        rec, _ = store.create("local", {}, ["a.png"], ["00.png"], False, callback_url=r.url)
        assert store.claim(rec.id, "poses", "test-worker", 60) is not None
        assert store.advance(rec.id, "test-worker", "done", "ready")
        app.state.services.queue.submit_webhook("", 0)  # the pipeline's kick: wakes the sender
        log = wait_delivery(client, rec.id, "failed")
        time.sleep(1.0)
    assert len(r.calls) == 3  # and no fourth
    times = [t for t, _, _ in r.calls]
    gaps = np.diff(times)
    assert gaps[0] >= 0.4 and gaps[1] >= 0.8, gaps  # backoff(1), backoff(2)
    (delivery,) = log["deliveries"]
    assert delivery["type"] == "scene.ready" and delivery["body"]["data"] == {"status": "ready"}
    assert [a["status_code"] for a in delivery["attempts"]] == [500, 500, 500]
    assert delivery["next_attempt_at"] is None and delivery["delivered_at"] is None
    assert len({h["CMC-Webhook-Id"] for _, h, _ in r.calls}) == 1
    assert backoff(hook_settings(tmp_path, webhook_backoff_max_seconds=1.0), 5) == 1.0  # capped


def test_webhook_log_is_the_owners_only(tmp_path: Path) -> None:
    app = create_app(settings_for(tmp_path, api_keys="key-a,key-b", webhook_secret=SECRET), queue=RecordingQueue())
    with TestClient(app) as client:
        rec, _ = app.state.services.store.create("x", {}, ["a.png"], ["00.png"], False)
        a = {"Authorization": "Bearer key-a"}
        assert client.get(f"/v1/scenes/{rec.id}/webhooks", headers=a).status_code == 404
        secret_a = client.get("/v1/webhooks/secret", headers=a).json()["secret"]
        secret_b = client.get("/v1/webhooks/secret", headers={"Authorization": "Bearer key-b"}).json()["secret"]
        assert secret_a != secret_b
        assert client.get("/v1/webhooks/secret").status_code == 401


# -- the Celery task ------------------------------------------------------------------------------------


def _redis_reachable() -> bool:
    try:
        socket.create_connection(("127.0.0.1", 6379), timeout=2).close()
        return True
    except OSError:
        return False


def test_celery_task_retries_with_backoff(tmp_path: Path, receiver) -> None:
    """The cmc.webhook task in a real Celery worker (its own queue, Redis database 14): two 500s,
    then a 200; each retry is a new message sent with the backoff as its countdown."""
    if not _redis_reachable():
        if os.environ.get("CI"):
            pytest.fail("Redis at 127.0.0.1:6379 is needed")
        pytest.skip("needs Redis at 127.0.0.1:6379")
    import redis

    r = receiver(500, 500, 200)
    queue_name = f"webhooks-{uuid.uuid4().hex[:8]}"
    db_url = f"sqlite:///{tmp_path / 'cmc.db'}"
    env = {k: v for k, v in os.environ.items() if not k.startswith("CMC_")}
    env.update(
        PYTHONPATH=str(ROOT),
        CMC_MODE="celery",
        CMC_BROKER_URL=REDIS_URL,
        CMC_DATABASE_URL=db_url,
        CMC_DATA_DIR=str(tmp_path),
        CMC_WEBHOOK_QUEUE=queue_name,
        CMC_WEBHOOK_SECRET=SECRET,
        CMC_WEBHOOK_ALLOW_PRIVATE="true",
        CMC_WEBHOOK_BACKOFF_SECONDS="0.5",
        CMC_WEBHOOK_MAX_ATTEMPTS="4",
    )
    store = SceneStore(db_url)  # creates the tables before the worker opens the database
    rec, _ = store.create("local", {}, ["a.png"], ["00.png"], False, callback_url=r.url)
    store.add_event(rec.id, "video.ready", {"path": "orbit"})
    (d,) = store.deliveries(rec.id)
    log = open(tmp_path / "worker.log", "wb")  # noqa: SIM115 - closed below
    worker = subprocess.Popen(
        [sys.executable, "-m", "celery", "-A", "worker.celery_app", "worker", "-Q", queue_name, "-c", "1"]
        + ["-n", f"{queue_name}@%h", "--without-gossip", "--without-mingle", "--loglevel", "INFO"],
        env=env,
        cwd=ROOT,
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    try:
        from service.jobs import CeleryJobQueue

        CeleryJobQueue(REDIS_URL, webhook_queue=queue_name).submit_webhook(d.id)
        try:
            r.wait(3, timeout=90)
        except AssertionError:
            raise AssertionError((tmp_path / "worker.log").read_text()[-3000:]) from None
        t0 = time.time()
        while (d := store.delivery(d.id)).status == "pending":
            assert time.time() - t0 < 10
            time.sleep(0.1)
    finally:
        os.killpg(worker.pid, 15)
        worker.wait(20)
        log.close()
        client = redis.Redis.from_url(REDIS_URL)
        client.delete(queue_name)
        client.close()
    assert d.status == "delivered" and [a["status_code"] for a in d.attempts] == [500, 500, 200]
    gaps = np.diff([t for t, _, _ in r.calls])
    assert gaps[0] >= 0.5 and gaps[1] >= 1.0, gaps
    for _, headers, body in r.calls:
        assert readme_verify(owner_secret(SECRET, "local"), headers, body)
        assert json.loads(body)["id"] == d.id
    assert "cmc.webhook" in (tmp_path / "worker.log").read_text()
