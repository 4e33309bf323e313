"""The deployment, run for real: builds the images, starts docker-compose.yml, drives it as a phone
app would, then breaks it the ways production does. One line per check; exits 1 on any failure.

    python bench/deployment_test.py [--offline-docker ../shared/tools/offline-docker] [--keep]

(``make deployment-test``). Works on a scratch copy of the working tree (tracked and untracked,
not ignored files) with a throw-away ``.env`` (random secrets, free ports), as the compose project
``cmc-deploytest``, removed with its volumes at the end unless ``--keep``. Without an NVIDIA GPU
(no ``nvidia-smi``) the training worker runs on the CPU through docker-compose.cpu.yml.
``--offline-docker`` is for a host without an image registry (these machines): its stand-ins for
Redis, PostgreSQL and MinIO, its local CPU torch index for the build, its compose v1 wrapper.
Test-only settings (``docker-compose.deploytest.yml``, written into the copy): webhooks may go to
a receiver on this host's Docker network. The report (the commit and machine, times per stage,
image sizes, build time, every check) goes to ``--out`` (default
bench/reports/current/deployment_test.json).

Checks, in order: every healthcheck; one job through the API (three fern JPEGs, a short training):
status stages, cameras, camera path, render, depth, viewer, MPI atlas and glb through presigned
URLs at S3_PUBLIC_URL, a signed webhook, delete (record and bucket objects gone); the training
worker stopped mid-training and started again (the job resumes from its checkpoint's step); Redis
and then PostgreSQL restarted with a job queued (nothing lost); the API restarted mid-upload (a
clean error, no record, no object, no working folder left); three scenes at once on three pose
workers.
"""

from __future__ import annotations

import argparse
import hashlib
import hmac
import json
import os
import secrets
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import boto3
import httpx2
from servers import free_port  # bench/servers.py: this script runs as python bench/deployment_test.py

from cmc.eval.bench import git_commit, machine_info

ROOT = Path(__file__).resolve().parents[1]
PROJECT = "cmc-deploytest"
PHOTOS = ("IMG_4027.JPG", "IMG_4036.JPG", "IMG_4045.JPG")
# short jobs: the working images' long side and the steps (a training long enough to stop midway)
SHORT = {"steps": 30, "resolution": 192}
LONG = {"steps": 150, "resolution": 192}
TEST_OVERRIDE = """\
# Test-only settings of bench/deployment_test.py: webhooks to a receiver on the Docker network.
services:
  api:
    environment:
      CMC_WEBHOOK_ALLOW_PRIVATE: "true"
  worker-webhooks:
    environment:
      CMC_WEBHOOK_ALLOW_PRIVATE: "true"
"""


def log(msg: str) -> None:
    print(msg, flush=True)


def run(cmd: list[str], timeout: float = 1800, check: bool = True, **kw: Any) -> subprocess.CompletedProcess[str]:
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, **kw)
    if check and r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd[:6])}... exited {r.returncode}:\n{(r.stdout + r.stderr)[-3000:]}")
    return r


class Report:
    """The checks (name, ok, seconds, detail) and the measurements, printed as they come."""

    def __init__(self) -> None:
        self.checks: list[dict[str, Any]] = []
        self.measured: dict[str, Any] = {}

    @contextmanager
    def check(self, name: str) -> Iterator[dict[str, Any]]:
        """A check: PASS unless the block raises; the block may put a ``detail`` in the dict."""
        info: dict[str, Any] = {}
        t0 = time.perf_counter()
        try:
            yield info
            ok, detail = True, info.get("detail", "")
        except Exception as e:  # a failed check is reported, the run goes on
            ok, detail = False, f"{type(e).__name__}: {e}"
        seconds = round(time.perf_counter() - t0, 1)
        self.checks.append({"check": name, "ok": ok, "seconds": seconds, "detail": detail})
        log(f"{'PASS' if ok else 'FAIL'} {name} ({seconds} s){': ' + str(detail) if detail else ''}")

    @property
    def failed(self) -> int:
        return sum(not c["ok"] for c in self.checks)


