"""Intake memory (issue 15, item 1): peak resident memory of the API for N concurrent worst-case uploads.

Worst-case upload: three photos of one flat colour at exactly ``CMC_MAX_IMAGE_PIXELS`` (the
default 50,000,000: 8000 x 6250), a few hundred KB each however many pixels they hold, in the
two formats that cost the most memory to decode per pixel (``cmc.data.images.decode_bytes``): PNG
with alpha (8 bytes per pixel) and WebP (16). Each upload is one ``POST /v1/scenes`` with its
own three files; N of them are sent at once from N threads.

Shapes, each a fresh server process per measurement (so its high-water mark is its own):

* ``api``: the deployed API (``uvicorn --factory service.app:create_app``, ``CMC_MODE=celery``)
  over the real Redis (a database of its own, emptied after) with no worker: intake alone.
* ``embedded``: ``cmc serve`` (jobs in the same process): intake, then the pose jobs one after
  another (structure from motion fails on flat photos after decoding them, as it would on a real
  upload's decode; its SIFT runs at 1600 px either way). ``intake`` is the peak when every upload
  was answered, ``with pose jobs`` the peak once every job has finished.

Peak = ``VmHWM`` of the server process (/proc/PID/status); ``idle`` = its ``VmRSS`` after one
small upload (everything imported). Linux only.

Usage (from the repository root; writes bench/reports/current/intake_memory.json)::

    python bench/intake_memory.py --out bench/reports/current/intake_memory.json
    python bench/intake_memory.py --label before --counts 1 4 --kinds png --shapes api \\
        --out bench/reports/current/intake_memory_before.json     # on the code before the fix (git stash)
"""

from __future__ import annotations

import argparse
import io
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from datetime import date
from pathlib import Path

import httpx2
from PIL import Image
from servers import flush_redis, free_port, wait_ready, write_report

ROOT = Path(__file__).resolve().parents[1]
MIB = 1 << 20


def proc_status(pid: int) -> dict[str, int]:
    """VmRSS and VmHWM of a process, in bytes."""
    out = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            out[key] = int(value.split()[0]) * 1024
    return out


def worst_case_photo(kind: str, pixels: int) -> tuple[str, bytes, str]:
    """A flat photo of ``pixels`` pixels (4:3-ish, exactly at the limit when it factors so):
    (file name, bytes, media type)."""
    w = 8000 if pixels % 8000 == 0 else int((pixels * 4 / 3) ** 0.5)
    h = pixels // w
    buf = io.BytesIO()
    if kind == "png":
        Image.new("RGBA", (w, h), (40, 90, 160, 200)).save(buf, "PNG")
        return "flat.png", buf.getvalue(), "image/png"
    if kind == "webp":
        Image.new("RGB", (w, h), (40, 90, 160)).save(buf, "WEBP", quality=80)
        return "flat.webp", buf.getvalue(), "image/webp"
    raise ValueError(kind)


def decode_memory_bytes() -> int | None:
    """The decode budget the servers run with (None: code without one, before issue 15)."""
    sys.path.insert(0, str(ROOT))
    from service.settings import Settings

    if "decode_memory_bytes" not in Settings.model_fields:
        return None
    return int(os.environ.get("CMC_DECODE_MEMORY_BYTES") or Settings.model_construct().decode_memory_bytes)


def small_png() -> bytes:
    buf = io.BytesIO()
    Image.new("RGB", (96, 72), (128, 128, 128)).save(buf, "PNG")
    return buf.getvalue()


