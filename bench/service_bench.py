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

With ``--load`` (issue 10) the bench instead uploads ``--scenes`` such scenes (default 8, trained
one after the other by the worker) and, with ``--baked DIR``, replaces each scene's bake by DIR
before the first render (a full ``fast`` bake, as bench/render_speed.py builds: the renderer's
cost depends on the alphas, and a few training steps leave them unlike a trained scene's). Then:

5. Encoding, in this process, of a render of the first scene: the service's PNG, JPEG (quality
   90), 16-bit depth PNG and float32 ``.npy``, and for comparison Pillow's PNG (compress levels
   0, 1, 6) and JPEG quality 80: median ms and bytes.
6. Load: for 1, 20 and 50 concurrent clients (``--clients``), each sending
   ``--requests-per-client`` render requests one after the other (held-out views in turn), first
   all to one scene, then to the scenes round-robin, after one warm-up render per scene (cache
   warm). A 503 is waited out as its ``Retry-After`` says and sent again (counted as ``retries``);
   a request's latency runs from its first send to its image. p50 / p95 / max, and errors (an
   answer other than a PNG of the right size, or no answer within 120 s).

Usage (from the repository root; writes bench/reports/current/service_cpu.json, or with ``--load``
bench/reports/current/service_load_cpu.json)::

    python bench/service_bench.py --data ../shared/datasets/llff/fern --out bench/reports/current/service_cpu.json
    python bench/service_bench.py --load --baked /tmp/bake --steps 20 --out bench/reports/current/service_load_cpu.json
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from datetime import date
from pathlib import Path

import httpx2
import numpy as np
from servers import flush_redis, free_port, stop_process_groups, wait_ready, write_report

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cmc.data.datasets import load_llff  # noqa: E402
from cmc.eval.bench import git_commit, machine_info  # noqa: E402
from cmc.geometry.cameras import CameraFile, camera_file_to_dict  # noqa: E402


def percentile(xs: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(xs), q))


def camera_body(split, i: int) -> dict:
    """The render request body for test view ``i``: its cameras-file frame, size and convention."""
    data = camera_file_to_dict(CameraFile(split.cameras[i : i + 1], ["render"]), "opengl")
    frame = {k: v for k, v in data["frames"][0].items() if k != "file_path"}
    return {**frame, "w": data["w"], "h": data["h"], "convention": "opengl"}


def deployed_env(tmp: Path, redis_url: str, run: str) -> dict[str, str]:
    """Environment of the deployed shape: Celery mode on ``redis_url``, data in ``tmp``, queues
    of this run only, one API key (``bench-key``). Both protocols measure latency and capacity, so
    the per-key quotas (issue 15, measured by bench/quota_load.py) are off: one key sends everything."""
    return {
        **os.environ,
        "PYTHONPATH": str(ROOT),
        "CMC_MODE": "celery",
        "CMC_BROKER_URL": redis_url,
        "CMC_DATA_DIR": str(tmp),
        "CMC_CPU_QUEUE": f"bench-cpu-{run}",
        "CMC_GPU_QUEUE": f"bench-gpu-{run}",
        "CMC_API_KEYS": "bench-key",
        "CMC_MAX_CONCURRENT_JOBS": "0",
        "CMC_MAX_RENDERS_PER_SECOND": "0",
    }


def render_settings(env: dict[str, str]) -> dict[str, str]:
    """The API's render settings in ``env``: each ``CMC_`` variable, else the setting's default."""
    from service.settings import Settings

    names = ("render_concurrency", "render_threads", "render_queue")
    return {n: env.get(f"CMC_{n.upper()}", str(Settings.model_fields[n].default)) for n in names}


def start_services(tmp: Path, env: dict, procs: list, port: int) -> None:
    """The API and one worker for both queues, each its own process, as in main()."""
    api = ["-m", "uvicorn", "service.app:create_app", "--factory", "--log-level", "warning", "--port", str(port)]
    first = len(procs)
    for name, cmd in (
        ("api", api),
        ("worker", ["-m", "celery", "-A", "worker.celery_app", "worker", "-c", "1", "--loglevel", "WARNING",
                    "-Q", f"{env['CMC_CPU_QUEUE']},{env['CMC_GPU_QUEUE']}", "--without-gossip", "--without-mingle"]),
    ):  # fmt: skip
        log = open(tmp / f"{name}.log", "wb")  # noqa: SIM115
        procs.append(
            subprocess.Popen(
                [sys.executable, *cmd], env=env, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, start_new_session=True
            )
        )
    wait_ready(f"http://127.0.0.1:{port}", "/readyz", 200, procs[first], tmp / "api.log")


def timed(fn, repeats: int = 15) -> tuple[float, object]:
    """Median milliseconds of ``fn()`` and its last result."""
    ms, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        ms.append(1000 * (time.perf_counter() - t0))
    return statistics.median(ms), out


