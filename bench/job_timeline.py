"""One whole job through ``cmc serve`` as a phone user has it: what the status said and when.

The three full-resolution fern JPEGs (``images/``, no cameras part: pose estimation included) are
uploaded to a fresh ``cmc serve`` (embedded runner, CPU) with the ``fast`` preset at ``--steps``
training steps, and the status is polled every ``--poll`` seconds until the scene is ready. Per
run: seconds from the upload to each preview (the status' ``preview_step``) and to ``ready``, the
seconds in each status,
and how good the ETA was (issue 39: within 25 % of the truth from the first 10 % of the job on):
at every poll from 10 % of the job's duration on, ``|eta_seconds - seconds left| / seconds left``;
the median, the 90th percentile and the largest, and the share of polls within 25 %. The polls
of the last 5 s are left out (a few seconds' error is a large share of nothing). Also the error of
the first estimate the job showed (while its poses are estimated, before it has measured
anything). Jobs of the same step count share a data folder, so a second one starts its estimate
from the first one's measured pace (``worker.pipeline.JobPace``), as on a deployment that has run
a job before; ``earlier_jobs`` counts the scenes already there. Each run also keeps the scene's
``stats`` as the worker recorded them (the stages' measured seconds).

Usage (repository root, nothing else running):
    PYTHONPATH=. python bench/job_timeline.py --data ../shared/datasets/llff/fern --steps 80,300 \\
        --out bench/reports/current/job_timeline_fern_cpu.json
writes the report and a markdown table beside it (``.md``); ``--table REPORT.json`` prints the
table of an earlier report.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sqlite3
import statistics
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

import httpx2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from servers import free_port, stop_process_groups, wait_ready, write_report  # noqa: E402
from stop_time import start  # noqa: E402

from cmc.eval.bench import git_commit  # noqa: E402


def upload_parts(scene: Path, steps: int) -> list:
    """The multipart parts of ``POST /v1/scenes``: the scene's full-resolution photos and options."""
    parts: list = [("images", (p.name, p.read_bytes(), "image/jpeg")) for p in sorted((scene / "images").glob("*.JPG"))]
    parts.append(("options", (None, f'{{"steps": {steps}}}')))
    return parts


def eta_errors(samples: list[dict], total_s: float) -> dict:
    """The ETA's relative errors at the polls from 10 % of the job on (the last 5 s left out)."""
    errs = [
        abs(s["eta_seconds"] - (total_s - s["t"])) / (total_s - s["t"])
        for s in samples
        if s["t"] >= 0.1 * total_s and total_s - s["t"] > 5 and s["eta_seconds"] is not None
    ]
    if not errs:
        return {"polls": 0}
    return {
        "polls": len(errs),
        "median": round(statistics.median(errs), 3),
        "p90": round(float(np.quantile(errs, 0.9)), 3),
        "max": round(max(errs), 3),
        "share_within_25_percent": round(sum(e <= 0.25 for e in errs) / len(errs), 3),
    }


def end_bias(samples: list[dict], total_s: float) -> tuple[float, float]:
    """The ETA's mean signed error in seconds (+: too long) at the polls of the last 10 % of
    the training steps and at those while baking: where the checkpoint writes and the bake's
    estimates show."""

    def mean_error(polls: list[dict]) -> float:
        return float(np.mean([s["eta_seconds"] - (total_s - s["t"]) for s in polls])) if polls else float("nan")

    training = [s for s in samples if s["status"] == "training" and s["progress"] >= 0.9]
    return mean_error(training), mean_error([s for s in samples if s["status"] == "baking"])


def _scenes_in(database: Path) -> int:
    """Scenes in a ``cmc serve`` data folder's SQLite database (0 before its first run)."""
    if not database.exists():
        return 0
    with contextlib.closing(sqlite3.connect(database)) as db:
        return db.execute("select count(*) from scenes").fetchone()[0]


def _stats_of(database: Path, scene_id: str) -> dict:
    """What the worker measured on a scene (its record's ``stats``: the stages' seconds)."""
    with contextlib.closing(sqlite3.connect(database)) as db:
        row = db.execute("select stats from scenes where id = ?", (scene_id,)).fetchone()
    return json.loads(row[0]) if row and row[0] else {}


