"""The deployed shape, on this machine: uvicorn (API, Celery mode) and Celery workers for the
``cpu`` and ``gpu`` queues as separate processes, the real Redis at 127.0.0.1:6379 as broker and
the real PostgreSQL at 127.0.0.1:5432 as the scene store.

1. Upload a tiny synthetic scene, poll to ``ready``, render a novel camera and its depth and
   compare them with the scene's exact ground truth.
2. Kill the GPU worker (SIGKILL, its whole process group) mid-training; a new GPU worker resumes
   the job from its last checkpoint, not from zero; also with the artifacts in an S3 bucket
   (moto_server) and a data folder of each process's own (no shared volume).
3. Stop the API (SIGTERM, as ``docker compose stop``) in the middle of an upload: the client gets
   an error, and no scene, artifact or working folder is left.

The API runs with docker-compose.yml's command (bench/deployment_test.py runs the images).

Each test uses its own queue names and PostgreSQL database; Redis database 14 is the tests' own
and is emptied after each test (queues, bindings, the killed worker's unacknowledged message).
"""

from __future__ import annotations

import io
import json
import os
import signal
import socket
import subprocess
import sys
import time
import uuid
from pathlib import Path

import httpx2
import numpy as np
import pytest
import yaml
from helpers import (
    PG_ADMIN,
    REDIS_URL,
    S3_CREDENTIALS,
    free_port,
    new_bucket,
    render_body,
    synthetic_upload,
    throwaway_postgres,
)
from PIL import Image

from cmc.data.datasets import DEFAULT_LAYERS, render_layers
from cmc.eval.metrics import psnr

ROOT = Path(__file__).resolve().parents[1]


def _reachable(url: str, port: int) -> bool:
    host = url.split("://", 1)[1].split("@")[-1].split(":")[0].split("/")[0]
    try:
        socket.create_connection((host, port), timeout=2).close()
        return True
    except OSError:
        return False


class Deployment:
    """The API and workers as child processes sharing one environment."""

    def __init__(self, tmp: Path, database_url: str):
        run = uuid.uuid4().hex[:8]
        self.tmp = tmp
        self.own_data_dirs = False  # True: CMC_DATA_DIR is tmp/<process name>, shared by none
        self.port = free_port()
        self.env = {
            **os.environ,
            "PYTHONPATH": str(ROOT),
            "PYTHONUNBUFFERED": "1",
            "CMC_MODE": "celery",
            "CMC_BROKER_URL": REDIS_URL,
            "CMC_DATABASE_URL": database_url,
            "CMC_STORAGE_DIR": str(tmp / "storage"),
            "CMC_CPU_QUEUE": f"cpu-{run}",
            "CMC_GPU_QUEUE": f"gpu-{run}",
            "CMC_API_KEYS": f"integration-key-{run}",  # a key per run: its quotas in Redis start at zero
            "CMC_CHECKPOINT_EVERY": "5",
            "CMC_LEASE_SECONDS": "4",
            "CMC_HEARTBEAT_SECONDS": "0.5",
            "CMC_DEVICE": "cpu",
        }
        self.logs = tmp / "logs"
        self.logs.mkdir()
        self.procs: dict[str, subprocess.Popen] = {}
        self.headers = {"Authorization": f"Bearer integration-key-{run}"}
        self.url = f"http://127.0.0.1:{self.port}"

    def start(self, name: str, args: list[str]) -> subprocess.Popen:
        log = open(self.logs / f"{name}.log", "ab")  # noqa: SIM115 - closed with the process
        env = {**self.env, "CMC_DATA_DIR": str(self.tmp / name)} if self.own_data_dirs else self.env
        p = subprocess.Popen(args, env=env, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT, start_new_session=True)
        self.procs[name] = p
        return p

    def start_api(self) -> None:
        """The API as docker-compose.yml starts it, on 127.0.0.1 and a free port."""
        cmd = yaml.safe_load((ROOT / "docker-compose.yml").read_text())["services"]["api"]["command"]
        assert cmd[0] == "uvicorn"
        cmd[cmd.index("--host") + 1], cmd[cmd.index("--port") + 1] = "127.0.0.1", str(self.port)
        self.start("api", [sys.executable, "-m", *cmd])
        t0 = time.time()
        while time.time() - t0 < 60:
            try:
                if httpx2.get(f"{self.url}/readyz", timeout=2).status_code == 200:
                    return
            except httpx2.HTTPError:
                pass
            time.sleep(0.3)
        raise AssertionError(f"API did not become ready:\n{self.log('api')}")

    def start_worker(self, name: str, queue: str) -> subprocess.Popen:
        return self.start(
            name,
            [
                sys.executable,
                "-m",
                "celery",
                "-A",
                "worker.celery_app",
                "worker",
                "-Q",
                self.env[queue],
                "--concurrency",
                "1",
                "--prefetch-multiplier",
                "1",
                "-n",
                f"{name}@%h",
                "--without-gossip",
                "--without-mingle",
                "--loglevel",
                "INFO",
            ],
        )

    def start_all(self) -> None:
        """The API, a CPU worker and a GPU worker."""
        self.start_api()
        self.start_worker("cpu", "CMC_CPU_QUEUE")
        self.start_worker("gpu", "CMC_GPU_QUEUE")

    def kill(self, name: str) -> None:
        p = self.procs.pop(name)
        try:
            os.killpg(p.pid, signal.SIGKILL)  # the worker and its pool child: a node dying
        except ProcessLookupError:
            pass
        p.wait(10)

    def stop(self) -> None:
        for name in list(self.procs):
            p = self.procs[name]
            try:
                os.killpg(p.pid, signal.SIGTERM)
                p.wait(10)
            except (ProcessLookupError, subprocess.TimeoutExpired):
                self.kill(name)

    def log(self, name: str) -> str:
        return "\n".join((self.logs / f"{name}.log").read_text(errors="replace").splitlines()[-40:])

    def status(self, sid: str) -> dict:
        return httpx2.get(f"{self.url}/v1/scenes/{sid}", headers=self.headers, timeout=10).json()

    def wait(self, sid: str, until, timeout: float) -> dict:
        t0 = time.time()
        while time.time() - t0 < timeout:
            body = self.status(sid)
            if until(body):
                return body
            time.sleep(0.3)
        logs = "\n\n".join(f"--- {n}\n{self.log(n)}" for n in os.listdir(self.logs))
        raise AssertionError(f"timed out at {body}\n{logs}")