def encodings(baked_dir: Path, split) -> dict:
    """Median time and size of every encoding of one render (the first held-out view)."""
    import io

    from PIL import Image

    from cmc.serving.baking import BakedScene
    from service.renders import encode_depth_npy, encode_depth_png16, encode_image

    baked = BakedScene.load(baked_dir)
    K, pose = split.test.cameras.K[0], split.test.cameras.world_from_cam[0]
    render_ms, out = timed(lambda: baked.render(K, pose, threads=1), 5)
    rgb, depth = out.rgb, out.depth
    rgb8 = Image.fromarray((np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8))

    def pil(fmt: str, **kw):
        buf = io.BytesIO()
        rgb8.save(buf, fmt, **kw)
        return buf.getvalue()

    cases = {
        "png (service: sub filter, zlib 1 run-length)": lambda: encode_image(rgb, "image/png"),
        "jpeg (service: quality 90)": lambda: encode_image(rgb, "image/jpeg"),
        "depth png16 (service)": lambda: encode_depth_png16(depth, baked.far),
        "depth npy (service)": lambda: encode_depth_npy(depth),
        "png Pillow compress_level 0 (8-bit image only)": lambda: pil("PNG", compress_level=0),
        "png Pillow compress_level 1 (8-bit image only)": lambda: pil("PNG", compress_level=1),
        "png Pillow compress_level 6 (8-bit image only)": lambda: pil("PNG", compress_level=6),
        "jpeg quality 80 (8-bit image only)": lambda: pil("JPEG", quality=80),
        "float to 8-bit conversion alone": lambda: (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8).tobytes(),
    }
    result = {"render_ms_one_thread": render_ms, "size": [int(rgb.shape[1]), int(rgb.shape[0])]}
    for name, fn in cases.items():
        ms, data = timed(fn)
        result[name] = {"median_ms": ms, "bytes": len(data)}  # type: ignore[arg-type]
        print(f"encode {name}: {ms:.1f} ms, {len(data)} bytes", flush=True)  # type: ignore[arg-type]
    return result


