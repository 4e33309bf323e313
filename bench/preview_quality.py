"""How good a preview is after how much training: the `fast` model baked at a few early steps and
scored on the test views (issue 39's preview target: fern's test views at >= 20 dB PSNR within
30 s of the upload).

Step 0 is the model as the plane sweep starts it (a job with ``CMC_PREVIEW_AT=0`` publishes
that). Each row gives the step, the seconds from the start of the model build to the end of that
bake (training time included, the bakes and scoring before it not), and the baked renders' mean
PSNR / SSIM on the test views. Pose estimation, before the model build in a job, is not in it
(bench/reports/history/sift_octave.md: 2.45 s on fern's phone photos, median of 3).

Usage (repository root, nothing else running):
    PYTHONPATH=. python bench/preview_quality.py --data ../shared/datasets/llff/fern \
        --steps-at 0,10,20,45,90 --out bench/reports/current/preview_quality_fern.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

from cmc.config import preset_config
from cmc.data.datasets import load_llff
from cmc.eval.bench import report_header
from cmc.eval.metrics import psnr, ssim
from cmc.method.training import Trainer
from cmc.serving.baking import BakedScene, bake


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="one LLFF scene folder")
    ap.add_argument("--steps-at", default="0,10,20,45,90", help="comma-separated steps to bake a preview at")
    ap.add_argument(
        "--scale", type=float, default=1.0, help="texel resolution of the preview bakes (cmc.serving.baking.bake)"
    )
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    torch.set_num_threads(2)
    cfg = preset_config("fast")
    split = load_llff(Path(args.data))
    at = sorted(int(s) for s in args.steps_at.split(","))
    t0 = time.perf_counter()
    trainer = Trainer(split.train, cfg, "cpu")
    build_s = time.perf_counter() - t0
    rows: list[dict[str, Any]] = []
    train_s = 0.0
    with tempfile.TemporaryDirectory() as tmp:
        for step in at:
            t = time.perf_counter()
            while trainer.step < step:
                trainer.train_step()
            train_s += time.perf_counter() - t
            t = time.perf_counter()
            bake(trainer.model, Path(tmp) / f"step{step}", scale=args.scale)
            bake_s = time.perf_counter() - t
            baked = BakedScene.load(Path(tmp) / f"step{step}")
            test = split.test
            preds = [baked.render(test.cameras.K[k], test.cameras.world_from_cam[k]).rgb for k in range(len(test))]
            row = {
                "step": step,
                "seconds_from_build_start": round(build_s + train_s + bake_s, 1),  # earlier bakes not counted
                "bake_s": round(bake_s, 1),
                "psnr": round(statistics.mean(psnr(p, test.images[k]) for k, p in enumerate(preds)), 3),
                "ssim": round(statistics.mean(ssim(p, test.images[k]) for k, p in enumerate(preds)), 4),
            }
            rows.append(row)
            print(json.dumps(row), flush=True)
    report = {
        **report_header(cfg, torch.device("cpu")),
        "scene": Path(args.data).name,
        "scale": args.scale,
        "build_s": round(build_s, 1),
    }
    report["previews"] = rows
    Path(args.out).write_text(json.dumps(report, indent=1) + "\n")
    lines = ["| step | s from the model build's start | PSNR | SSIM |", "|---|---|---|---|"]
    lines += [f"| {r['step']} | {r['seconds_from_build_start']} | {r['psnr']:.2f} | {r['ssim']:.3f} |" for r in rows]
    Path(args.out).with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
