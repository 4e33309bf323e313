"""Does refining the input poses while training recover views from misplaced cameras? (trex, 2026-11-27)

Training cameras 1 and 2 of an LLFF scene's RegNeRF split are moved by ``ROT_DEG`` degrees
about a random axis and ``FRAC`` of the mean baseline in a random direction (seed 7: the size
of the errors `bench/pose_accuracy.py` measures for three photos), the `fast` preset trains on
them with the given ``--set`` settings (``pose_lr=0.001``: the pose corrections of commit
"training: pose refinement" below), and the validation views are scored at their dataset poses.
One JSON line per run is appended to bench/reports/history/pose_refinement.jsonl (the log of its runs).

    PYTHONPATH=. .venv/bin/python bench/pose_refinement.py trex 0.3 0.015 [--set pose_lr=0.001]

The refinement was removed again after this measurement (see bench/DIAGNOSIS.md, "Refining the
input poses while training"); the script runs at the commit that added it.
"""

import argparse
import datetime as dt
import json
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from cmc.config import preset_config, with_settings
from cmc.data.datasets import load_llff
from cmc.eval.bench import git_commit, score_views
from cmc.geometry.planes import mean_baseline
from cmc.method.training import Trainer
from cmc.serving.baking import BakedScene, bake


def rotation(axis: np.ndarray, deg: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    a = np.radians(deg)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("rot_deg", type=float)
    ap.add_argument("frac", type=float)
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--data", type=Path, default=Path("../shared/datasets/llff"))
    ap.add_argument("--lpips-dir", default="../shared/weights")
    args = ap.parse_args()
    torch.set_num_threads(2)
    split = load_llff(args.data / args.scene)
    cams = split.train.cameras
    poses = cams.world_from_cam.copy()
    rng = np.random.default_rng(7)
    baseline = mean_baseline(cams.centers)
    for k in (1, 2):
        poses[k, :3, :3] = rotation(rng.normal(size=3), args.rot_deg) @ poses[k, :3, :3]
        d = rng.normal(size=3)
        poses[k, :3, 3] += args.frac * baseline * d / np.linalg.norm(d)
    train = replace(split.train, cameras=replace(cams, world_from_cam=poses))
    t0 = time.time()
    trainer = Trainer(train, with_settings(preset_config("fast"), args.set), "cpu")
    trainer.fit()
    seconds = time.time() - t0
    with tempfile.TemporaryDirectory() as tmp:
        baked = BakedScene.load(bake(trainer.model, Path(tmp)), torch.device("cpu"))
        names = [f"val_{i:03d}" for i in split.val_ids]
        views, _ = score_views(baked, split.val, names, args.lpips_dir, 1, None)
    record = {
        "scene": args.scene,
        "rot_deg": args.rot_deg,
        "frac": args.frac,
        "settings": args.set,
        **{f"val_{m}": float(np.mean([v[m] for v in views])) for m in ("psnr", "ssim", "lpips_vgg")},
        "train_s": seconds,
        "commit": git_commit(),
        "date": dt.date.today().isoformat(),
    }
    print(json.dumps(record), flush=True)
    with open(Path(__file__).parent / "reports" / "history" / "pose_refinement.jsonl", "a") as f:
        f.write(json.dumps(record) + "\n")


if __name__ == "__main__":
    main()
