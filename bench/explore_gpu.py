"""Many `fast` variants at once on a lent GPU, chosen on views that are neither train nor test.

Each real LLFF scene's RegNeRF split (``cmc.data.datasets.load_llff``) trains on three images and tests
on every 8th; the rest are *validation* views: a setting is judged on them (and on the synthetic
set, which is ours), never on the test views. The test views are scored too, only to see
afterwards whether validation predicted them; a variant is adopted only after the CPU benchmark
(`cmc bench`) confirms it. Validation views are also scored with the MPIs blended by inverse
distance to the power ``--blend-powers`` (the renderer's is 2; ``cmc.geometry.planes.blend_weights``),
without retraining.

Usage (repository root; data as in bench/gpu_run.sh):
    PYTHONPATH=. python bench/explore_gpu.py VARIANTS.json OUT_DIR --data .gpudata/llff \
        --scenes fern,room,trex --workers 7 --seconds 330 [--grace 120] [--synthetic posts,cards] \
        [--device cuda] [--steps N] [--lpips] [--blend-powers 2,6]
VARIANTS.json maps a name to a list of `--set` style settings (``[]`` is the preset itself).
Tasks run variant by variant (every scene of the first variant, then the next), so a deadline
cuts whole variants; a task not started before the deadline is skipped, and one still running
``--grace`` seconds after it is dropped. One JSON line per (variant, scene), with device, commit
and date, is appended to OUT_DIR/explore.jsonl as it ends. ``--lpips``: LPIPS-vgg too (weights
from ``$CMC_LPIPS_DIR``).
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

    import cmc.mpi.rendering
    from cmc.config import preset_config, with_settings
    from cmc.data.datasets import WIDE_SCENES, load_llff, wide_baseline_split
    from cmc.eval.bench import report_header
    from cmc.eval.metrics import LPIPS, psnr, ssim
    from cmc.method.training import Trainer
    from cmc.serving.baking import BakedScene, bake

    name, settings, scene, opts = task
    torch.set_num_threads(2)
    device = torch.device(opts["device"])
    cfg = with_settings(preset_config("fast"), settings)
    if opts.get("steps"):
        cfg = with_settings(cfg, [f"steps={opts['steps']}"])
    if scene in WIDE_SCENES:
        split = wide_baseline_split(scene)
        train, scored, kinds = split.train, [split.test], ["synthetic"]
    else:
        split = load_llff(Path(opts["data"]) / scene)
        train, scored, kinds = split.train, [split.val, split.test], ["val", "test"]
    lpips = LPIPS("vgg", device=device) if opts.get("lpips") else None
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
    blend_weights = cmc.mpi.rendering.blend_weights

    def score(baked: BakedScene, views: Any) -> list[dict[str, Any]]:
        per_view = []
        for k, view_name in enumerate(views.names):
            pred = baked.render(views.cameras.K[k], views.cameras.world_from_cam[k]).rgb
            v = {"name": view_name, "psnr": psnr(pred, views.images[k]), "ssim": ssim(pred, views.images[k])}
            if lpips is not None:
                v["lpips_vgg"] = lpips(pred, views.images[k])
            per_view.append(v)
        return per_view

    def mean(per_view: list[dict[str, Any]]) -> dict[str, float]:
        return {m: round(float(np.mean([v[m] for v in per_view])), 4) for m in per_view[0] if m != "name"}

    with tempfile.TemporaryDirectory() as tmp:
        baked = BakedScene.load(bake(trainer.model, Path(tmp) / "baked"), device)
        for kind, views in zip(kinds, scored, strict=True):
            per_view = score(baked, views)
            if kind == "synthetic":
                for v, k in zip(per_view, split.test_kinds, strict=True):
                    v["kind"] = k
                for k in sorted(set(split.test_kinds)):
                    rec[k] = mean([{m: x for m, x in v.items() if m != "kind"} for v in per_view if v["kind"] == k])
                continue
            rec[kind] = mean(per_view)
            rec[kind + "_views"] = {v["name"]: round(v["psnr"], 3) for v in per_view}
            if kind != "val":
                continue
            for power in opts.get("blend_powers", []):
                if power == 2:
                    continue
                cmc.mpi.rendering.blend_weights = _powered(blend_weights, power)
                try:
                    rec[f"val_blend{power:g}"] = mean(score(baked, views))
                finally:
                    cmc.mpi.rendering.blend_weights = blend_weights
    return rec


def _powered(blend_weights: Any, power: float) -> Any:
    """``blend_weights`` with inverse distance to ``power`` instead of squared distance."""

    def weights(ref_centers: Any, target_center: Any, baseline: float) -> Any:
        w = blend_weights(ref_centers, target_center, baseline) ** (power / 2)
        return w / w.sum()

    return weights


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("variants")
    ap.add_argument("out")
    ap.add_argument("--data", default="../shared/datasets/llff", help="folder of LLFF scenes")
    ap.add_argument("--scenes", default="fern", help="real scenes under --data, comma-separated")
    ap.add_argument("--lpips", action="store_true", help="LPIPS-vgg too ($CMC_LPIPS_DIR)")
    ap.add_argument("--blend-powers", default="2", help="inverse-distance powers of the MPI blend scored on val")
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
    opts = {
        "device": args.device,
        "data": args.data,
        "steps": args.steps,
        "deadline": deadline,
        "lpips": args.lpips,
        "blend_powers": [float(p) for p in args.blend_powers.split(",")],
    }
    real = [s for s in args.scenes.split(",") if s]
    synthetic = [s for s in args.synthetic.split(",") if s]
    tasks = [(n, s, scene, opts) for n, s in variants.items() for scene in real]
    tasks += [(n, s, scene, opts) for scene in synthetic for n, s in variants.items()]
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
