"""Load run of the quotas (issue 15, item 4): 50 clients, status polls, renders and uploads over a quota.

The deployed shape on this machine: two API processes (uvicorn, Celery mode, one SQLite store and
one artifact folder) counting the quotas in the real Redis at 127.0.0.1:6379, as two replicas
behind a load balancer would; the clients alternate between them. No worker runs, so every
upload stays queued: the concurrency quota fills and only deletes free it, and the daily quota
is reached within the run.

1. Setup: ``--keys`` API keys; per key, a ready scene whose baked MPI comes from an untrained
   model (render cost does not depend on training) at 128x96, 3 MPIs, written into the store
   and storage before the API starts. Limits: ``--max-concurrent-jobs``, ``--max-jobs-per-day``,
   ``--max-renders-per-second`` (small, so that each is reached).
2. ``--clients`` threads (client ``n`` uses key ``n % keys`` and replica ``n % 2``), each its own
   HTTP connection, for ``--seconds``: each request is a status poll of its key's ready scene
   (50 %), a 128x96 PNG render of it (30 %), an upload of three 96x72 PNGs with cameras (15 %),
   or a delete of one of the key's uploads (5 %; a poll when it has none), then a pause of
   0-0.2 s. A monitor reads each key's unfinished scenes from the database every 0.1 s.
3. Checks, written to the report with the numbers: no server error (5xx other than the render
   queue's 503 ``renderer_busy``, which is counted apart; or no answer); status polls never
   refused; every 429 with the expected code, ``Retry-After`` and ``RateLimit-*``; per key at
   most the daily quota of uploads accepted and never more unfinished scenes than the
   concurrency quota; renders admitted per key within the rolling-second bound; and the
   replicas' ``cmc_rate_limited_total`` summing to the clients' 429s.

Usage (from the repository root; writes bench/reports/current/quota_load_cpu.json)::

    python bench/quota_load.py --out bench/reports/current/quota_load_cpu.json
"""

from __future__ import annotations

import argparse
import io
import json
import math
import os
import random
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections import Counter, defaultdict
from datetime import UTC, datetime
from pathlib import Path

import httpx2
import numpy as np
from PIL import Image
from servers import free_port, stop_process_groups, wait_ready, write_report

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cmc.data.datasets import synthetic_scene  # noqa: E402
from cmc.eval.bench import git_commit, machine_info  # noqa: E402
from cmc.geometry.cameras import CameraFile, camera_file_to_dict  # noqa: E402
from service.auth import key_digest  # noqa: E402
from service.db.scenes import SceneStore  # noqa: E402

CODES = {"upload": {"too_many_concurrent_jobs", "daily_job_quota_exceeded"}, "render": {"render_rate_limited"}}
LIMIT_OF_CODE = {
    "too_many_concurrent_jobs": "concurrent_jobs",
    "daily_job_quota_exceeded": "jobs_per_day",
    "render_rate_limited": "renders_per_second",
}


def pct(xs: list[float], q: float) -> float | None:
    return float(np.percentile(np.asarray(xs), q)) if xs else None


def upload_parts() -> list[tuple]:
    """Three 96x72 PNGs of a synthetic scene with their cameras (no SfM): a small upload."""
    scene = synthetic_scene(3, 96, 72)
    parts: list[tuple] = []
    for i, img in enumerate(scene.images):
        buf = io.BytesIO()
        Image.fromarray((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)).save(buf, "PNG")
        parts.append(("images", (f"view{i}.png", buf.getvalue(), "image/png")))
    cams = camera_file_to_dict(CameraFile(scene.cameras, [f"view{i}.png" for i in range(3)], scene.near_far), "opengl")
    parts.append(("cameras", ("cameras.json", json.dumps(cams).encode(), "application/json")))
    parts.append(("options", (None, json.dumps({"steps": 10, "resolution": 96}))))
    return parts


