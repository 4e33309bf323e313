"""The compiled plane sampler's backward pass on one training step's own gradients: this tree's
kernel against an earlier commit's, alternating in one process.

One full-loss step of fern (``fast``, its parameters from ``--state``: ``bench/train_step.py
--save-state``) is run with this tree, recording every call of
:func:`cmc.mpi.plane_sampling.sample_planes` (grid, textures) and the gradient that reached its
output. Then each kernel, this tree's and ``--before``'s (its ``cmc/mpi/plane_sampling.py`` loaded
beside it), runs the backward pass of all of them, ``--rounds`` times alternating; the report
holds the medians of the per-step totals (the first round, which compiles, not counted). Whole
training steps vary more between processes on a shared machine than this part of them does
(``bench/train_step.py``).

Usage (from the repository root)::

    python bench/sampler_backward.py --data ../shared/datasets/llff/fern --state /tmp/fern150.pt \\
        --before e9bc185 --out bench/reports/current/sampler_backward_cpu.json
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cmc.config import preset_config, with_settings  # noqa: E402
from cmc.data.datasets import load_llff  # noqa: E402
from cmc.eval.bench import git_commit  # noqa: E402
from cmc.method.training import Trainer  # noqa: E402
from cmc.mpi import plane_sampling  # noqa: E402


def load_module_at(rev: str, folder: str):
    """``cmc/mpi/plane_sampling.py`` of commit ``rev`` as a module of its own."""
    source = subprocess.run(
        ["git", "show", f"{rev}:cmc/mpi/plane_sampling.py"], cwd=ROOT, check=True, capture_output=True, text=True
    ).stdout
    path = Path(folder) / "plane_sampling_before.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location("plane_sampling_before", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def record_step(data: str, state: str) -> list[tuple]:
    """(grid, plane_texture, textures, mode, gradient of the output) of every sampler call of
    one full-loss step (step 150) from ``state``."""
    calls: list[list] = []
    sample = plane_sampling.sample_planes

    def recording(grid, plane_texture, textures, mode="bilinear"):
        out = sample(grid, plane_texture, textures, mode)
        entry = [grid.clone(), list(plane_texture), [t.detach().clone() for t in textures], mode, None]
        calls.append(entry)
        out.register_hook(lambda g: entry.__setitem__(4, g.clone()))
        return out

    plane_sampling.sample_planes = recording
    try:
        torch.manual_seed(0)
        cfg = with_settings(preset_config("fast"), ["model.pyramid.init_from_sweep=false"])
        trainer = Trainer(load_llff(data).train, cfg)
        trainer.model.load_state_dict(torch.load(state))
        trainer.step = 150
        trainer.train_step()
    finally:
        plane_sampling.sample_planes = sample
    return [tuple(c) for c in calls]


def backward_seconds(sample_planes, calls: list[tuple]) -> float:
    total = 0.0
    for grid, plane_texture, textures, mode, grad in calls:
        leaves = [t.clone().requires_grad_() for t in textures]
        out = sample_planes(grid, plane_texture, leaves, mode)
        t = time.perf_counter()
        out.backward(grad)
        total += time.perf_counter() - t
    return total


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", required=True, help="the fern scene folder")
    ap.add_argument("--state", required=True, help="model parameters (bench/train_step.py --save-state)")
    ap.add_argument("--before", required=True, help="the commit whose kernel to compare with")
    ap.add_argument("--rounds", type=int, default=6)
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    calls = record_step(args.data, args.state)
    with tempfile.TemporaryDirectory() as tmp:
        before = load_module_at(args.before, tmp)
        runs: dict[str, list[float]] = {"before": [], "after": []}
        for r in range(args.rounds):
            for name, fn in (("before", before.sample_planes), ("after", plane_sampling.sample_planes)):
                seconds = backward_seconds(fn, calls)
                if r:
                    runs[name].append(seconds)
    report = {
        "command": "python bench/sampler_backward.py " + " ".join(sys.argv[1:]),
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "git_commit": git_commit(),
        "before_commit": args.before,
        "machine": {"cpu": platform.processor() or platform.machine(), "threads": torch.get_num_threads()},
        "calls_per_step": len(calls),
        "zero_gradient_share": statistics.fmean(float((c[4] == 0).float().mean()) for c in calls),
        "seconds_per_step": runs,
        "median_seconds_per_step": {name: statistics.median(v) for name, v in runs.items()},
    }
    Path(args.out).write_text(json.dumps(report, indent=1) + "\n")
    print(json.dumps(report["median_seconds_per_step"], indent=1))


if __name__ == "__main__":
    main()