class Stack:
    """The compose project in the scratch copy, and its API and bucket as a client sees them."""

    def __init__(self, copy: Path, compose: list[str], files: list[str], env: dict[str, str]) -> None:
        self.copy, self.env = copy, env
        self.compose_cmd = [*compose, "-p", PROJECT, *[a for f in files for a in ("-f", f)]]
        self.api_url = f"http://127.0.0.1:{env['API_PORT']}"
        self.s3_url = env["S3_PUBLIC_URL"]
        self.key = env["CMC_API_KEYS"].split(",")[0]
        self.http = httpx2.Client(base_url=self.api_url, headers={"Authorization": f"Bearer {self.key}"}, timeout=60)
        self.s3 = boto3.client(
            "s3",
            endpoint_url=self.s3_url,
            aws_access_key_id="cmc",
            aws_secret_access_key=env["MINIO_ROOT_PASSWORD"],
            region_name="us-east-1",
        )

    def compose(self, *args: str, timeout: float = 900) -> str:
        return run([*self.compose_cmd, *args], timeout=timeout, cwd=self.copy).stdout

    def containers(self) -> list[dict[str, Any]]:
        ids = run(["docker", "ps", "-aq", "--filter", f"label=com.docker.compose.project={PROJECT}"]).stdout.split()
        return json.loads(run(["docker", "inspect", *ids]).stdout) if ids else []

    def container(self, service: str) -> str:
        """The name of the (first) running container of ``service``."""
        for c in self.containers():
            if c["Config"]["Labels"].get("com.docker.compose.service") == service and c["State"]["Running"]:
                return c["Name"].lstrip("/")
        raise RuntimeError(f"no running container of {service}")

    def wait_healthy(self, timeout: float = 420) -> dict[str, str]:
        """Every long-running container healthy and the one-shots exited 0; their states."""
        t0 = time.time()
        while True:
            states = {}
            for c in self.containers():
                name, st = c["Name"].lstrip("/"), c["State"]
                if c["Config"]["Labels"].get("com.docker.compose.oneoff") == "True":
                    continue
                if st["Status"] == "exited":
                    states[name] = "exited 0" if st["ExitCode"] == 0 else f"exited {st['ExitCode']}"
                else:
                    states[name] = st.get("Health", {}).get("Status", st["Status"])
            one_shots_ok = all(s == "exited 0" for n, s in states.items() if "migrate" in n or "minio-init" in n)
            others = [s for n, s in states.items() if "migrate" not in n and "minio-init" not in n]
            if states and one_shots_ok and all(s in ("healthy", "running") for s in others):
                return states
            bad = {n: s for n, s in states.items() if s.startswith("exited") and s != "exited 0"}
            if bad or time.time() - t0 > timeout:
                raise RuntimeError(f"not healthy after {time.time() - t0:.0f} s: {states}")
            time.sleep(3)

    def bucket_keys(self, prefix: str = "") -> set[str]:
        keys: set[str] = set()
        for page in self.s3.get_paginator("list_objects_v2").paginate(Bucket="cmc-artifacts", Prefix=prefix):
            keys.update(o["Key"] for o in page.get("Contents", []))
        return keys

    def bucket_bytes(self, prefix: str) -> int:
        pages = self.s3.get_paginator("list_objects_v2").paginate(Bucket="cmc-artifacts", Prefix=prefix)
        return sum(o["Size"] for page in pages for o in page.get("Contents", []))

    def peak_memory_bytes(self) -> dict[str, int]:
        """Peak memory of each running container since it started (its cgroup's, v1 or v2)."""
        peaks = {}
        for c in self.containers():
            cid = c["Id"]
            for path in (
                f"/sys/fs/cgroup/memory/docker/{cid}/memory.max_usage_in_bytes",
                f"/sys/fs/cgroup/system.slice/docker-{cid}.scope/memory.peak",
            ):
                if Path(path).exists():
                    name = c["Config"]["Labels"].get("com.docker.compose.service", cid)
                    peaks[name] = max(peaks.get(name, 0), int(Path(path).read_text()))
        return peaks

    def upload(self, options: dict[str, Any], callback_url: str | None = None) -> str:
        photos = ROOT.parent / "shared" / "datasets" / "llff" / "fern" / "images"
        files = [("images", (p, (photos / p).read_bytes(), "image/jpeg")) for p in PHOTOS]
        data = {"options": json.dumps(options), **({"callback_url": callback_url} if callback_url else {})}
        r = self.http.post("/v1/scenes", files=files, data=data, headers={"Idempotency-Key": secrets.token_hex(8)})
        if r.status_code != 202:
            raise RuntimeError(f"upload: {r.status_code} {r.text[:500]}")
        return r.json()["id"]

    def poll(
        self,
        sid: str,
        until: tuple[str, ...] = ("ready", "failed"),
        timeout: float = 900,
        every: float = 1.0,
        stop: Callable[[dict[str, Any]], bool] | None = None,
    ) -> tuple[dict[str, Any], list[tuple[float, str, str | None]]]:
        """Poll the scene until its status is in ``until`` (or ``stop(body)``); the last body and
        the transitions (seconds since the first poll, status, detail)."""
        t0, seen = time.time(), []
        while True:
            body = self.http.get(f"/v1/scenes/{sid}").json()
            key = (body["status"], body.get("detail"))
            if not seen or seen[-1][1:] != key:
                seen.append((round(time.time() - t0, 1), *key))
            if body["status"] in until or (stop and stop(body)):
                return body, seen
            if time.time() - t0 > timeout:
                raise RuntimeError(f"scene {sid} still {body['status']} after {timeout} s: {body}")
            time.sleep(every)


