"""Score a fern bake at every one of fern's 20 poses, not only the protocol's three test views.

The RegNeRF protocol trains on views 1, 10, 19 and tests on 0, 8, 16. Fern was captured in two
rows (0-9, 10-19), and the three inputs all sit at the left end of the capture: most of the other
poses lie outside the inputs, up to 2.4 input baselines from the nearest one. Scoring every pose
against its distance from the nearest input camera shows how the novel views hold up as the camera
leaves the inputs, on a real scene. Nothing here trains; each ``--baked LABEL=DIR`` is the bake of
a ``cmc bench llff --save-dir DIR0`` run (``DIR0/fast/fern/baked``). These views are for
reporting only: no setting is chosen on them.

Usage (repository root)::

    CMC_LPIPS_DIR=../shared/weights .venv/bin/python bench/fern_every_view.py \\
        --baked previous=/tmp/runs_prev/fast/fern/baked --baked now=/tmp/runs/fast/fern/baked \\
        [--data ../shared/datasets/llff/fern] [--out bench/reports/current/fern_every_view.json]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
from pathlib import Path

import numpy as np
import torch

from cmc.data.datasets import load_llff, regnerf_split
from cmc.eval.bench import git_commit
from cmc.eval.metrics import image_metrics
from cmc.geometry.planes import mean_baseline
from cmc.serving.baking import BakedScene

# Distance bins, in mean input baselines (mean distance between the three input cameras).
BINS = ((0.0, 0.75), (0.75, 1.5), (1.5, float("inf")))


def inside_input_triangle(centres: np.ndarray, train: list[int]) -> np.ndarray:
    """Whether each camera centre ([N, 3]), projected onto the best-fit plane of all centres, lies
    inside the triangle of the three input centres ([N] bool)."""
    flat = centres - centres.mean(0)
    xy = flat @ np.linalg.svd(flat)[2][:2].T
    a, b, c = xy[train]

    def side(p: np.ndarray, q: np.ndarray, r: np.ndarray) -> np.ndarray:
        return (p[:, 0] - r[0]) * (q[1] - r[1]) - (q[0] - r[0]) * (p[:, 1] - r[1])

    s = np.stack([side(xy, a, b), side(xy, b, c), side(xy, c, a)])
    return (s >= 0).all(0) | (s <= 0).all(0)


def distances_to_inputs(centres: np.ndarray, train: list[int]) -> np.ndarray:
    """Distance of each camera centre ([N, 3]) to the nearest input camera, in mean input baselines."""
    inputs = centres[train]
    return np.linalg.norm(centres[:, None] - inputs[None], axis=-1).min(1) / mean_baseline(inputs)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="../shared/datasets/llff/fern")
    ap.add_argument("--baked", action="append", required=True, metavar="LABEL=DIR")
    ap.add_argument("--out", default="bench/reports/current/fern_every_view.json")
    args = ap.parse_args()
    torch.set_num_threads(os.cpu_count() or 1)
    num_images = len(np.load(Path(args.data) / "poses_bounds.npy"))
    train, test = regnerf_split(num_images)
    # Every non-test view as a "training" view: one load holds all the photos.
    every = load_llff(args.data, num_train=num_images - len(test))
    full = {v: (every.train, k) for k, v in enumerate(every.train_ids)} | {
        v: (every.test, k) for k, v in enumerate(test)
    }
    report: dict = {
        "command": "python bench/fern_every_view.py " + " ".join(f"--baked {b}" for b in args.baked),
        "date": datetime.date.today().isoformat(),
        "git_commit": git_commit(),
        "train_views": train,
        "test_views": test,
        "bakes": {},
    }
    centres = np.stack([full[v][0].cameras.world_from_cam[full[v][1]][:3, 3] for v in sorted(full)])
    dist, inside = distances_to_inputs(centres, train), inside_input_triangle(centres, train)
    for item in args.baked:
        label, _, folder = item.partition("=")
        baked = BakedScene.load(folder)
        views = []
        for v in sorted(full):
            scene, k = full[v]
            out = baked.render(scene.cameras.K[k], scene.cameras.world_from_cam[k])
            m = image_metrics(out.rgb, scene.images[k])  # LPIPS weights from $CMC_LPIPS_DIR
            kind = "input" if v in train else "protocol test" if v in test else "other"
            place = {"baselines_to_nearest_input": float(dist[v]), "inside_input_triangle": bool(inside[v])}
            views.append({"view": v, "kind": kind, **place, **m})
        bins = []
        for lo, hi in BINS:
            rows = [r for r in views if r["kind"] != "input" and lo <= r["baselines_to_nearest_input"] < hi]
            means = {key: float(np.mean([r[key] for r in rows])) for key in ("psnr", "ssim", "lpips_alex", "lpips_vgg")}
            bins.append(
                {"from": lo, "to": None if hi == float("inf") else hi, "views": [r["view"] for r in rows], **means}
            )
        report["bakes"][label] = {"folder": folder, "views": views, "bins": bins}
        print(label, json.dumps(bins))
    Path(args.out).write_text(json.dumps(report, indent=1) + "\n")
    print("wrote", args.out)


if __name__ == "__main__":
    main()