class Server:
    """The API as a child process: ``api`` (celery mode, no worker) or ``embedded`` (cmc serve)."""

    def __init__(self, shape: str, tmp: Path, env: dict[str, str]):
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.log = tmp / f"{shape}-{self.port}.log"
        if shape == "api":
            args = ["-m", "uvicorn", "service.app:create_app", "--factory", "--log-level", "warning"]
        else:
            args = ["-m", "cmc.cli", "serve", "--log-level", "warning", "--data-dir", str(tmp / f"data-{self.port}")]
        with open(self.log, "wb") as log:
            self.proc = subprocess.Popen(
                [sys.executable, *args, "--port", str(self.port)],
                env=env,
                cwd=ROOT,
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        wait_ready(self.url, "/healthz", 300, self.proc, self.log)

    def stop(self) -> None:
        try:
            os.killpg(self.proc.pid, signal.SIGTERM)
            self.proc.wait(30)
        except (ProcessLookupError, subprocess.TimeoutExpired):
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(10)


def upload(url: str, photo: tuple[str, bytes, str], headers: dict[str, str]) -> tuple[int, str]:
    name, data, media = photo
    stem, ext = name.rsplit(".", 1)
    files = [("images", (f"{stem}{k}.{ext}", data, media)) for k in range(3)]
    r = httpx2.post(f"{url}/v1/scenes", files=files, headers=headers, timeout=1800)
    return r.status_code, (r.json().get("id") or "") if r.status_code == 202 else r.text[:200]


def concurrent_uploads(url: str, photo: tuple[str, bytes, str], n: int, headers: dict[str, str]) -> list:
    """N uploads sent at once from N threads: [(status, scene id or error text)]."""
    results: list = [None] * n
    barrier = threading.Barrier(n)

    def one(k: int) -> None:
        barrier.wait()
        try:
            results[k] = upload(url, photo, headers)
        except httpx2.HTTPError as e:
            results[k] = (0, repr(e))

    threads = [threading.Thread(target=one, args=(k,)) for k in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return results


def measure(shape: str, kind: str, n: int, photo, tmp: Path, env: dict[str, str]) -> dict:
    headers = {"Authorization": "Bearer bench-key"} if shape == "api" else {}
    server = Server(shape, tmp, env)
    try:
        warm = upload(server.url, ("warm.png", small_png(), "image/png"), headers)
        assert warm[0] == 202, warm
        idle = proc_status(server.proc.pid)["VmRSS"]
        t0 = time.perf_counter()
        results = concurrent_uploads(server.url, photo, n, headers)
        seconds = time.perf_counter() - t0
        intake = proc_status(server.proc.pid)["VmHWM"]
        row = {
            "shape": shape,
            "kind": kind,
            "uploads": n,
            "statuses": sorted({s for s, _ in results}),
            "errors": [e for s, e in results if s != 202][:3],
            "seconds_to_last_answer": round(seconds, 2),
            "idle_rss_mib": round(idle / MIB),
            "peak_rss_mib": round(intake / MIB),
        }
        if shape == "embedded":  # wait for the pose jobs (and the warm-up's) to end
            ids = [warm[1]] + [i for s, i in results if s == 202]
            deadline = time.time() + 1800
            while time.time() < deadline:
                states = [httpx2.get(f"{server.url}/v1/scenes/{i}", timeout=30).json()["status"] for i in ids]
                if all(st in ("failed", "ready", "training", "baking") for st in states):
                    break
                time.sleep(1)
            row["job_statuses"] = sorted(set(states))
            row["peak_rss_with_pose_jobs_mib"] = round(proc_status(server.proc.pid)["VmHWM"] / MIB)
        return row
    finally:
        server.stop()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="bench/reports/current/intake_memory.json")
    ap.add_argument("--label", default="after", help="what code this measures (after / before)")
    ap.add_argument("--counts", type=int, nargs="+", default=[1, 4, 16])
    ap.add_argument("--kinds", nargs="+", default=["png", "webp"], choices=["png", "webp"])
    ap.add_argument("--shapes", nargs="+", default=["api", "embedded"], choices=["api", "embedded"])
    ap.add_argument("--embedded-counts", type=int, nargs="+", default=[1, 4], help="N for the embedded shape")
    ap.add_argument("--pixels", type=int, default=50_000_000, help="photo size: the pixel limit (default's)")
    ap.add_argument("--redis", default="redis://127.0.0.1:6379/12", help="a Redis database of its own (emptied)")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="cmc-intake-memory-"))
    run = uuid.uuid4().hex[:8]
    env = {
        **os.environ,
        "PYTHONPATH": str(ROOT),
        "CMC_BROKER_URL": args.redis,
        "CMC_DATA_DIR": str(tmp / "api-data"),
        "CMC_CPU_QUEUE": f"bench-cpu-{run}",
        "CMC_GPU_QUEUE": f"bench-gpu-{run}",
        "CMC_MAX_IMAGE_PIXELS": str(args.pixels),
        "CMC_DEVICE": "cpu",
    }
    api_env = {**env, "CMC_MODE": "celery", "CMC_API_KEYS": "bench-key"}
    embedded_env = {k: v for k, v in env.items() if k not in ("CMC_API_KEYS", "CMC_API_KEYS_FILE")}
    sys.path.insert(0, str(ROOT))
    from cmc.eval.bench import git_commit, machine_info

    report: dict = {
        "date": date.today().isoformat(),
        "command": "python bench/intake_memory.py " + " ".join(sys.argv[1:]),
        "label": args.label,
        "machine": machine_info(memory_gib=round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / (1 << 30))),
        "git_commit": git_commit(),
        "pixels": args.pixels,
        "decode_memory_bytes": decode_memory_bytes(),
        "rows": [],
    }
    try:
        for kind in args.kinds:
            photo = worst_case_photo(kind, args.pixels)
            report.setdefault("photos", {})[kind] = {"name": photo[0], "bytes": len(photo[1])}
            for shape in args.shapes:
                counts = args.counts if shape == "api" else args.embedded_counts
                if shape == "embedded" and kind != "png":
                    continue  # the pose jobs' share is the same for any format
                for n in counts:
                    row = measure(shape, kind, n, photo, tmp, api_env if shape == "api" else embedded_env)
                    report["rows"].append(row)
                    print(json.dumps(row), flush=True)
    finally:
        flush_redis(args.redis)
    write_report(report, args.out)


if __name__ == "__main__":
    main()