def ready(body: dict[str, Any]) -> None:
    if body["status"] != "ready":
        raise RuntimeError(f"{body['status']}: {body.get('error')}")


def stage_seconds(seen: list[tuple[float, str, str | None]], end: float) -> dict[str, float]:
    """Seconds spent in each status, from the transitions ``poll`` saw."""
    out: dict[str, float] = {}
    for (t, status, _), nxt in zip(seen, [*seen[1:], (end, "", None)], strict=True):
        out[status] = round(out.get(status, 0.0) + nxt[0] - t, 1)
    return out


class WebhookReceiver:
    """An HTTP server on this host's side of the Docker network that keeps every request."""

    def __init__(self, host: str) -> None:
        received = self.received = []

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:  # noqa: N802 (http.server's name)
                body = self.rfile.read(int(self.headers["Content-Length"]))
                received.append((dict(self.headers), body))
                self.send_response(204)
                self.end_headers()

            def log_message(self, *args: Any) -> None:
                pass

        self.server = ThreadingHTTPServer((host, 0), Handler)
        self.url = f"http://{host}:{self.server.server_address[1]}/hooks/cmc"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()


def scratch_copy() -> Path:
    """The working tree's files (tracked, and untracked but not ignored) in a new folder."""
    copy = Path(tempfile.mkdtemp(prefix="cmc-deploytest-"))
    names = run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=ROOT).stdout
    for name in filter(None, names.split("\0")):
        src = ROOT / name
        if src.is_file():
            (copy / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, copy / name)
    return copy


def throwaway_env() -> dict[str, str]:
    """.env.example with random secrets, free ports and webhooks on."""
    env = {}
    for line in (ROOT / ".env.example").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            k, _, v = line.partition("=")
            env[k] = v
    s3_port = free_port()
    env.update(
        CMC_API_KEYS=secrets.token_hex(16),
        POSTGRES_PASSWORD=secrets.token_hex(12),
        MINIO_ROOT_PASSWORD=secrets.token_hex(12),
        CMC_WEBHOOK_SECRET=secrets.token_hex(16),
        API_PORT=str(free_port()),
        S3_PORT=str(s3_port),
        S3_PUBLIC_URL=f"http://127.0.0.1:{s3_port}",
    )
    return env


