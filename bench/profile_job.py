"""Where the time of one `fast` job goes: model build, training, bake, first render.

Stages, each timed with the device synchronised at its ends:
  * ``model build``: ``Trainer(...)``, split into the plane sweeps that place the planes and fit
    the depth range (``cmc.method.model.sweep_statistics``, the sweeps it runs included), the sweeps
    that set each MPI's initial alpha (``cmc.method.model.sweep_probabilities`` called on its own) and
    the rest;
  * ``train``: every step of ``Trainer.train_step`` done here in three timed parts (forward =
    ``compute_losses``, backward, Adam step), per loss phase (reconstruction only, then all terms);
  * ``preview bake``: the bake a job publishes after ``--preview-at`` of its steps (the service's
    ``CMC_PREVIEW_AT``, at ``cmc.serving.baking.PREVIEW_TEXEL_SCALE``), and the final ``bake``
    (``cmc.serving.baking.bake``), each scored on the test views (PSNR; the scoring is not
    timed); ``load`` (``BakedScene.load``), the first render of a test view and the median of
    ``--renders`` more.
Pose estimation is not in it (bench/reports/history/sift_octave.md times it on the phone photos). The split
training loop syncs the device three times a step, which the service's loop does not.

Usage (repository root):
    PYTHONPATH=. python bench/profile_job.py --data ../shared/datasets/llff/fern --device cpu \
        --out bench/reports/current/profile_job_fern_cpu_cross_view.json
prints a markdown table (seconds and share per stage) and writes it with the raw timings as JSON;
    python bench/profile_job.py --update-md bench/PROFILE.md REPORT.json [REPORT.json ...]
rewrites the table between ``<!-- profile-table -->`` and ``<!-- /profile-table -->`` in that
file, one column pair per report.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import statistics
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import torch

import cmc.method.model
from cmc.config import preset_config, with_settings
from cmc.data.datasets import load_llff
from cmc.eval.bench import report_header
from cmc.eval.metrics import psnr
from cmc.method.training import Trainer, lr_at
from cmc.serving.baking import PREVIEW_TEXEL_SCALE, BakedScene, bake


def side_by_side(reports: list[dict[str, Any]]) -> str:
    """One markdown table of several reports' stages: seconds and share per report."""
    stages = list(dict.fromkeys(n for r in reports for n in r["stages_s"]))
    head = " | ".join(f"{r['device']}, {r['date']}, {r['git_commit']}: s | share" for r in reports)
    lines = [f"| stage | {head} |", "|---|" + "---|---|" * len(reports)]
    sizes = [f"{r['config']['steps']} steps, {r['config']['model']['num_planes']} planes | " for r in reports]
    lines.append("| the job | " + " | ".join(sizes) + "|")
    for n in stages:
        cells = []
        for r in reports:
            s = r["stages_s"].get(n)
            cells += ["", ""] if s is None else [f"{s:.2f}", f"{100 * s / r['total_s']:.1f} %"]
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    lines.append("| **total** | " + " | ".join(f"**{r['total_s']:.1f}** | " for r in reports) + "|")
    steps = [", ".join(f"{k} {v:.1f}" for k, v in r["median_step_ms"].items()) for r in reports]
    lines.append("| median ms per step | " + " | ".join(f"{s} | " for s in steps) + "|")
    lines.append("| later render, ms | " + " | ".join(f"{r['render_ms_median']:.1f} | " for r in reports) + "|")
    return "\n".join(lines) + "\n"