def ready_scenes(store: SceneStore, storage: Path, owners: list[str]) -> tuple[dict[str, str], dict]:
    """Per owner, a ready scene with a baked MPI of an untrained model at 128x96; and a render body."""
    from cmc.config import preset_config
    from cmc.method.training import Trainer
    from cmc.serving.baking import bake

    scene = synthetic_scene(3, 128, 96)
    baked = storage / "_baked"
    bake(Trainer(scene, preset_config("fast", steps=1, rays_per_view=64, unseen_rays=64)).model, baked)
    ids = {}
    for owner in owners:
        rec, _ = store.create(owner, {}, ["a.png", "b.png", "c.png"], ["00.png", "01.png", "02.png"], False)
        assert store.claim(rec.id, "poses", "bench", 60) is not None
        assert store.advance(rec.id, "bench", "done", "ready")
        shutil.copytree(baked, storage / rec.id / "baked")
        ids[owner] = rec.id
    shutil.rmtree(baked)
    data = camera_file_to_dict(CameraFile(scene.cameras[1:2], ["render"]), "opengl")
    frame = {k: v for k, v in data["frames"][0].items() if k != "file_path"}
    return ids, {**frame, "w": data["w"], "h": data["h"], "convention": "opengl"}


def rate_limited_totals(text: str) -> dict[str, float]:
    return {m[1]: float(m[2]) for m in re.finditer(r'^cmc_rate_limited_total\{limit="(\w+)"\} (\S+)$', text, re.M)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="bench/reports/current/quota_load_cpu.json")
    ap.add_argument("--clients", type=int, default=50)
    ap.add_argument("--keys", type=int, default=5)
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--max-concurrent-jobs", type=int, default=3)
    ap.add_argument("--max-jobs-per-day", type=int, default=10)
    ap.add_argument("--max-renders-per-second", type=int, default=2)
    ap.add_argument("--redis", default="redis://127.0.0.1:6379/12", help="a Redis database (only our keys are removed)")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="cmc-quota-load-"))
    run = uuid.uuid4().hex[:8]
    keys = [f"load-{run}-{k}" for k in range(args.keys)]
    owners = [key_digest(k)[:16] for k in keys]
    env = {
        **os.environ,
        "PYTHONPATH": str(ROOT),
        "CMC_MODE": "celery",
        "CMC_BROKER_URL": args.redis,
        "CMC_DATA_DIR": str(tmp),
        "CMC_CPU_QUEUE": f"load-cpu-{run}",
        "CMC_GPU_QUEUE": f"load-gpu-{run}",
        "CMC_API_KEYS": ",".join(keys),
        "CMC_MAX_CONCURRENT_JOBS": str(args.max_concurrent_jobs),
        "CMC_MAX_JOBS_PER_DAY": str(args.max_jobs_per_day),
        "CMC_MAX_RENDERS_PER_SECOND": str(args.max_renders_per_second),
    }
    store = SceneStore(f"sqlite:///{(tmp / 'cmc.db').resolve()}")
    ready, camera = ready_scenes(store, tmp / "storage", owners)
    parts = upload_parts()
    ports = [free_port(), free_port()]
    urls = [f"http://127.0.0.1:{p}" for p in ports]
    procs = []
    report: dict = {
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "command": "python bench/quota_load.py " + " ".join(sys.argv[1:]),
        "machine": machine_info(load_average_before=os.getloadavg()[0]),
        "git_commit": git_commit(),
        "settings": {k: v for k, v in vars(args).items() if k not in ("out", "redis")},
    }
    try:
        for i, port in enumerate(ports):
            log = open(tmp / f"api{i}.log", "wb")  # noqa: SIM115
            cmd = [sys.executable, "-m", "uvicorn", "service.app:create_app", "--factory", "--log-level", "warning"]
            p = subprocess.Popen(
                [*cmd, "--port", str(port)],
                env=env,
                cwd=ROOT,
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
            procs.append(p)
        for url, p, i in zip(urls, procs, range(len(urls)), strict=True):
            wait_ready(url, "/readyz", 300, p, tmp / f"api{i}.log")
        # warm-up: each replica loads each key's baked scene once (these renders are not counted)
        for url in urls:
            for key, owner in zip(keys, owners, strict=True):
                r = httpx2.post(
                    f"{url}/v1/scenes/{ready[owner]}/render",
                    json=camera,
                    headers={"Authorization": f"Bearer {key}"},
                    timeout=60,
                )
                assert r.status_code == 200, r.text
        time.sleep(1.1)  # the warm-up's renders leave their rolling second
        metrics_before = [rate_limited_totals(httpx2.get(f"{u}/metrics", timeout=10).text) for u in urls]

        records: list[dict] = []
        rec_lock = threading.Lock()
        mine: dict[str, list[str]] = defaultdict(list)  # key -> its uploaded scene ids
        peak_unfinished: dict[str, int] = defaultdict(int)
        stop = threading.Event()
        barrier = threading.Barrier(args.clients + 1)

        def monitor() -> None:
            while not stop.is_set():
                for key, owner in zip(keys, owners, strict=True):
                    n = len(store.unfinished(owner))
                    peak_unfinished[key] = max(peak_unfinished[key], n)
                time.sleep(0.1)

        def client(n: int) -> None:
            key, url = keys[n % len(keys)], urls[n % 2]
            sid = ready[owners[n % len(keys)]]
            rng = random.Random(n)
            with httpx2.Client(base_url=url, headers={"Authorization": f"Bearer {key}"}, timeout=60) as c:
                barrier.wait()
                while not stop.is_set():
                    kind = rng.choices(["poll", "render", "upload", "delete"], [50, 30, 15, 5])[0]
                    target = None
                    if kind == "delete":
                        with rec_lock:
                            target = mine[key].pop(rng.randrange(len(mine[key]))) if mine[key] else None
                        kind = "delete" if target else "poll"
                    t0 = time.perf_counter()
                    try:
                        if kind == "poll":
                            r = c.get(f"/v1/scenes/{sid}")
                        elif kind == "render":
                            r = c.post(f"/v1/scenes/{sid}/render", json=camera)
                        elif kind == "upload":
                            r = c.post("/v1/scenes", files=parts)
                        else:
                            r = c.delete(f"/v1/scenes/{target}")
                        status = r.status_code
                        body = r.json() if r.headers.get("content-type", "").startswith("application/json") else {}
                        error = body.get("error") if isinstance(body, dict) else None
                        code = error.get("code") if isinstance(error, dict) else None
                        h = r.headers
                        fields = all(f in h for f in ("ratelimit-limit", "ratelimit-remaining", "ratelimit-reset"))
                        retry = h.get("retry-after")
                        if kind == "upload" and status == 202:
                            with rec_lock:
                                mine[key].append(body["id"])
                    except httpx2.HTTPError as e:
                        status, code, fields, retry = 0, type(e).__name__, False, None
                    with rec_lock:
                        records.append(
                            {
                                "kind": kind,
                                "key": key,
                                "status": status,
                                "code": code,
                                "seconds": time.perf_counter() - t0,
                                "fields": fields,
                                "retry_after": retry,
                            }
                        )
                    time.sleep(rng.uniform(0, 0.2))

        threads = [threading.Thread(target=client, args=(n,)) for n in range(args.clients)]
        watcher = threading.Thread(target=monitor)
        for t in threads:
            t.start()
        barrier.wait()
        t_start = time.perf_counter()
        watcher.start()
        time.sleep(args.seconds)
        stop.set()
        for t in threads:
            t.join()
        watcher.join()
        elapsed = time.perf_counter() - t_start
        metrics_after = [rate_limited_totals(httpx2.get(f"{u}/metrics", timeout=10).text) for u in urls]
        report["results"] = summarize(records, args, elapsed, keys, owners, store, peak_unfinished)
        refused_by_metrics = {
            limit: sum(a.get(limit, 0) - b.get(limit, 0) for a, b in zip(metrics_after, metrics_before, strict=True))
            for limit in LIMIT_OF_CODE.values()
        }
        res = report["results"]
        res["metrics_rate_limited"] = refused_by_metrics
        res["checks"]["metrics_match_clients"] = all(
            refused_by_metrics[LIMIT_OF_CODE[code]] == n for code, n in res["refused_by_code"].items()
        ) and sum(refused_by_metrics.values()) == sum(res["refused_by_code"].values())
        res["all_checks_pass"] = all(res["checks"].values())
    finally:
        stop_process_groups(procs)
        import redis

        r = redis.Redis.from_url(args.redis)  # remove only this run's keys: queues and quota buckets
        ours = [env["CMC_CPU_QUEUE"], env["CMC_GPU_QUEUE"]]
        for owner in owners:
            ours += list(r.scan_iter(f"cmc:limits:{owner}:*"))
        r.delete(*ours)
        r.close()
        store.close()
        shutil.rmtree(tmp, ignore_errors=True)
    res = report["results"]
    print(json.dumps({k: res[k] for k in ("requests", "server_errors", "refused_by_code", "checks")}, indent=1))
    write_report(report, args.out)


def summarize(records, args, elapsed, keys, owners, store, peak_unfinished) -> dict:
    by_kind: dict[str, Counter] = defaultdict(Counter)
    for r in records:
        by_kind[r["kind"]][str(r["status"])] += 1
    refused = [r for r in records if r["status"] == 429]
    server_errors = [r for r in records if r["status"] == 0 or (r["status"] >= 500 and r["code"] != "renderer_busy")]
    latency = {
        kind: {
            "p50_ms": 1000 * pct(xs, 50),
            "p99_ms": 1000 * pct(xs, 99),
            "max_ms": 1000 * max(xs),
        }
        for kind in by_kind
        if (xs := [r["seconds"] for r in records if r["kind"] == kind])
    }
    per_key = {}
    bound = args.max_renders_per_second * (math.ceil(elapsed) + 1)
    for key, owner in zip(keys, owners, strict=True):
        mine = [r for r in records if r["key"] == key]
        renders = [r for r in mine if r["kind"] == "render" and r["status"] not in (0, 429)]
        per_key[key] = {
            "uploads_accepted": sum(1 for r in mine if r["kind"] == "upload" and r["status"] == 202),
            "uploads_refused": sum(1 for r in mine if r["kind"] == "upload" and r["status"] == 429),
            "peak_unfinished": peak_unfinished[key],
            "unfinished_at_end": len(store.unfinished(owner)),
            "renders_admitted": len(renders),
            "renders_refused": sum(1 for r in mine if r["kind"] == "render" and r["status"] == 429),
        }
    checks = {
        "no_server_errors": not server_errors,
        "status_polls_never_refused": all(r["status"] != 429 for r in records if r["kind"] in ("poll", "delete")),
        "refusals_have_expected_codes": all(r["code"] in CODES.get(r["kind"], set()) for r in refused),
        "refusals_have_retry_after_and_ratelimit_fields": all(r["fields"] and r["retry_after"] for r in refused),
        "accepted_uploads_and_renders_have_ratelimit_fields": all(
            r["fields"] for r in records if (r["kind"], r["status"]) in (("upload", 202), ("render", 200))
        ),
        "uploads_within_daily_quota": all(k["uploads_accepted"] <= args.max_jobs_per_day for k in per_key.values()),
        "daily_quota_reached_by_every_key": all(
            k["uploads_accepted"] == args.max_jobs_per_day for k in per_key.values()
        ),
        "unfinished_within_concurrency_quota": all(
            k["peak_unfinished"] <= args.max_concurrent_jobs for k in per_key.values()
        ),
        "renders_within_rolling_second_bound": all(k["renders_admitted"] <= bound for k in per_key.values()),
    }
    return {
        "seconds": elapsed,
        "requests": len(records),
        "requests_per_second": len(records) / elapsed,
        "by_kind_and_status": {k: dict(sorted(v.items())) for k, v in sorted(by_kind.items())},
        "refused_by_code": dict(Counter(r["code"] for r in refused)),
        "server_errors": len(server_errors),
        "renderer_busy_503": sum(1 for r in records if r["code"] == "renderer_busy"),
        "latency": latency,
        "retry_after_by_code": {
            code: [min(vs), max(vs)]
            for code in sorted({r["code"] for r in refused})
            if (vs := [int(r["retry_after"]) for r in refused if r["code"] == code and r["retry_after"]])
        },
        "per_key": per_key,
        "render_bound_per_key": bound,
        "checks": checks,
    }


if __name__ == "__main__":
    main()