def build_images(report: Report, copy: Path, stack: Stack, offline: Path | None, gpu: bool, fresh: bool) -> None:
    with report.check("build images") as c:
        t0 = time.perf_counter()
        if offline:
            index = run([str(offline / "torch-index.sh")]).stdout.split()[-1]
            build = ["docker", "build", "--network", "host", "--build-arg", f"TORCH_INDEX_URL={index}"]
            build += ["--no-cache"] if fresh else []
            run([*build, "-f", "docker/Dockerfile", "-t", "cmc-service:cpu", "."], cwd=copy,
                env={**os.environ, "DOCKER_BUILDKIT": "0"})  # fmt: skip
        else:
            stack.compose("build", *(["--no-cache"] if fresh else []))
        report.measured["build_seconds"] = round(time.perf_counter() - t0, 1)
        report.measured["build_from_scratch"] = fresh
        sizes = {}
        for tag in ["cmc-service:cpu"] + (["cmc-service:gpu"] if gpu else []):
            sizes[tag] = int(run(["docker", "image", "inspect", "-f", "{{.Size}}", tag]).stdout)
        report.measured["image_bytes"] = sizes
        c["detail"] = ", ".join(f"{t} {b / 1e9:.2f} GB" for t, b in sizes.items())
        if sizes["cmc-service:cpu"] > 2e9:
            raise RuntimeError(f"the CPU image is over 2 GB: {c['detail']}")