@pytest.fixture
def deployment(tmp_path):
    if not _reachable(REDIS_URL, 6379) or not _reachable(PG_ADMIN, 5432):
        if os.environ.get("CI"):
            pytest.fail("Redis at 127.0.0.1:6379 and PostgreSQL at 127.0.0.1:5432 are needed")
        pytest.skip("needs Redis at 127.0.0.1:6379 and PostgreSQL at 127.0.0.1:5432")
    import redis

    with throwaway_postgres("cmc_it_") as url:
        d = Deployment(tmp_path, url)
        try:
            yield d
        finally:
            d.stop()
            r = redis.Redis.from_url(REDIS_URL)
            r.flushdb()  # database 14 is these tests' own: queues, bindings, the killed worker's unacked message
            r.close()


def test_upload_poll_render_and_depth_across_processes(deployment: Deployment) -> None:
    d = deployment
    d.start_all()
    parts, _, novel = synthetic_upload(steps=25)
    r = httpx2.post(f"{d.url}/v1/scenes", files=parts, headers=d.headers, timeout=30)
    assert r.status_code == 202, r.text
    # counted in Redis by the deployed API: 1 of its 4 unfinished jobs (the limit closest to refusing)
    assert (r.headers["ratelimit-limit"], r.headers["ratelimit-remaining"]) == ("4", "3")
    sid = r.json()["id"]
    seen = set()
    body = d.wait(sid, lambda b: seen.add(b["status"]) or b["status"] in ("ready", "failed"), timeout=400)
    assert body["status"] == "ready", body
    assert "training" in seen
    render = httpx2.post(f"{d.url}/v1/scenes/{sid}/render", json=render_body(novel), headers=d.headers, timeout=60)
    assert render.status_code == 200 and render.headers["ratelimit-limit"] == "10"
    gt_rgb, gt_depth = render_layers(DEFAULT_LAYERS, novel)
    rgb = np.asarray(Image.open(io.BytesIO(render.content)).convert("RGB"), dtype=np.float32) / 255
    assert psnr(rgb, gt_rgb[0]) > 25.0  # as in test_service_api (untrained: 23.5 dB, depth 29 %)
    depth_r = httpx2.post(
        f"{d.url}/v1/scenes/{sid}/depth",
        json=render_body(novel),
        headers={**d.headers, "Accept": "application/x-npy"},
        timeout=60,
    )
    depth = np.load(io.BytesIO(depth_r.content))
    assert np.median(np.abs(depth - gt_depth[0]) / gt_depth[0]) < 0.18
    metrics = httpx2.get(f"{d.url}/metrics", timeout=10).text
    assert 'cmc_jobs{status="ready"} 1.0' in metrics
    assert f'cmc_queue_depth{{queue="{d.env["CMC_GPU_QUEUE"]}"}} 0.0' in metrics
    # the queues are separate: poses ran on the CPU worker only, training on the GPU worker only
    assert "Task cmc.poses[" in d.log("cpu") and "Task cmc.train[" not in d.log("cpu")
    assert "Task cmc.train[" in d.log("gpu") and "Task cmc.poses[" not in d.log("gpu")