def run(scene: Path, steps: int, poll_s: float, tmp: Path, preview_at: str | None = None) -> dict:
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    data, log = tmp / f"data-{steps}", tmp / f"serve-{steps}.log"
    earlier = _scenes_in(data / "cmc.db")
    env = {k: v for k, v in os.environ.items() if k not in ("CMC_API_KEYS", "CMC_API_KEYS_FILE", "CMC_PREVIEW_AT")}
    env.update(PYTHONPATH=str(ROOT), CMC_DEVICE="cpu", CMC_DATA_DIR=str(data))
    if preview_at is not None:
        env["CMC_PREVIEW_AT"] = preview_at
    serve = [sys.executable, "-m", "cmc.cli", "serve", "--log-level", "warning", "--data-dir", str(data)]
    proc = start([*serve, "--port", str(port)], env, log)
    try:
        wait_ready(url, "/healthz", 600, proc, log)
        with httpx2.Client(base_url=url, timeout=60) as client:
            parts = upload_parts(scene, steps)
            t0 = time.perf_counter()
            r = client.post("/v1/scenes", files=parts)
            r.raise_for_status()
            sid = r.json()["id"]
            samples: list[dict] = []
            while True:
                body = client.get(f"/v1/scenes/{sid}").json()
                t = time.perf_counter() - t0
                samples.append(
                    {
                        k: body.get(k)
                        for k in ("status", "progress", "eta_seconds", "preview_ready", "preview_step", "detail")
                    }
                    | {"t": t}
                )
                if body["status"] in ("ready", "failed"):
                    break
                time.sleep(poll_s)
        if body["status"] != "ready":
            raise RuntimeError(f"the job failed: {body}")
        total = samples[-1]["t"]
        preview = next((s["t"] for s in samples if s["preview_ready"]), None)
        previews: dict[int, float] = {}  # each preview's step: when a poll first saw it
        for s in samples:
            if s.get("preview_step") is not None:
                previews.setdefault(s["preview_step"], round(s["t"], 1))
        by_status: dict[str, float] = {}
        for a, b in zip(samples, samples[1:], strict=False):
            by_status[a["status"]] = by_status.get(a["status"], 0.0) + b["t"] - a["t"]
        first = next(x for x in samples if x["eta_seconds"] is not None)
        return {
            "steps": steps,
            "earlier_jobs": earlier,
            "seconds_to_ready": round(total, 1),
            # the first estimate the job showed, against the truth then (before any stage of this
            # job measured itself: the reference's pace, or the latest earlier job's)
            "first_eta_error": round(abs(first["eta_seconds"] - (total - first["t"])) / (total - first["t"]), 3),
            "seconds_to_preview": None if preview is None else round(preview, 1),
            "seconds_to_previews": {str(step): t for step, t in previews.items()},
            "seconds_by_status": {k: round(v, 1) for k, v in by_status.items()},
            "eta_relative_error": eta_errors(samples, total),
            "stats": _stats_of(data / "cmc.db", sid),
            "samples": [{k: (round(v, 2) if isinstance(v, float) else v) for k, v in s.items()} for s in samples],
        }
    finally:
        stop_process_groups([proc], grace_s=30)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", help="an LLFF scene folder with its photos in images/ (required to run)")
    ap.add_argument("--steps", default="80,300", help="comma-separated training steps, one job each")
    ap.add_argument("--poll", type=float, default=0.5, help="seconds between status polls")
    ap.add_argument("--preview-at", help="the server's CMC_PREVIEW_AT (default: the service's default)")
    ap.add_argument("--out", help="the report to write (required to run)")
    ap.add_argument("--table", help="only print the markdown table of this report")
    args = ap.parse_args()
    if args.table:
        print(summary_table(json.loads(Path(args.table).read_text())))
        return
    if not args.data or not args.out:
        ap.error("--data and --out are required to run jobs")
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for steps in (int(s) for s in args.steps.split(",")):
            row = run(Path(args.data), steps, args.poll, Path(tmp), args.preview_at)
            runs.append(row)
            print({k: v for k, v in row.items() if k != "samples"}, flush=True)
    report = {
        "command": " ".join(["python", *sys.argv]),
        "machine": f"{os.cpu_count()} CPU cores",
        "date": date.today().isoformat(),
        "git_commit": git_commit(),
        "runs": runs,
    }
    write_report(report, args.out)
    Path(args.out).with_suffix(".md").write_text(summary_table(report) + "\n")


def summary_table(report: dict) -> str:
    """A markdown table of a report's runs."""
    lines = [
        "| steps | earlier jobs | preview after s (its step) | ready after s | poses / training / baking s "
        "| first ETA's error | ETA error: median / p90 / max | within 25 % | ETA's mean error at the end: "
        "last 10 % of steps / baking, s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in report["runs"]:
        st, e = r["seconds_by_status"], r["eta_relative_error"]
        stages = " / ".join(f"{st.get(k, 0.0):.1f}" for k in ("estimating_poses", "training", "baking"))
        first = "-" if "first_eta_error" not in r else f"{r['first_eta_error']:.2f}"  # (reports before 2026-12-02)
        training, baking = end_bias(r["samples"], r["seconds_to_ready"])
        # each preview (reports before 2026-12-06: the first, whose step they did not record)
        steps = r.get("seconds_to_previews") or {}
        previews = ", ".join(f"{t} ({step})" for step, t in steps.items()) or str(r["seconds_to_preview"])
        lines.append(
            f"| {r['steps']} | {r.get('earlier_jobs', '-')} | {previews} | {r['seconds_to_ready']} | "
            f"{stages} | {first} | {e['median']:.2f} / {e['p90']:.2f} / {e['max']:.2f} | "
            f"{100 * e['share_within_25_percent']:.0f} % of {e['polls']} polls | {training:+.1f} / {baking:+.1f} |"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    main()
