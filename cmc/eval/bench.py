"""The LLFF few-shot benchmark (the paper's protocol, RegNeRF's split) and its report.

For each scene: train on the 3 evenly chosen views of ``images_8``, bake, render every held-out
view (index % 8 == 0) with the baked renderer, and score PSNR / SSIM / LPIPS (alex, vgg).
"""

from __future__ import annotations

import datetime as dt
import json
import os
import platform
import resource
import statistics
import subprocess
import tempfile
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from cmc.config import TrainConfig
from cmc.data.datasets import Scene, load_llff, save_image, wide_baseline_split
from cmc.eval.diagnostics import contact_sheet, depth_error_map, depth_preview, error_map
from cmc.eval.metrics import image_metrics, psnr
from cmc.method.training import Progress, Trainer
from cmc.serving.baking import BakedRender, BakedScene, bake

METRICS = ("psnr", "ssim", "lpips_alex", "lpips_vgg")
ScoredViews = Literal["test", "val"]


def git_commit() -> str:
    """``$CMC_GIT_COMMIT`` where set (a copy of the tree on another machine, whose git
    repository, if any, may be stale), else the repository's HEAD commit (with '+dirty' for
    uncommitted changes), else 'unknown'."""
    if os.environ.get("CMC_GIT_COMMIT"):
        return os.environ["CMC_GIT_COMMIT"]
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
    views: ScoredViews = "test",
    near_scale: float = 1.0,
) -> dict[str, Any]:
    """Train, bake and evaluate one LLFF scene; returns its record. ``views``: score the test
    views (the protocol's) or the validation views (those that may choose settings);
    ``near_scale``: train with the near bound times this (< 1: looser bounds)."""
    split = load_llff(scene_dir)
    train = split.train.with_near_scaled(near_scale)
    trainer, train_s = _train(train, cfg, device, on_progress)
    scored, ids = (split.test, split.test_ids) if views == "test" else (split.val, split.val_ids)
    if scored is None:
        raise ValueError(f"{scene_dir.name} has no {views} views")
    record: dict[str, Any] = {"scene": scene_dir.name, "train_views": split.train_ids, f"{views}_views": ids}
    names = [f"{views}_{i:03d}" for i in ids]
    with tempfile.TemporaryDirectory() as tmp:
        for merge in (1, 2):  # all planes, then adjacent planes merged in pairs (faster renders)
            out_dir = (save_dir or Path(tmp)) / ("baked" if merge == 1 else f"baked_merge{merge}")
            baked = BakedScene.load(bake(trainer.model, out_dir, merge=merge), device)
            per_view, times = score_views(
                baked, scored, names, lpips_dir, render_repeats, save_dir if merge == 1 else None
            )
            for v, i in zip(per_view, ids, strict=True):
                v["view"] = i
            scores = {**_means(per_view), "render_ms_median": 1000 * statistics.median(times)}
            if merge == 1:
                record.update(scores, num_planes_baked=len(baked.frames[0].depths), views=per_view)
            else:
                record[f"merge{merge}"] = scores
    record["train_seconds"] = train_s
    return record


def _train(
    scene: Scene, cfg: TrainConfig, device: torch.device, on_progress: Callable[[Progress], None] | None
) -> tuple[Trainer, float]:
    """Train on ``scene``; the seconds include building the model (plane sweep)."""
    t0 = time.perf_counter()
    trainer = Trainer(scene, cfg, device)
    trainer.fit(on_progress=on_progress)
    if device.type == "cuda":
        torch.cuda.synchronize()
    return trainer, time.perf_counter() - t0


def _means(per_view: list[dict[str, Any]]) -> dict[str, float]:
    keys = [k for k in (*METRICS, "depth_rel_error") if k in per_view[0]]
    return {k: float(np.mean([v[k] for v in per_view])) for k in keys}


def score_views(
    baked: BakedScene,
    test: Scene,
    names: list[str],
    lpips_dir: str | None,
    repeats: int,
    save_dir: Path | None,
) -> tuple[list[dict[str, Any]], list[float]]:
    """Render every test view ``repeats`` times with the baked renderer and score it.

    Returns one record per view (PSNR / SSIM / LPIPS, and ``depth_rel_error``, the median of
    |z - z_gt| / z_gt over pixels, where the test scene has depth) and all render times (s).
    With ``save_dir``: ``<name>.png`` (the render) and ``<name>_sheet.png``
    (:func:`diagnostic_sheet`) per view.
    """
    per_view, times = [], []
    for k, name in enumerate(names):
        K, pose = test.cameras.K[k], test.cameras.world_from_cam[k]
        for _ in range(repeats):
            t = time.perf_counter()
            out = baked.render(K, pose)  # NumPy: the device has finished
            times.append(time.perf_counter() - t)
        pred = out.rgb
        rec: dict[str, Any] = {"name": name, **image_metrics(pred, test.images[k], lpips_dir)}
        gt_depth = None if test.depths is None else test.depths[k]
        if gt_depth is not None:
            rec["depth_rel_error"] = float(np.median(np.abs(out.depth - gt_depth) / gt_depth))
        per_view.append(rec)
        if save_dir:
            save_image(save_dir / f"{name}.png", pred)
            sheet = diagnostic_sheet(baked, K, pose, test.images[k], gt_depth, blended=out)
            save_image(save_dir / f"{name}_sheet.png", sheet)
    return per_view, times