@pytest.mark.parametrize("storage", ["local", "s3"])
def test_killed_worker_is_resumed_from_its_checkpoint(deployment: Deployment, storage: str, request) -> None:
    from service.storage import LocalStorage

    d = deployment
    if storage == "s3":
        from service.storage.s3 import S3Storage

        endpoint = request.getfixturevalue("s3")
        bucket = new_bucket(endpoint)
        del d.env["CMC_STORAGE_DIR"]
        d.env.update(CMC_STORAGE=f"s3://{bucket}/it", CMC_S3_ENDPOINT_URL=endpoint, **S3_CREDENTIALS)
        d.own_data_dirs = True  # the processes share the bucket, no folder
        store = S3Storage(bucket, "it", d.tmp / "test-work", endpoint)
    else:
        store = LocalStorage(d.env["CMC_STORAGE_DIR"])

    def stored(sid: str) -> bool:
        return store.exists(f"{sid}/checkpoint.pt")

    d.start_all()
    parts, _, _ = synthetic_upload(steps=40)
    sid = httpx2.post(f"{d.url}/v1/scenes", files=parts, headers=d.headers, timeout=30).json()["id"]
    d.wait(sid, lambda b: b["status"] == "training" and b["progress"] >= 0.3 and stored(sid), timeout=300)
    d.kill("gpu")
    killed_at = d.status(sid)["progress"]
    time.sleep(1)
    assert d.status(sid)["status"] == "training"  # nothing marks it failed: the record survives
    d.start_worker("gpu2", "CMC_GPU_QUEUE")
    body = d.wait(sid, lambda b: b["status"] in ("ready", "failed"), timeout=400)
    assert body["status"] == "ready", body
    import psycopg

    with psycopg.connect(d.env["CMC_DATABASE_URL"].replace("+psycopg", "")) as conn:
        stats, attempts = conn.execute("select stats, attempts from scenes where id = %s", (sid,)).fetchone()
    stats = stats if isinstance(stats, dict) else json.loads(stats)
    assert attempts == 1
    resumed = stats["train"]["resumed_from_step"]
    assert resumed >= 5 and resumed <= killed_at * 40 + 1e-6, (resumed, killed_at)
    assert "re-queued" in d.log("gpu2") or "re-queued" in d.log("cpu")
    if storage == "s3":  # everything went through the bucket: no process kept artifacts of its own
        assert store.exists(f"{sid}/baked/mpi.json")
        deadline = time.time() + 30  # the worker drops the checkpoint just after making the scene ready
        while stored(sid) and time.time() < deadline:
            time.sleep(0.5)
        assert not stored(sid)
        for name in ("api", "cpu", "gpu2"):
            assert not (d.tmp / name / "storage").exists()
            assert [p for p in (d.tmp / name / "work").rglob("*") if p.is_file()] == [], name