def update_md(md: Path, report_paths: list[str]) -> None:
    reports = [json.loads(Path(p).read_text()) for p in report_paths]
    text = md.read_text()
    start, end = "<!-- profile-table -->\n", "<!-- /profile-table -->"
    a, b = text.index(start) + len(start), text.index(end)
    md.write_text(text[:a] + side_by_side(reports) + text[b:])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--update-md", metavar="MD", help="rewrite MD's profile table from the reports given")
    ap.add_argument("reports", nargs="*", help="with --update-md: the reports, one column pair each")
    ap.add_argument("--data", help="an LLFF scene folder (images_8, poses_bounds.npy)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--set", action="append", default=[], help="a config override, as in `cmc train`")
    ap.add_argument("--renders", type=int, default=10)
    ap.add_argument(
        "--preview-at",
        type=float,
        default=0.0,
        help="share of the steps after which a preview is baked (the service's default: 0)",
    )
    ap.add_argument("--out")
    args = ap.parse_args()
    if args.update_md:
        update_md(Path(args.update_md), args.reports)
        return
    if not (args.data and args.out):
        ap.error("--data and --out are needed to profile a job")
    device = torch.device(args.device)

    def sync() -> None:
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    spent: dict[str, float] = defaultdict(float)
    running: list[str] = []  # the timed call in progress: a timed call inside it counts as its time

    def timed(name: str, fn: Any) -> Any:
        def wrapper(*a: Any, **kw: Any) -> Any:
            if running:
                return fn(*a, **kw)
            running.append(name)
            sync()
            t = time.perf_counter()
            try:
                out = fn(*a, **kw)
                sync()
            finally:
                running.pop()
            spent[name] += time.perf_counter() - t
            return out

        return wrapper

    cfg = with_settings(preset_config(args.preset), args.set)
    t = time.perf_counter()
    split = load_llff(Path(args.data))
    spent["load photos"] = time.perf_counter() - t

    cmc.method.model.sweep_statistics = timed(
        "model build: sweeps placing the planes", cmc.method.model.sweep_statistics
    )
    cmc.method.model.sweep_probabilities = timed(
        "model build: sweeps setting alpha", cmc.method.model.sweep_probabilities
    )
    sync()
    t = time.perf_counter()
    trainer = Trainer(split.train, cfg, device)
    sync()
    build = time.perf_counter() - t
    spent["model build: rest"] = build - sum(v for k, v in spent.items() if k.startswith("model build"))

    test = split.test
    scores: dict[str, float] = {}

    def bake_and_score(name: str, folder: Path, scale: float = 1.0) -> None:
        """Bake into ``folder`` at texel ``scale`` (timed as ``name``), then the baked renders' mean
        PSNR on the test views."""
        t = time.perf_counter()
        bake(trainer.model, folder, scale=scale)
        sync()
        spent[name] = time.perf_counter() - t
        baked = BakedScene.load(folder, device)
        preds = [baked.render(test.cameras.K[k], test.cameras.world_from_cam[k]).rgb for k in range(len(test))]
        scores[name] = round(float(statistics.mean(psnr(p, test.images[k]) for k, p in enumerate(preds))), 3)

    tmp = Path(tempfile.mkdtemp())
    per_step: dict[str, list[float]] = defaultdict(list)
    first_full = int(cfg.loss.recon_only_fraction * cfg.steps)
    preview_step = math.ceil(args.preview_at * cfg.steps)
    for step in range(cfg.steps):
        if step == preview_step:
            bake_and_score("preview bake", tmp / "preview", PREVIEW_TEXEL_SCALE)
        phase = "reconstruction only" if step < first_full else "all terms"
        for g in trainer.optimizer.param_groups:
            g["lr"] = lr_at(cfg, step)
        trainer.optimizer.zero_grad(set_to_none=True)
        sync()
        t0 = time.perf_counter()
        losses = trainer.compute_losses(step)
        sync()
        t1 = time.perf_counter()
        losses.total.backward()
        sync()
        t2 = time.perf_counter()
        trainer.optimizer.step()
        sync()
        t3 = time.perf_counter()
        trainer.step = step + 1
        for part, dt in (("forward", t1 - t0), ("backward", t2 - t1), ("optimizer", t3 - t2)):
            spent[f"train ({phase}): {part}"] += dt
            per_step[f"{phase}: {part}"].append(dt)

    bake_and_score("bake", tmp / "baked")
    t = time.perf_counter()
    baked = BakedScene.load(tmp / "baked", device)
    sync()
    spent["load baked scene"] = time.perf_counter() - t
    render = timed("first render", baked.render)
    render(test.cameras.K[0], test.cameras.world_from_cam[0])
    times = []
    for k in range(args.renders):
        sync()
        t = time.perf_counter()
        baked.render(test.cameras.K[k % len(test)], test.cameras.world_from_cam[k % len(test)])
        sync()
        times.append(time.perf_counter() - t)
    shutil.rmtree(tmp)

    total = sum(spent.values())
    rows = [(name, s, s / total) for name, s in spent.items()]
    table = "| stage | s | share |\n|---|---|---|\n"
    table += "".join(f"| {n} | {s:.2f} | {100 * f:.1f} % |\n" for n, s, f in rows)
    table += f"| **total** | **{total:.1f}** | |\n"
    medians = {k: statistics.median(v) * 1000 for k, v in per_step.items()}
    table += "\nMedian ms per step: " + ", ".join(f"{k} {v:.1f}" for k, v in medians.items())
    table += f"; a later render (median of {args.renders}): {statistics.median(times) * 1000:.1f} ms.\n"
    table += f"Test-view PSNR of the preview (step {preview_step}): {scores['preview bake']:.2f} dB, "
    table += f"of the final bake: {scores['bake']:.2f} dB.\n"
    print(table)
    report = {
        **report_header(cfg, device),
        "scene": Path(args.data).name,
        "settings": args.set,
        "stages_s": {n: round(s, 3) for n, s, _ in rows},
        "total_s": round(total, 2),
        "median_step_ms": {k: round(v, 2) for k, v in medians.items()},
        "render_ms_median": round(statistics.median(times) * 1000, 2),
        "preview_step": preview_step,
        "test_psnr": scores,
        "table": table,
    }
    Path(args.out).write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