def diagnostic_sheet(
    baked: BakedScene,
    K: np.ndarray,
    pose: np.ndarray,
    gt: np.ndarray,
    gt_depth: np.ndarray | None = None,
    blended: BakedRender | None = None,
) -> np.ndarray:
    """One picture of a test view: where its error lives and which MPI it comes from.

    Row 1: ground truth, the blended render (``blended`` when the caller already has it), its
    colour error (white = 0.25 mean abs error), and its depth error where ``gt_depth`` is given
    (white = 25 % relative). Row 2: each MPI's own render with its PSNR. Row 3: each MPI's
    depth, the blended depth, the true depth.
    """
    near, far = baked.near, baked.far
    blended = blended or baked.render(K, pose)
    rgb, depth = blended.rgb, blended.depth
    row1 = [("truth", gt), (f"blend {psnr(rgb, gt):.2f} dB", rgb), ("|error|", error_map(rgb, gt))]
    if gt_depth is not None:
        row1.append(("depth error", depth_error_map(depth, gt_depth)))
    row2, row3 = [], []
    for i in range(len(baked.fields)):
        o = baked.render(K, pose, mpi_index=i)
        r = o.rgb
        row2.append((f"MPI {i} {psnr(r, gt):.2f} dB", r))
        row3.append((f"MPI {i} depth", depth_preview(o.depth, near, far)))
    row3.append(("blend depth", depth_preview(depth, near, far)))
    if gt_depth is not None:
        row3.append(("true depth", depth_preview(gt_depth, near, far)))
    return contact_sheet([row1, row2, row3])


def run_llff_bench(
    data_dir: Path,
    scenes: list[str],
    cfg: TrainConfig,
    device: torch.device,
    lpips_dir: str | None,
    save_dir: Path | None = None,
    on_progress: Callable[[str, Progress], None] | None = None,
    views: ScoredViews = "test",
    near_scale: float = 1.0,
) -> dict[str, Any]:
    """Benchmark several scenes (:func:`bench_scene`); returns the full report (per scene and mean)."""
    records = []
    for name in scenes:
        sd = save_dir / name if save_dir else None
        if sd:
            sd.mkdir(parents=True, exist_ok=True)
        hook = (lambda p, n=name: on_progress(n, p)) if on_progress else None
        records.append(
            bench_scene(
                data_dir / name,
                cfg,
                device,
                lpips_dir,
                save_dir=sd,
                on_progress=hook,
                views=views,
                near_scale=near_scale,
            )
        )
    keys = (*METRICS, "train_seconds", "render_ms_median")
    return {
        "protocol": "LLFF images_8, test = index % 8 == 0, 3 train views evenly from the rest (RegNeRF)",
        "scored_views": views,
        **({"near_scale": near_scale} if near_scale != 1 else {}),
        **report_header(cfg, device),
        "scenes": records,
        "mean": {k: float(np.mean([r[k] for r in records])) for k in keys},
    }


def machine_info(**extra: Any) -> dict[str, Any]:
    """The machine a benchmark report was measured on: CPU, cores, Python, ``OMP_NUM_THREADS``,
    and any ``extra`` fields the script adds (its memory, the load before it ran)."""
    return {
        "cpu": platform.processor() or platform.machine(),
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
        **extra,
    }


def report_header(cfg: TrainConfig, device: torch.device) -> dict[str, Any]:
    """What every benchmark report starts with: preset, full configuration, device, commit, date,
    peak memory."""
    return {
        "preset": cfg.preset,
        "config": cfg.to_dict(),
        "device": torch.cuda.get_device_name(device)
        if device.type == "cuda"
        else f"cpu ({platform.processor() or platform.machine()}, {torch.get_num_threads()} threads)",
        "git_commit": git_commit(),
        "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d"),
        "peak_memory_mb": peak_memory_mb(device),
    }


SYNTHETIC_KINDS = ("halfway", "near", "beyond")