def test_docker_stop_of_the_gpu_worker_checkpoints_and_hands_the_job_on(deployment: Deployment) -> None:
    """``docker stop`` sends SIGTERM to the worker's main process only (Celery's warm shutdown,
    which waits for the running task). The worker forwards it to the job: within 10 s it has
    written a checkpoint and exited, the job waits for a worker with its message sent again, and
    the next worker resumes from that step. No step or time period writes a checkpoint here."""
    import psycopg
    import torch

    d = deployment
    d.env.update(CMC_CHECKPOINT_EVERY="100000", CMC_CHECKPOINT_SECONDS="3600")
    d.start_all()
    parts, _, _ = synthetic_upload(steps=3000)
    sid = httpx2.post(f"{d.url}/v1/scenes", files=parts, headers=d.headers, timeout=30).json()["id"]
    ckpt = Path(d.env["CMC_STORAGE_DIR"]) / sid / "checkpoint.pt"
    d.wait(sid, lambda b: b["status"] == "training" and b["progress"] > 0.005, timeout=300)
    assert not ckpt.exists()
    gpu = d.procs.pop("gpu")
    t0 = time.time()
    os.kill(gpu.pid, signal.SIGTERM)  # the main process, as docker stop does (not its group)
    try:
        gpu.wait(30)
    except subprocess.TimeoutExpired:
        d.procs["gpu"] = gpu  # killed by the fixture
        raise AssertionError(f"the worker did not stop within 30 s:\n{d.log('gpu')}") from None
    stopped_s = time.time() - t0
    assert stopped_s <= 10, f"{stopped_s:.1f} s to stop"
    step = torch.load(ckpt, weights_only=False)["step"]
    assert 0 < step < 3000
    body = d.status(sid)
    assert (body["status"], body["detail"]) == ("training", "waiting for a worker")
    d.start_worker("gpu2", "CMC_GPU_QUEUE")  # the deploy's new container
    with psycopg.connect(d.env["CMC_DATABASE_URL"].replace("+psycopg", "")) as conn:
        t0 = time.time()
        while time.time() - t0 < 120:  # the first attempt's stats say resumed_from_step 0
            (stats,) = conn.execute("select stats from scenes where id = %s", (sid,)).fetchone()
            stats = stats if isinstance(stats, dict) else json.loads(stats)
            if stats.get("train", {}).get("resumed_from_step") == step:
                break
            time.sleep(0.3)
        else:
            raise AssertionError(f"not resumed from step {step}: {stats}\n{d.log('gpu2')}")
        (attempts,) = conn.execute("select attempts from scenes where id = %s", (sid,)).fetchone()
    assert attempts == 0  # a clean stop is not a lost worker


def test_api_stopped_mid_upload_leaves_nothing(deployment: Deployment) -> None:
    """The upload's body stops half-way and the API is stopped: uvicorn cancels the request after
    its graceful-shutdown timeout (compose's command), which removes the staged photos; before
    that timeout existed, Docker's SIGKILL left them in the API's working folder."""
    deployment.start_api()
    parts, _, _ = synthetic_upload(width=160, height=120)
    request = httpx2.Request("POST", f"{deployment.url}/v1/scenes", files=parts, headers=deployment.headers)
    body = request.read()
    head = "".join(f"{k}: {v}\r\n" for k, v in request.headers.items() if k.lower() != "host")
    sock = socket.create_connection(("127.0.0.1", deployment.port), timeout=60)
    sock.sendall(f"POST /v1/scenes HTTP/1.1\r\nHost: 127.0.0.1\r\n{head}\r\n".encode() + body[: len(body) // 2])
    work = deployment.tmp / "storage" / ".work"
    t0 = time.time()
    while not (work.is_dir() and any(work.rglob("*.upload"))):  # the API is staging the photos
        assert time.time() - t0 < 30, deployment.log("api")
        time.sleep(0.1)
    api = deployment.procs["api"]
    t_stop = time.time()
    os.killpg(api.pid, signal.SIGTERM)
    try:
        api.wait(40)
    except subprocess.TimeoutExpired:
        pass  # asserted below; the fixture kills it
    stopped_s = time.time() - t_stop
    try:
        answer = sock.recv(4096)
    except OSError:
        answer = b""
    sock.close()
    assert b" 202 " not in answer.split(b"\r\n", 1)[0], answer[:200]
    assert stopped_s < 25, f"the API took {stopped_s:.0f} s to stop: Docker would have killed it"
    assert not [p for p in work.rglob("*")], f"left in the working folder: {list(work.rglob('*'))}"
    scenes = [p for p in (deployment.tmp / "storage").iterdir() if p.name != ".work"]
    assert not scenes, f"left in storage: {scenes}"
    deployment.procs.pop("api")
    deployment.start_api()
    listed = httpx2.get(f"{deployment.url}/v1/scenes", headers=deployment.headers, timeout=10).json()["items"]
    assert listed == [], listed
