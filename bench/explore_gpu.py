"""Many `fast` variants at once on a lent GPU, chosen on views that are neither train nor test.

Fern's RegNeRF split trains on images 1, 10, 19 and tests on 0, 8, 16; the other 14 images are
*validation* views: a setting is judged on them (and on the synthetic set, which is ours), never
on the test views. The test views are scored too, only to see afterwards whether validation
predicted them; a variant is adopted only after the CPU benchmark (`cmc bench`) confirms it.

Usage (repository root; data as in bench/gpu_run.sh):
    PYTHONPATH=. python bench/explore_gpu.py VARIANTS.json OUT_DIR --data .gpudata/llff/fern \
        --workers 7 --seconds 330 [--grace 120] [--synthetic posts,cards] [--device cuda] [--steps N]
VARIANTS.json maps a name to a list of `--set` style settings (``[]`` is the preset itself).
Every fern run comes first, then the synthetic scenes; a task not started before the deadline is
skipped, and one still running ``--grace`` seconds after it is dropped. One JSON line per
(variant, scene), with device, commit and date, is appended to OUT_DIR/explore.jsonl as it ends.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np


def _run(task: tuple[str, list[str], str, dict[str, Any]]) -> dict[str, Any]:
    import torch

    from cmc.baking import BakedScene, bake
    from cmc.bench import report_header
    from cmc.config import preset_config, with_settings
    from cmc.datasets import load_llff, wide_baseline_split
    from cmc.metrics import psnr, ssim
    from cmc.training import Trainer

    name, settings, scene, opts = task
    torch.set_num_threads(2)
    device = torch.device(opts["device"])
    cfg = with_settings(preset_config("fast"), settings)
    if opts.get("steps"):
        cfg = with_settings(cfg, [f"steps={opts['steps']}"])
    if scene == "fern":
        split = load_llff(opts["data"])
        train, scored, kinds = split.train, [split.val, split.test], ["val", "test"]
    else:
        split = wide_baseline_split(scene)
        train, scored, kinds = split.train, [split.test], ["synthetic"]
    t0 = time.perf_counter()
    try:
        trainer = Trainer(train, cfg, device)
        trainer.fit()
    except Exception as e:  # a variant that cannot train is a result, not a crash of the sweep
        return {"variant": name, "scene": scene, "error": repr(e)}
    train_s = time.perf_counter() - t0
    header = report_header(cfg, device)
    rec: dict[str, Any] = {
        "variant": name,
        "settings": settings,
        "scene": scene,
        "train_s": round(train_s, 1),
        **{k: header[k] for k in ("device", "git_commit", "date")},
    }
    with tempfile.TemporaryDirectory() as tmp:
        baked = BakedScene.load(bake(trainer.model, Path(tmp) / "baked"), device)
        for kind, views in zip(kinds, scored, strict=True):
            per_view = []
            for k, view_name in enumerate(views.names):
                pred = baked.render(views.cameras.K[k], views.cameras.world_from_cam[k]).rgb.cpu().numpy()
                per_view.append(
                    {"name": view_name, "psnr": psnr(pred, views.images[k]), "ssim": ssim(pred, views.images[k])}
                )
            if kind == "synthetic":
                for v, k in zip(per_view, split.test_kinds, strict=True):
                    v["kind"] = k
                for k in sorted(set(split.test_kinds)):
                    sel = [v for v in per_view if v["kind"] == k]
                    rec[k] = {m: round(float(np.mean([v[m] for v in sel])), 4) for m in ("psnr", "ssim")}
            else:
                rec[kind] = {m: round(float(np.mean([v[m] for v in per_view])), 4) for m in ("psnr", "ssim")}
                rec[kind + "_views"] = {v["name"]: round(v["ssim"], 4) for v in per_view}
    return rec


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("variants")
    ap.add_argument("out")
    ap.add_argument("--data", default="../shared/datasets/llff/fern")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seconds", type=float, default=500)
    ap.add_argument("--synthetic", default="")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--steps", type=int, default=0)
    ap.add_argument(
        "--grace", type=float, default=120, help="seconds a task started before the deadline may run past it"
    )
    args = ap.parse_args()
    deadline = time.time() + args.seconds
    variants: dict[str, list[str]] = json.loads(Path(args.variants).read_text())
    opts = {"device": args.device, "data": args.data, "steps": args.steps, "deadline": deadline}
    scenes = ["fern", *[s for s in args.synthetic.split(",") if s]]
    tasks = [(n, s, scene, opts) for scene in scenes for n, s in variants.items()]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    ctx = mp.get_context("spawn")
    with ctx.Pool(args.workers, maxtasksperchild=1) as pool, (out / "explore.jsonl").open("a") as f:
        results = pool.imap_unordered(_gate, tasks)
        for _ in tasks:
            try:
                rec = results.next(timeout=max(1.0, deadline + args.grace - time.time()))
            except (mp.TimeoutError, StopIteration):
                break
            if rec is not None:
                f.write(json.dumps(rec) + "\n")
                f.flush()
                print(json.dumps({k: v for k, v in rec.items() if not k.endswith("_views")}), flush=True)
        pool.terminate()


def _gate(task: tuple[str, list[str], str, dict[str, Any]]) -> dict[str, Any] | None:
    """Run ``task`` unless the sweep's deadline has passed."""
    return None if time.time() > task[3]["deadline"] else _run(task)


if __name__ == "__main__":
    main()