def main_job(report: Report, stack: Stack, hooks: WebhookReceiver) -> None:
    """One scene through every endpoint a phone app uses, then deleted."""
    sid = None
    with report.check("upload three fern JPEGs, poll to ready") as c:
        t0 = time.time()
        sid = stack.upload(SHORT, callback_url=hooks.url)
        body, seen = stack.poll(sid)
        ready(body)
        stages = stage_seconds(seen, time.time() - t0)
        report.measured["job_stages_seconds"] = stages
        report.measured["job_seconds"] = round(time.time() - t0, 1)
        missing = {"estimating_poses", "training"} - set(stages)
        if missing:
            raise RuntimeError(f"the status never showed {missing}: {seen}")
        c["detail"] = f"{report.measured['job_seconds']} s; " + ", ".join(f"{k} {v} s" for k, v in stages.items())
    if sid is None:
        return
    base = f"/v1/scenes/{sid}"
    with report.check("cameras, camera path, render (PNG), depth (npy), viewer page") as c:
        cams = stack.http.get(f"{base}/cameras").raise_for_status().json()
        path = stack.http.get(f"{base}/camera-path", params={"path": "orbit", "frames": 4}).raise_for_status().json()
        cam = path["frames"][1]
        t0 = time.perf_counter()
        png = stack.http.post(f"{base}/render", json=cam, headers={"Accept": "image/png"}).raise_for_status()
        render_ms = (time.perf_counter() - t0) * 1e3
        assert png.content[:8] == b"\x89PNG\r\n\x1a\n", png.headers
        warm_ms = []
        for frame in path["frames"]:
            t0 = time.perf_counter()
            stack.http.post(f"{base}/render", json=frame, headers={"Accept": "image/png"}).raise_for_status()
            warm_ms.append((time.perf_counter() - t0) * 1e3)
        report.measured["render_ms"] = {
            "first": round(render_ms),
            "loaded_median": round(sorted(warm_ms)[len(warm_ms) // 2]),
        }
        depth = stack.http.post(f"{base}/depth", json=cam, headers={"Accept": "application/x-npy"}).raise_for_status()
        assert depth.content[:6] == b"\x93NUMPY", depth.headers
        page = stack.http.get(f"{base}/viewer").raise_for_status()
        assert "<canvas" in page.text
        c["detail"] = (
            f"{len(cams['frames'])} cameras, render {render_ms:.0f} ms (the scene loaded from the bucket), then "
            f"{report.measured['render_ms']['loaded_median']} ms; {len(depth.content)} B depth"
        )
    with report.check("MPI atlas and glb through presigned URLs at S3_PUBLIC_URL") as c:
        manifest = stack.http.get(f"{base}/mpi").raise_for_status().json()
        got = {}
        for url, magic in ((f"{base}/mpi/{manifest['mpis'][0]['atlas']}", b"\x89PNG"), (f"{base}/export.glb", b"glTF")):
            r = stack.http.get(url)
            assert r.status_code == 307, f"{url}: {r.status_code}"
            loc = r.headers["location"]
            assert loc.startswith(stack.s3_url), loc
            data = httpx2.get(loc, timeout=60).raise_for_status().content  # no API key: the URL is signed
            assert data[:4] == magic, data[:8]
            got[url.rsplit("/", 1)[-1]] = len(data)
        c["detail"] = ", ".join(f"{k} {v} B" for k, v in got.items())
    with report.check("signed webhook scene.ready received on the host") as c:
        secret = stack.http.get("/v1/webhooks/secret").raise_for_status().json()["secret"]
        t0 = time.time()
        while not any(json.loads(b).get("scene_id") == sid for _, b in hooks.received):
            assert time.time() - t0 < 60, "no webhook within 60 s"
            time.sleep(0.5)
        headers, body = next((h, b) for h, b in hooks.received if json.loads(b).get("scene_id") == sid)
        ts = headers["CMC-Webhook-Timestamp"]
        mac = hmac.new(secret.encode(), ts.encode() + b"." + body, hashlib.sha256).hexdigest()
        assert hmac.compare_digest(headers["CMC-Webhook-Signature"], f"v1={mac}"), "bad signature"
        c["detail"] = json.loads(body)["type"]
    with report.check("delete: 204, then 404, no object left in the bucket") as c:
        before = len(stack.bucket_keys(f"scenes/{sid}/"))
        report.measured["bucket_bytes_per_scene"] = stack.bucket_bytes(f"scenes/{sid}/")
        assert stack.http.delete(base).status_code == 204
        assert stack.http.get(base).status_code == 404
        t0 = time.time()
        while left := stack.bucket_keys(f"scenes/{sid}/"):
            assert time.time() - t0 < 30, f"left in the bucket: {sorted(left)[:5]}"
            time.sleep(1)
        c["detail"] = f"{before} objects removed"


def fault_training_worker_stopped(report: Report, stack: Stack) -> None:
    with report.check("training worker stopped mid-training resumes from its checkpoint") as c:
        sid = stack.upload(LONG)
        body, _ = stack.poll(sid, stop=lambda b: b["status"] == "training" and b["progress"] >= 0.15, every=0.5)
        if body["status"] != "training":
            raise RuntimeError(f"the job was {body['status']} before it could be stopped mid-training")
        stopped_at = body["progress"]
        stack.compose("stop", "worker-gpu")
        body = stack.http.get(f"/v1/scenes/{sid}").json()
        assert body["status"] != "failed", body
        stack.compose("start", "worker-gpu")
        body, seen = stack.poll(sid)
        ready(body)
        resumed = [d for _, s, d in seen if s == "training" and d and "resumed from the checkpoint of step" in d]
        assert resumed, f"the status never showed a resumed step: {seen}"
        step = int(resumed[0].rsplit(" ", 1)[-1])
        assert step >= stopped_at * LONG["steps"] - 1, (step, stopped_at)
        c["detail"] = f"stopped at progress {stopped_at:.2f}, {resumed[0]!r}"
        stack.http.delete(f"/v1/scenes/{sid}")


def fault_broker_and_database_restarted(report: Report, stack: Stack) -> None:
    with report.check("Redis and PostgreSQL restarted with a job queued: nothing lost") as c:
        stack.compose("stop", "worker-cpu")
        sid = stack.upload(SHORT)
        stack.compose("restart", "redis")
        stack.compose("restart", "db")
        stack.compose("start", "worker-cpu")
        body, seen = stack.poll(sid)
        ready(body)
        c["detail"] = " -> ".join(s for _, s, _ in seen)
        stack.http.delete(f"/v1/scenes/{sid}")
    with report.check("healthy again after the restarts"):
        stack.wait_healthy()


def fault_api_restarted_mid_upload(report: Report, stack: Stack) -> None:
    with report.check("API restarted mid-upload: a clean error, nothing left") as c:
        scenes_before = {s["id"] for s in stack.http.get("/v1/scenes", params={"limit": 100}).json()["items"]}
        keys_before = stack.bucket_keys()
        photos = ROOT.parent / "shared" / "datasets" / "llff" / "fern" / "images"
        boundary = secrets.token_hex(8)
        body = (
            b"".join(
                f'--{boundary}\r\nContent-Disposition: form-data; name="images"; filename="{p}"\r\n'
                f"Content-Type: image/jpeg\r\n\r\n".encode()
                + (photos / p).read_bytes()
                + b"\r\n"
                for p in PHOTOS
            )
            + f"--{boundary}--\r\n".encode()
        )
        sock = socket.create_connection(("127.0.0.1", int(stack.env["API_PORT"])), timeout=120)
        head = (
            f"POST /v1/scenes HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer {stack.key}\r\n"
            f"Content-Type: multipart/form-data; boundary={boundary}\r\nContent-Length: {len(body)}\r\n\r\n"
        )
        sock.sendall(head.encode() + body[: len(body) // 2])
        time.sleep(1)
        stack.compose("restart", "api")
        try:
            sock.sendall(body[len(body) // 2 :])
            answer = sock.recv(4096).decode(errors="replace").split("\r\n", 1)[0]
        except OSError as e:
            answer = f"connection error ({type(e).__name__})"
        finally:
            sock.close()
        assert " 202 " not in answer, answer
        stack.wait_healthy()
        scenes_after = {s["id"] for s in stack.http.get("/v1/scenes", params={"limit": 100}).json()["items"]}
        assert scenes_after <= scenes_before, f"a scene was made: {scenes_after - scenes_before}"
        new_keys = stack.bucket_keys() - keys_before
        assert not new_keys, f"left in the bucket: {sorted(new_keys)[:5]}"
        work = run(["docker", "exec", stack.container("api"), "find", "/data", "-mindepth", "2"]).stdout.split()
        assert not work, f"left in the API's /data: {work[:5]}"
        c["detail"] = f"client saw: {answer!r}"


def fault_three_scenes_three_pose_workers(report: Report, stack: Stack) -> None:
    with report.check("--scale worker-cpu=3: three scenes at once, all ready") as c:
        stack.compose("up", "-d", "--no-recreate", "--scale", "worker-cpu=3")
        stack.wait_healthy()
        t0 = time.time()
        sids = [stack.upload(SHORT) for _ in range(3)]
        results: dict[str, Any] = {}

        def follow(sid: str) -> None:
            results[sid] = stack.poll(sid, timeout=1500)

        threads = [threading.Thread(target=follow, args=(s,)) for s in sids]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        for sid in sids:
            ready(results[sid][0])
        posed = run(["docker", "ps", "-q", "--filter", f"label=com.docker.compose.project={PROJECT}",
                     "--filter", "label=com.docker.compose.service=worker-cpu"]).stdout.split()  # fmt: skip
        workers = set()
        for cid in posed:
            out = run(["docker", "logs", cid])
            if any(f"job {sid} phase poses" in out.stdout + out.stderr for sid in sids):
                workers.add(cid)
        report.measured["three_scenes_seconds"] = round(time.time() - t0, 1)
        c["detail"] = f"{report.measured['three_scenes_seconds']} s, poses on {len(workers)} of {len(posed)} workers"
        for sid in sids:
            stack.http.delete(f"/v1/scenes/{sid}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--offline-docker", type=Path, help="../shared/tools/offline-docker on a host without a registry")
    ap.add_argument("--keep", action="store_true", help="leave the stack running (and the scratch copy)")
    ap.add_argument("--no-cache", action="store_true", help="build the images without Docker's layer cache")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "reports" / "current" / "deployment_test.json")
    args = ap.parse_args()
    offline = args.offline_docker.resolve() if args.offline_docker else None
    gpu = shutil.which("nvidia-smi") is not None
    if offline:
        compose = [str(offline / "compose-v1.sh")]
    elif run(["docker", "compose", "version"], check=False).returncode == 0:
        compose = ["docker", "compose"]
    else:
        sys.exit("needs the Docker Compose v2 plugin (or --offline-docker)")
    report = Report()
    copy = scratch_copy()
    env = throwaway_env()
    (copy / ".env").write_text("".join(f"{k}={v}\n" for k, v in env.items()))
    (copy / "docker-compose.deploytest.yml").write_text(TEST_OVERRIDE)
    files = ["docker-compose.yml"] + ([] if gpu else ["docker-compose.cpu.yml"]) + ["docker-compose.deploytest.yml"]
    stack = Stack(copy, compose, files, env)
    log(f"scratch copy {copy}; compose {' '.join(stack.compose_cmd)}; API {stack.api_url}; GPU: {gpu}")
    t_start = time.perf_counter()
    try:
        if offline:
            run([str(offline / "build-standins.sh"), str(copy / "docker-compose.yml")], timeout=1800)
        build_images(report, copy, stack, offline, gpu, args.no_cache)
        with report.check("compose up: every healthcheck green, migrate and minio-init exited 0") as c:
            t0 = time.perf_counter()
            stack.compose("up", "-d", *([] if offline else ["--build"]))
            states = stack.wait_healthy()
            report.measured["up_seconds"] = round(time.perf_counter() - t0, 1)
            c["detail"] = f"{len(states)} containers in {report.measured['up_seconds']} s"
        if report.failed == 0:
            network = json.loads(run(["docker", "network", "inspect", f"{PROJECT}_default"]).stdout)[0]
            hooks = WebhookReceiver(network["IPAM"]["Config"][0]["Gateway"])
            main_job(report, stack, hooks)
            fault_training_worker_stopped(report, stack)
            fault_broker_and_database_restarted(report, stack)
            fault_api_restarted_mid_upload(report, stack)
            fault_three_scenes_three_pose_workers(report, stack)
    finally:
        report.measured["total_seconds"] = round(time.perf_counter() - t_start, 1)
        report.measured["peak_memory_bytes"] = stack.peak_memory_bytes()
        if report.failed:
            for c in stack.containers():
                name = c["Name"].lstrip("/")
                tail = run(["docker", "logs", "--tail", "30", name], check=False)
                log(f"--- {name} ({c['State']['Status']})\n{(tail.stdout + tail.stderr)[-2500:]}")
        if not args.keep:
            stack.compose("down", "-v", "--remove-orphans", timeout=300)
            shutil.rmtree(copy, ignore_errors=True)
    passed = len(report.checks) - report.failed
    args.out.write_text(
        json.dumps(
            {
                "command": " ".join(["python", "bench/deployment_test.py", *sys.argv[1:]]),
                "date": datetime.now(UTC).strftime("%Y-%m-%d"),
                "host": f"{os.cpu_count()} cores, {'NVIDIA GPU' if gpu else 'no GPU: training on the CPU'}",
                "machine": machine_info(),
                "git_commit": git_commit(),
                "compose": " ".join(compose),
                "settings": {"short_job": SHORT, "long_job": LONG},
                "measured": report.measured,
                "checks": report.checks,
            },
            indent=2,
        )
        + "\n"
    )
    log(f"{passed} passed, {report.failed} failed")
    return 1 if report.failed else 0


if __name__ == "__main__":
    sys.exit(main())