def run_synthetic_bench(
    scenes: list[str],
    cfg: TrainConfig,
    device: torch.device,
    lpips_dir: str | None,
    save_dir: Path | None = None,
    on_progress: Callable[[str, Progress], None] | None = None,
    render_repeats: int = 3,
    input_gains: list[float] | None = None,
    near_scale: float = 1.0,
) -> dict[str, Any]:
    """The wide-baseline synthetic set (:func:`cmc.data.datasets.wide_baseline_split`): train on each
    scene's three inputs, bake, and score the halfway, near and beyond test views separately
    (colour metrics and the median relative depth error against the exact depth).

    ``input_gains``: a factor on each input photo's colours (clipped to [0, 1]), as differing
    exposures of phone photos; the test views keep the scene's own."""
    records = []
    for name in scenes:
        split = wide_baseline_split(name)
        split = replace(split, train=split.train.with_near_scaled(near_scale))
        if input_gains is not None:
            split = replace(split, train=split.train.with_gains(input_gains))
        hook = (lambda p, n=name: on_progress(n, p)) if on_progress else None
        trainer, train_s = _train(split.train, cfg, device, hook)
        sd = save_dir / name if save_dir else None
        with tempfile.TemporaryDirectory() as tmp:
            baked = BakedScene.load(bake(trainer.model, (sd or Path(tmp)) / "baked"), device)
            per_view, times = score_views(baked, split.test, split.test.names, lpips_dir, render_repeats, sd)
        for v, kind in zip(per_view, split.test_kinds, strict=True):
            v["kind"] = kind
        rec: dict[str, Any] = {"scene": name, "train_seconds": train_s}
        rec["render_ms_median"] = 1000 * statistics.median(times)
        for kind in SYNTHETIC_KINDS:
            rec[kind] = _means([v for v in per_view if v["kind"] == kind])
        rec["views"] = per_view
        records.append(rec)
    mean = {
        kind: {k: float(np.mean([r[kind][k] for r in records])) for k in records[0][kind]} for kind in SYNTHETIC_KINDS
    }
    for k in ("train_seconds", "render_ms_median"):
        mean[k] = float(np.mean([r[k] for r in records]))
    return {
        "protocol": "wide-baseline synthetic scenes (cmc.data.datasets.wide_baseline_split), 252x189, 3 input views; "
        "test views halfway between two inputs, near each input and beyond each input",
        **({"input_gains": input_gains} if input_gains is not None else {}),
        **({"near_scale": near_scale} if near_scale != 1 else {}),
        **report_header(cfg, device),
        "scenes": records,
        "mean": mean,
    }


def _markdown(columns: list[str], rows: list[list[str]]) -> str:
    """A markdown table of string cells."""
    head = "| " + " | ".join(columns) + " |\n|" + "---|" * len(columns) + "\n"
    return head + "".join("| " + " | ".join(row) + " |\n" for row in rows)


def _numbers(m: dict[str, Any], keys: tuple[str, ...]) -> list[str]:
    """Cells of metrics ``keys`` of ``m``: PSNR with 2 decimals, seconds and milliseconds with none,
    the rest with 3."""
    digits = {"psnr": 2, "train_seconds": 0, "render_ms_median": 0}
    return [f"{m[k]:.{digits.get(k, 3)}f}" for k in keys]


def synthetic_markdown_table(report: dict[str, Any]) -> str:
    """One row per scene and kind of test view, then the means."""
    columns = ["scene", "views", "PSNR", "SSIM", "LPIPS-alex", "LPIPS-vgg", "depth rel. error", "train s", "render ms"]
    rows = []
    for r in [*report["scenes"], {"scene": "**mean**", **report["mean"]}]:
        for kind in SYNTHETIC_KINDS:
            cells = _numbers(r[kind], (*METRICS, "depth_rel_error"))
            rows.append([r["scene"], kind, *cells, *_numbers(r, ("train_seconds", "render_ms_median"))])
    return _markdown(columns, rows)


def markdown_table(report: dict[str, Any]) -> str:
    """The report as a markdown table (one row per scene, then the mean)."""
    columns = ["scene", "PSNR", "SSIM", "LPIPS-alex", "LPIPS-vgg", "train s", "render ms"]
    columns.append("merged x2: PSNR / SSIM / LPIPS-alex / render ms")
    keys = (*METRICS, "train_seconds", "render_ms_median")
    rows = []
    for r in report["scenes"]:
        merged = " / ".join(_numbers(r["merge2"], ("psnr", "ssim", "lpips_alex", "render_ms_median")))
        rows.append([r["scene"], *_numbers(r, keys), merged])
    rows.append(["**mean**", *_numbers(report["mean"], keys), ""])
    return _markdown(columns, rows)


def write_report(report: dict[str, Any], out: Path) -> None:
    """The report as JSON at ``out`` and its markdown table beside it (.md)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=1))
    table = synthetic_markdown_table if "halfway" in report["mean"] else markdown_table
    out.with_suffix(".md").write_text(table(report))
