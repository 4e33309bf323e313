"""Service benchmark (issue 4 targets): upload answer time, render latency, concurrent renders.

Runs the deployed shape on this machine: uvicorn (API, Celery mode, SQLite store) and one Celery
worker for both queues, over the real Redis at 127.0.0.1:6379, each its own process.

1. Upload: the three full-resolution fern JPEGs (``images/``, 2.9-3.2 MB each, 4032x3024) as one
   ``POST /v1/scenes``, timed from sending the request to the 202 answer, ``--uploads`` times
   (median). No worker runs yet, so nothing else loads the CPU; each scene is deleted after.
2. A fern scene at 504x378 (``images_8`` views 1, 10, 19 with the dataset's poses as the cameras
   part, so no SfM) is trained for ``--steps`` steps and baked. Render cost does not depend on
   the number of steps: every pixel composites every plane of every MPI.
3. Render latency: ``POST /v1/scenes/{id}/render`` at 504x378 for the held-out views 0, 8, 16
   (PNG), after one warm-up request (baked cache warm), ``--renders`` sequential requests; the
   client's wall time per request (HTTP over loopback, rendering, PNG encoding). p50 and p90.
4. Concurrency: ``--concurrent`` requests sent at once from as many threads; every answer must
   be 200 with a PNG of the right size.

Usage (from the repository root; writes bench/service_cpu.json)::

    python bench/service_bench.py --data ../shared/datasets/llff/fern --out bench/service_cpu.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from datetime import date
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cmc.cameras import CameraFile, camera_file_to_dict  # noqa: E402
from cmc.datasets import load_llff  # noqa: E402


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def percentile(xs: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(xs), q))


def camera_body(split, i: int) -> dict:
    """The render request body for test view ``i``: its cameras-file frame, size and convention."""
    data = camera_file_to_dict(CameraFile(split.cameras[i : i + 1], ["render"]), "opengl")
    frame = {k: v for k, v in data["frames"][0].items() if k != "file_path"}
    return {**frame, "w": data["w"], "h": data["h"], "convention": "opengl"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default="../shared/datasets/llff/fern")
    ap.add_argument("--out", default="bench/service_cpu.json")
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--uploads", type=int, default=7)
    ap.add_argument("--renders", type=int, default=30)
    ap.add_argument("--concurrent", type=int, default=20)
    ap.add_argument("--redis", default="redis://127.0.0.1:6379/13", help="a Redis database of its own (emptied after)")
    args = ap.parse_args()
    fern = Path(args.data).resolve()
    tmp = Path(tempfile.mkdtemp(prefix="cmc-service-bench-"))
    run = uuid.uuid4().hex[:8]
    port = free_port()
    env = {
        **os.environ,
        "PYTHONPATH": str(ROOT),
        "CMC_MODE": "celery",
        "CMC_BROKER_URL": args.redis,
        "CMC_DATA_DIR": str(tmp),
        "CMC_CPU_QUEUE": f"bench-cpu-{run}",
        "CMC_GPU_QUEUE": f"bench-gpu-{run}",
        "CMC_API_KEYS": "bench-key",
    }
    headers = {"Authorization": "Bearer bench-key"}
    url = f"http://127.0.0.1:{port}"
    procs = []

    def start(name: str, cmd: list[str]) -> None:
        log = open(tmp / f"{name}.log", "wb")  # noqa: SIM115
        p = subprocess.Popen(cmd, env=env, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        procs.append(p)

    report: dict = {
        "date": date.today().isoformat(),
        "command": "python bench/service_bench.py " + " ".join(sys.argv[1:]),
        "machine": {
            "cpu": platform.processor() or platform.machine(),
            "cores": os.cpu_count(),
            "python": platform.python_version(),
        },
        "git_commit": subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True
        ).stdout.strip(),
        "settings": vars(args),
    }
    try:
        uvicorn = ["-m", "uvicorn", "service.app:create_app", "--factory", "--log-level", "warning"]
        start("api", [sys.executable, *uvicorn, "--port", str(port)])
        for _ in range(200):
            try:
                if httpx.get(f"{url}/readyz", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                time.sleep(0.2)
        client = httpx.Client(base_url=url, headers=headers, timeout=120)

        # 1. uploads of the phone JPEGs
        jpegs = sorted((fern / "images").glob("*.JPG"))
        blobs = [(p.name, p.read_bytes()) for p in jpegs]
        upload_s = []
        for k in range(args.uploads):
            files = [("images", (name, data, "image/jpeg")) for name, data in blobs]
            t0 = time.perf_counter()
            r = client.post("/v1/scenes", files=files, headers={"Idempotency-Key": f"{run}-{k}"})
            upload_s.append(time.perf_counter() - t0)
            assert r.status_code == 202, r.text
            client.delete(f"/v1/scenes/{r.json()['id']}")
        report["upload"] = {
            "files": [{"name": n, "bytes": len(b)} for n, b in blobs],
            "seconds": upload_s,
            "median_s": statistics.median(upload_s),
            "max_s": max(upload_s),
            "target_s": 2.0,
        }
        print(f"upload of {len(blobs)} JPEGs: median {report['upload']['median_s']:.3f} s", flush=True)

        # 2. a fern scene at 504x378 with the dataset's poses
        queues = f"{env['CMC_CPU_QUEUE']},{env['CMC_GPU_QUEUE']}"
        celery = ["-m", "celery", "-A", "worker.celery_app", "worker", "-c", "1", "--loglevel", "WARNING"]
        start("worker", [sys.executable, *celery, "-Q", queues, "--without-gossip", "--without-mingle"])
        split = load_llff(fern)
        train = split.train
        names = train.names  # the images_8 file names
        files = [("images", (n, (fern / "images_8" / n).read_bytes(), "image/png")) for n in names]
        cams = camera_file_to_dict(CameraFile(train.cameras, names, train.near_far), "opengl")
        files.append(("cameras", ("cameras.json", json.dumps(cams).encode(), "application/json")))
        files.append(("options", (None, json.dumps({"steps": args.steps}))))
        sid = client.post("/v1/scenes", files=files).json()["id"]
        t0 = time.perf_counter()
        while True:
            body = client.get(f"/v1/scenes/{sid}").json()
            if body["status"] in ("ready", "failed"):
                break
            time.sleep(1)
        assert body["status"] == "ready", body
        report["scene"] = {"steps": args.steps, "seconds_to_ready": time.perf_counter() - t0}
        print(f"fern scene ready in {report['scene']['seconds_to_ready']:.0f} s", flush=True)

        # 3. sequential renders, warm cache
        bodies = [camera_body(split.test, i) for i in range(len(split.test))]
        w, h = bodies[0]["w"], bodies[0]["h"]
        assert client.post(f"/v1/scenes/{sid}/render", json=bodies[0]).status_code == 200  # warm-up
        times = []
        for k in range(args.renders):
            t0 = time.perf_counter()
            r = client.post(f"/v1/scenes/{sid}/render", json=bodies[k % len(bodies)])
            times.append(time.perf_counter() - t0)
            assert r.status_code == 200 and r.headers["content-type"] == "image/png"
        report["render"] = {
            "size": [w, h],
            "seconds": times,
            "p50_s": percentile(times, 50),
            "p90_s": percentile(times, 90),
            "target_p50_s": 0.3,
        }
        print(f"render {w}x{h}: p50 {report['render']['p50_s'] * 1000:.0f} ms", flush=True)

        # 4. concurrent renders
        results: list[tuple[int, float, int]] = []
        barrier = threading.Barrier(args.concurrent)

        def one(k: int) -> None:
            with httpx.Client(base_url=url, headers=headers, timeout=300) as c:
                barrier.wait()
                t0 = time.perf_counter()
                try:
                    r = c.post(f"/v1/scenes/{sid}/render", json=bodies[k % len(bodies)])
                    results.append((r.status_code, time.perf_counter() - t0, len(r.content)))
                except httpx.HTTPError:
                    results.append((0, time.perf_counter() - t0, 0))

        threads = [threading.Thread(target=one, args=(k,)) for k in range(args.concurrent)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        ok = sum(1 for status, _, n in results if status == 200 and n > 0)
        report["concurrent"] = {
            "requests": args.concurrent,
            "ok": ok,
            "errors": args.concurrent - ok,
            "slowest_s": max(t for _, t, _ in results),
            "median_s": statistics.median(t for _, t, _ in results),
        }
        print(f"{args.concurrent} concurrent renders: {ok} ok, slowest {report['concurrent']['slowest_s']:.1f} s")
        client.delete(f"/v1/scenes/{sid}")
    finally:
        for p in procs:
            try:
                os.killpg(p.pid, signal.SIGTERM)
                p.wait(15)
            except (ProcessLookupError, subprocess.TimeoutExpired):
                os.killpg(p.pid, signal.SIGKILL)
        import redis

        redis.Redis.from_url(args.redis).flushdb()  # the benchmark's own database (--redis)
    out = Path(args.out)
    out.write_text(json.dumps(report, indent=1) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
