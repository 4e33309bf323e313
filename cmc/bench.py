"""The LLFF few-shot benchmark (the paper's protocol, RegNeRF's split) and its report.

For each scene: train on the 3 evenly chosen views of ``images_8``, bake, render every held-out
view (index % 8 == 0) with the baked renderer, and score PSNR / SSIM / LPIPS (alex, vgg).
"""

from __future__ import annotations

import datetime as dt
import json
import platform
import resource
import statistics
import subprocess
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from cmc.baking import BakedScene, bake
from cmc.config import TrainConfig
from cmc.datasets import load_llff, save_image
from cmc.metrics import image_metrics
from cmc.training import Progress, Trainer

METRICS = ("psnr", "ssim", "lpips_alex", "lpips_vgg")


def git_commit() -> str:
    """The repository's HEAD commit (with '+dirty' for uncommitted changes), or 'unknown'."""
    here = Path(__file__).resolve().parent
    try:
        sha = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=here, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=here,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        return sha + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def peak_memory_mb(device: torch.device) -> float:
    """Peak resident memory of this process (CPU) or peak allocated GPU memory, in MiB."""
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**20
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def bench_scene(
    scene_dir: Path,
    cfg: TrainConfig,
    device: torch.device,
    lpips_dir: str | None,
    render_repeats: int = 5,
    save_dir: Path | None = None,
    on_progress: Callable[[Progress], None] | None = None,
) -> dict[str, Any]:
    """Train, bake and evaluate one LLFF scene; returns its record."""
    split = load_llff(scene_dir)
    t0 = time.perf_counter()  # training time includes building the model (plane sweep)
    trainer = Trainer(split.train, cfg, device)
    trainer.fit(on_progress=on_progress)
    if device.type == "cuda":
        torch.cuda.synchronize()
    train_s = time.perf_counter() - t0
    record: dict[str, Any] = {"scene": scene_dir.name, "train_views": split.train_ids, "test_views": split.test_ids}
    with tempfile.TemporaryDirectory() as tmp:
        for merge in (1, 2):  # all planes, then adjacent planes merged in pairs (faster renders)
            out_dir = (save_dir or Path(tmp)) / ("baked" if merge == 1 else f"baked_merge{merge}")
            baked = BakedScene.load(bake(trainer.model, out_dir, merge=merge), device)
            scores = _score_baked(baked, split, device, lpips_dir, render_repeats, save_dir if merge == 1 else None)
            if merge == 1:
                record.update(scores)
            else:
                record[f"merge{merge}"] = {k: scores[k] for k in (*METRICS, "render_ms_median")}
    record["train_seconds"] = train_s
    return record


def _score_baked(
    baked: BakedScene, split, device: torch.device, lpips_dir: str | None, repeats: int, save_dir: Path | None
) -> dict[str, Any]:
    """Render every held-out view ``repeats`` times; mean metrics and the median render time."""
    per_view, times = [], []
    test = split.test
    for k in range(len(test)):
        K, pose = test.cameras.K[k], test.cameras.world_from_cam[k]
        for _ in range(repeats):
            t = time.perf_counter()
            out = baked.render(K, pose)
            if device.type == "cuda":
                torch.cuda.synchronize()
            times.append(time.perf_counter() - t)
        pred = out.rgb.cpu().numpy()
        per_view.append({"view": split.test_ids[k], **image_metrics(pred, test.images[k], lpips_dir)})
        if save_dir:
            save_image(save_dir / f"test_{split.test_ids[k]:03d}.png", pred)
    return {
        **{k: float(np.mean([v[k] for v in per_view])) for k in METRICS},
        "render_ms_median": 1000 * statistics.median(times),
        "num_planes_baked": len(baked.frames[0].depths),
        "views": per_view,
    }


def run_llff_bench(
    data_dir: Path,
    scenes: list[str],
    cfg: TrainConfig,
    device: torch.device,
    lpips_dir: str | None,
    save_dir: Path | None = None,
    on_progress: Callable[[str, Progress], None] | None = None,
) -> dict[str, Any]:
    """Benchmark several scenes; returns the full report (per scene and mean)."""
    records = []
    for name in scenes:
        sd = save_dir / name if save_dir else None
        if sd:
            sd.mkdir(parents=True, exist_ok=True)
        hook = (lambda p, n=name: on_progress(n, p)) if on_progress else None
        records.append(bench_scene(data_dir / name, cfg, device, lpips_dir, save_dir=sd, on_progress=hook))
    keys = (*METRICS, "train_seconds", "render_ms_median")
    return {
        "protocol": "LLFF images_8, test = index % 8 == 0, 3 train views evenly from the rest (RegNeRF)",
        "preset": cfg.preset,
        "config": cfg.to_dict(),
        "device": torch.cuda.get_device_name(device)
        if device.type == "cuda"
        else f"cpu ({platform.processor() or platform.machine()}, {torch.get_num_threads()} threads)",
        "git_commit": git_commit(),
        "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d"),
        "peak_memory_mb": peak_memory_mb(device),
        "scenes": records,
        "mean": {k: float(np.mean([r[k] for r in records])) for k in keys},
    }


def markdown_table(report: dict[str, Any]) -> str:
    """The report as a markdown table (one row per scene, then the mean)."""
    head = (
        "| scene | PSNR | SSIM | LPIPS-alex | LPIPS-vgg | train s | render ms "
        "| merged x2: PSNR / SSIM / LPIPS-alex / render ms |\n|---|---|---|---|---|---|---|---|\n"
    )
    row = "| {} | {:.2f} | {:.3f} | {:.3f} | {:.3f} | {:.0f} | {:.0f} | {} |\n"
    rows = []
    for r in report["scenes"]:
        m2 = r["merge2"]
        merged = f"{m2['psnr']:.2f} / {m2['ssim']:.3f} / {m2['lpips_alex']:.3f} / {m2['render_ms_median']:.0f}"
        rows.append(row.format(r["scene"], *(r[k] for k in (*METRICS, "train_seconds", "render_ms_median")), merged))
    m = report["mean"]
    rows.append(row.format("**mean**", *(m[k] for k in (*METRICS, "train_seconds", "render_ms_median")), ""))
    return head + "".join(rows)


def write_report(report: dict[str, Any], out: Path) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=1))
    out.with_suffix(".md").write_text(markdown_table(report))
