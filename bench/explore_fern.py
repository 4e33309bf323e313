"""Exploratory fern runs used while designing the fast preset (field renders of the held-out views).

Usage: PYTHONPATH=. python bench/explore_fern.py NAME '{"steps": 400, "model": {"num_planes": 48}}'
Appends one line to /tmp/exp_results.txt (its lines from development are in
bench/reports/current/exploration_fern_400steps.txt). Overrides: top-level TrainConfig fields, and "loss",
"model", "pyramid" dicts for the nested configs.
"""

import json
import sys
import time
from dataclasses import replace

from cmc.config import preset_config
from cmc.data.datasets import load_llff
from cmc.eval.metrics import LPIPS, psnr, ssim
from cmc.method.training import Trainer

name, ov = sys.argv[1], json.loads(sys.argv[2])
split = load_llff("../shared/datasets/llff/fern")
cfg = preset_config("fast", **{k: v for k, v in ov.items() if k not in ("loss", "model", "pyramid")})
if "loss" in ov:
    cfg = replace(cfg, loss=replace(cfg.loss, **ov["loss"]))
if "model" in ov:
    cfg = replace(cfg, model=replace(cfg.model, **ov["model"]))
if "pyramid" in ov:
    py = {k: tuple(v) if isinstance(v, list) else v for k, v in ov["pyramid"].items()}
    cfg = replace(cfg, model=replace(cfg.model, pyramid=replace(cfg.model.pyramid, **py)))
trainer = Trainer(split.train, cfg)
t = time.time()
trainer.fit()
seconds = time.time() - t
trainer.save_checkpoint(f"/tmp/ckpt_{name}.pt")
lpips = LPIPS("alex", "../shared/weights")
res = []
for k in range(len(split.test)):
    cams = split.test.cameras
    pred = trainer.model.render(cams.K[k], cams.world_from_cam[k], 504, 378).rgb.numpy()
    gt = split.test.images[k]
    res.append((psnr(pred, gt), ssim(pred, gt), lpips(pred, gt)))
m = [sum(r[i] for r in res) / len(res) for i in range(3)]
line = (
    f"{name}: train {seconds:.0f}s steps {cfg.steps} PSNR {m[0]:.2f} SSIM {m[1]:.3f} LPIPS {m[2]:.3f} "
    f"per-view {[round(r[0], 2) for r in res]} {json.dumps(ov)}"
)
print(line)
with open("/tmp/exp_results.txt", "a") as f:
    f.write(line + "\n")
