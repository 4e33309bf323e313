"""Time to a clean stop on SIGTERM during training (issue 15, item 3).

The job: the fern scene of bench/service_bench.py (``images_8`` views 1, 10, 19 at 504x378 with
the dataset's poses as the cameras part, so no structure from motion), ``fast`` preset, 400
steps, default settings (a checkpoint every 250 steps or 60 s of training). SIGTERM is sent once
training has done ``--after-steps`` steps, before any periodic checkpoint, so a checkpoint on
disk afterwards was written by the stop.

Shapes, each its own run:

* ``celery``: the deployed shape (API in Celery mode, one Celery worker for both queues, prefork,
  concurrency 1, over the real Redis: a database of its own, emptied after; SQLite store). The
  SIGTERM goes to the worker's main process only, as ``docker stop`` sends it.
* ``embedded``: ``cmc serve``, SIGTERM to it (Ctrl-C, systemd, a container).

Measured: seconds from SIGTERM to the process's exit; the checkpoint's step; the job's status
afterwards; for ``celery`` whether the training message is back in the queue for the next worker.
A process still running ``--grace`` seconds after SIGTERM (compose's stop_grace_period, 30 s) is
killed with SIGKILL, as Docker does, and recorded so.

Usage (from the repository root; writes bench/reports/current/stop_time.json)::

    python bench/stop_time.py --data ../shared/datasets/llff/fern --out bench/reports/current/stop_time.json
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
import uuid
from datetime import date
from pathlib import Path

import httpx2

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from servers import flush_redis, free_port, stop_process_groups, wait_ready, write_report  # noqa: E402

from cmc.data.datasets import load_llff  # noqa: E402
from cmc.eval.bench import git_commit, machine_info  # noqa: E402
from cmc.geometry.cameras import CameraFile, camera_file_to_dict  # noqa: E402


def fern_upload(fern: Path, steps: int) -> list:
    train = load_llff(fern).train
    files = [("images", (n, (fern / "images_8" / n).read_bytes(), "image/png")) for n in train.names]
    cams = camera_file_to_dict(CameraFile(train.cameras, train.names, train.near_far), "opengl")
    files.append(("cameras", ("cameras.json", json.dumps(cams).encode(), "application/json")))
    files.append(("options", (None, json.dumps({"steps": steps}))))
    return files


def start(cmd: list[str], env: dict, log: Path) -> subprocess.Popen:
    with open(log, "wb") as out:
        return subprocess.Popen(cmd, env=env, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)


def run(shape: str, args: argparse.Namespace, tmp: Path) -> dict:
    run_id = uuid.uuid4().hex[:8]
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    data = tmp / f"{shape}-data"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "CMC_DEVICE": "cpu", "CMC_DATA_DIR": str(data)}
    procs: dict[str, subprocess.Popen] = {}
    headers: dict[str, str] = {}
    if shape == "celery":
        env.update(
            CMC_MODE="celery",
            CMC_BROKER_URL=args.redis,
            CMC_API_KEYS="bench-key",
            CMC_CPU_QUEUE=f"bench-cpu-{run_id}",
            CMC_GPU_QUEUE=f"bench-gpu-{run_id}",
        )
        headers = {"Authorization": "Bearer bench-key"}
        api = [sys.executable, "-m", "uvicorn", "service.app:create_app", "--factory", "--log-level", "warning"]
        procs["api"] = start([*api, "--port", str(port)], env, tmp / f"{shape}-api.log")
        wait_ready(url, "/healthz", 600, procs["api"], tmp / f"{shape}-api.log")
        queues = f"{env['CMC_CPU_QUEUE']},{env['CMC_GPU_QUEUE']}"
        celery = [sys.executable, "-m", "celery", "-A", "worker.celery_app", "worker", "-c", "1", "-Q", queues]
        celery += ["--without-gossip", "--without-mingle", "--loglevel", "INFO"]
        procs["stopped"] = start(celery, env, tmp / f"{shape}-worker.log")
    else:
        env.pop("CMC_API_KEYS", None)
        env.pop("CMC_API_KEYS_FILE", None)
        serve = [sys.executable, "-m", "cmc.cli", "serve", "--log-level", "warning", "--data-dir", str(data)]
        procs["stopped"] = start([*serve, "--port", str(port)], env, tmp / f"{shape}-serve.log")
        wait_ready(url, "/healthz", 600, procs["stopped"], tmp / f"{shape}-serve.log")
    client = httpx2.Client(base_url=url, headers=headers, timeout=60)
    try:
        sid = client.post("/v1/scenes", files=fern_upload(Path(args.data), args.steps)).json()["id"]
        while True:
            body = client.get(f"/v1/scenes/{sid}").json()
            assert body["status"] not in ("failed", "ready"), body
            if body["status"] == "training" and body["progress"] * args.steps >= args.after_steps:
                break
            time.sleep(0.2)
        proc = procs.pop("stopped")
        t0 = time.perf_counter()
        proc.send_signal(signal.SIGTERM)  # the process itself, not its group: what docker stop does
        try:
            proc.wait(args.grace)
            seconds, killed = time.perf_counter() - t0, False
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(30)
            seconds, killed = time.perf_counter() - t0, True
        ckpt = data / "storage" / sid / "checkpoint.pt"
        step = None
        if ckpt.exists():
            import torch

            step = int(torch.load(ckpt, weights_only=False, map_location="cpu")["step"])
        row: dict = {
            "shape": shape,
            "steps_when_signalled": round(body["progress"] * args.steps),
            "seconds_to_exit": round(seconds, 2),
            "killed_after_grace": killed,
            "checkpoint_step": step,
            "checkpoint_mib": round(ckpt.stat().st_size / 2**20) if ckpt.exists() else None,
        }
        if shape == "celery":
            after = client.get(f"/v1/scenes/{sid}").json()
            row["status_after"] = {k: after[k] for k in ("status", "progress", "detail")}
            import redis

            r = redis.Redis.from_url(args.redis)
            row["training_message_queued"] = int(r.llen(env["CMC_GPU_QUEUE"]))
            r.close()
        return row
    finally:
        client.close()
        stop_process_groups(procs.values(), grace_s=30)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default="../shared/datasets/llff/fern")
    ap.add_argument("--out", default="bench/reports/current/stop_time.json")
    ap.add_argument("--label", default="after", help="what code this measures (after / before)")
    ap.add_argument("--shapes", nargs="+", default=["celery", "embedded"], choices=["celery", "embedded"])
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--after-steps", type=int, default=10, help="training steps done before SIGTERM")
    ap.add_argument("--grace", type=float, default=30.0, help="seconds before SIGKILL (compose: 30)")
    ap.add_argument("--redis", default="redis://127.0.0.1:6379/12", help="a Redis database of its own (emptied)")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="cmc-stop-time-"))
    report: dict = {
        "date": date.today().isoformat(),
        "command": "python bench/stop_time.py " + " ".join(sys.argv[1:]),
        "label": args.label,
        "machine": machine_info(),
        "git_commit": git_commit(),
        "steps": args.steps,
        "after_steps": args.after_steps,
        "grace_s": args.grace,
        "target_s": 10.0,
        "rows": [],
    }
    try:
        for shape in args.shapes:
            row = run(shape, args, tmp)
            report["rows"].append(row)
            print(json.dumps(row), flush=True)
    finally:
        flush_redis(args.redis)
    write_report(report, args.out)


if __name__ == "__main__":
    main()