def load_phase(url: str, headers: dict, targets: list[tuple[str, dict]], clients: int, per_client: int) -> dict:
    """``clients`` threads, each sending ``per_client`` renders in turn; 503s waited out and resent."""
    results: list[dict] = []
    barrier = threading.Barrier(clients)
    lock = threading.Lock()

    def client(c: int) -> None:
        with httpx2.Client(base_url=url, headers=headers, timeout=120) as http:
            barrier.wait()
            for r in range(per_client):
                sid, body = targets[(c * per_client + r) % len(targets)]
                t0, retries, status, ok = time.perf_counter(), 0, 0, False
                while True:
                    try:
                        resp = http.post(f"/v1/scenes/{sid}/render", json=body)
                    except httpx2.HTTPError:
                        status = 0
                        break
                    status = resp.status_code
                    if status == 503 and "Retry-After" in resp.headers:
                        retries += 1
                        time.sleep(float(resp.headers["Retry-After"]))
                        continue
                    ok = status == 200 and resp.content[:8] == b"\x89PNG\r\n\x1a\n"
                    break
                with lock:
                    results.append({"ok": ok, "status": status, "retries": retries, "s": time.perf_counter() - t0})

    t0 = time.perf_counter()
    threads = [threading.Thread(target=client, args=(c,)) for c in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.perf_counter() - t0
    lat = [r["s"] for r in results if r["ok"]]
    return {
        "clients": clients,
        "requests": len(results),
        "ok": len(lat),
        "errors": len(results) - len(lat),
        "retries_after_503": sum(r["retries"] for r in results),
        "p50_s": percentile(lat, 50) if lat else None,
        "p95_s": percentile(lat, 95) if lat else None,
        "max_s": max(lat) if lat else None,
        "renders_per_s": len(lat) / wall,
        "wall_s": wall,
    }


def load_bench(args) -> None:
    """The --load protocol (module docstring, 5-6)."""
    import shutil

    fern = Path(args.data).resolve()
    tmp = Path(tempfile.mkdtemp(prefix="cmc-service-load-"))
    run = uuid.uuid4().hex[:8]
    port = free_port()
    env = deployed_env(tmp, args.redis, run)
    settings = {k: v for k, v in env.items() if k.startswith(("CMC_RENDER", "CMC_MAX_"))}
    headers = {"Authorization": "Bearer bench-key"}
    url = f"http://127.0.0.1:{port}"
    procs: list = []
    report: dict = {
        "date": date.today().isoformat(),
        "command": "python bench/service_bench.py " + " ".join(sys.argv[1:]),
        "machine": machine_info(),
        "git_commit": git_commit(),  # "+dirty" when the tree had uncommitted changes
        "settings": {k: str(v) for k, v in vars(args).items()},
        "render_settings_from_env": settings,
        "render_settings": render_settings(env),
    }
    try:
        start_services(tmp, env, procs, port)
        client = httpx2.Client(base_url=url, headers=headers, timeout=120)
        split = load_llff(fern)
        train = split.train
        names = train.names
        cams = camera_file_to_dict(CameraFile(train.cameras, names, train.near_far), "opengl")
        sids = []
        t0 = time.perf_counter()
        for _ in range(args.scenes):
            files = [("images", (n, (fern / "images_8" / n).read_bytes(), "image/png")) for n in names]
            files.append(("cameras", ("cameras.json", json.dumps(cams).encode(), "application/json")))
            files.append(("options", (None, json.dumps({"steps": args.steps}))))
            r = client.post("/v1/scenes", files=files)
            r.raise_for_status()
            sids.append(r.json()["id"])
        for sid in sids:
            while (body := client.get(f"/v1/scenes/{sid}").json())["status"] not in ("ready", "failed"):
                time.sleep(2)
            assert body["status"] == "ready", body
        report["scenes"] = {"count": len(sids), "steps": args.steps, "seconds_to_all_ready": time.perf_counter() - t0}
        print(f"{len(sids)} scenes ready in {report['scenes']['seconds_to_all_ready']:.0f} s", flush=True)
        for p in procs[1:]:  # the worker: nothing else runs beside the API from here on
            os.killpg(p.pid, signal.SIGTERM)
            p.wait(30)
        if args.baked:
            for sid in sids:
                dst = tmp / "storage" / sid / "baked"
                shutil.rmtree(dst)
                shutil.copytree(args.baked, dst)
        report["encoding"] = encodings(tmp / "storage" / sids[0] / "baked", split)
        bodies = [camera_body(split.test, i) for i in range(len(split.test))]
        for sid in sids:  # warm the cache
            assert client.post(f"/v1/scenes/{sid}/render", json=bodies[0]).status_code == 200
        report["load"] = []
        for scenario, targets in (
            ("one scene", [(sids[0], b) for b in bodies]),
            (f"{len(sids)} scenes round-robin", [(sid, bodies[k % len(bodies)]) for k, sid in enumerate(sids)]),
        ):
            for clients in (int(c) for c in args.clients.split(",")):
                r = {"scenario": scenario, **load_phase(url, headers, targets, clients, args.requests_per_client)}
                report["load"].append(r)
                print(
                    f"{scenario}, {clients} clients: {r['ok']}/{r['requests']} ok, {r['errors']} errors, "
                    f"{r['retries_after_503']} retries after 503, p50 {r['p50_s']:.2f} s p95 {r['p95_s']:.2f} s "
                    f"max {r['max_s']:.2f} s, {r['renders_per_s']:.2f} renders/s",
                    flush=True,
                )
        rss = subprocess.run(["ps", "-o", "rss=", "-p", str(procs[0].pid)], capture_output=True, text=True).stdout
        report["api_rss_mb_after"] = int(rss.split()[0]) / 1024 if rss.split() else None
    finally:
        stop_process_groups(procs)
        flush_redis(args.redis)
    write_report(report, args.out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default="../shared/datasets/llff/fern")
    ap.add_argument("--out", default="bench/reports/current/service_cpu.json")
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--uploads", type=int, default=7)
    ap.add_argument("--renders", type=int, default=30)
    ap.add_argument("--concurrent", type=int, default=20)
    ap.add_argument("--redis", default="redis://127.0.0.1:6379/13", help="a Redis database of its own (emptied after)")
    ap.add_argument("--load", action="store_true", help="the issue-10 protocol: encodings and latency under load")
    ap.add_argument("--scenes", type=int, default=8, help="scenes for --load")
    ap.add_argument("--baked", type=Path, default=None, help="with --load: the bake every scene renders")
    ap.add_argument("--clients", default="1,20,50", help="with --load: concurrent clients, comma-separated")
    ap.add_argument("--requests-per-client", type=int, default=4)
    args = ap.parse_args()
    if args.load:
        return load_bench(args)
    fern = Path(args.data).resolve()
    tmp = Path(tempfile.mkdtemp(prefix="cmc-service-bench-"))
    run = uuid.uuid4().hex[:8]
    port = free_port()
    env = deployed_env(tmp, args.redis, run)
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
        "machine": machine_info(),
        "git_commit": git_commit(),  # "+dirty" when the tree had uncommitted changes
        "settings": vars(args),
    }
    try:
        uvicorn = ["-m", "uvicorn", "service.app:create_app", "--factory", "--log-level", "warning"]
        start("api", [sys.executable, *uvicorn, "--port", str(port)])
        wait_ready(url, "/readyz", 200)
        client = httpx2.Client(base_url=url, headers=headers, timeout=120)

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
            with httpx2.Client(base_url=url, headers=headers, timeout=300) as c:
                barrier.wait()
                t0 = time.perf_counter()
                try:
                    r = c.post(f"/v1/scenes/{sid}/render", json=bodies[k % len(bodies)])
                    results.append((r.status_code, time.perf_counter() - t0, len(r.content)))
                except httpx2.HTTPError:
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
        stop_process_groups(procs)
        flush_redis(args.redis)
    write_report(report, args.out)


if __name__ == "__main__":
    main()
