"""Time of baking fern's model, this tree against an earlier commit, and its cost in training steps.

Each tree is timed in its own process, the two alternating, ``--rounds`` times. A process builds
the ``fast`` model of fern's three training views (``images_8``, RegNeRF split; without the plane
sweep, then the parameters of ``--state``, a trained model written by
``python bench/train_step.py --save-state``), times ``--steps`` training steps of each loss phase
(reconstruction only from step 0, the full loss from step 150, after two warm-up steps) and
``--repeats`` bakes at full texel resolution and at a preview's (``--preview-scale``, the
worker's ``PREVIEW_TEXEL_SCALE``), and reports the medians: what ``cmc.method.eta.bake_steps``
models (a bake in training steps) measured on this machine.

Usage (from the repository root, nothing else running; writes the report and prints it)::

    python bench/train_step.py --data ../shared/datasets/llff/fern --save-state /tmp/fern150.pt
    python bench/bake_time.py --data ../shared/datasets/llff/fern --before 0123abc \
        --state /tmp/fern150.pt --out bench/reports/current/bake_time_cpu.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
from datetime import UTC, datetime
from pathlib import Path

from train_step import ROOT, git, machine, run_in_tree

from cmc.eval.bench import git_commit

MEASURE = r"""
import json, statistics, sys, tempfile, time, torch
from cmc.config import preset_config, with_settings
from cmc.data.datasets import load_llff
from cmc.method.training import Trainer
from cmc.serving.baking import bake
data, state, steps, repeats, preview = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), float(sys.argv[5])
torch.manual_seed(0)
cfg = with_settings(preset_config("fast"), ["model.pyramid.init_from_sweep=false"])
trainer = Trainer(load_llff(data).train, cfg)
trainer.model.load_state_dict(torch.load(state))
out = {}
for phase, start in (("step_reconstruction_only", 0), ("step_full", 150)):
    trainer.step = start
    times = []
    for i in range(steps + 2):
        t = time.perf_counter()
        trainer.train_step()
        if i >= 2:
            times.append(time.perf_counter() - t)
    out[phase] = statistics.median(times)
trainer.model.load_state_dict(torch.load(state))  # bake the trained model, not the steps' changes
for name, scale in (("bake_full", 1.0), ("bake_preview", preview)):
    times = []
    for _ in range(repeats):
        with tempfile.TemporaryDirectory() as tmp:
            t = time.perf_counter()
            bake(trainer.model, tmp, scale=scale)
            times.append(time.perf_counter() - t)
    out[name] = statistics.median(times)
print(json.dumps(out))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", required=True, help="the fern scene folder")
    ap.add_argument("--before", required=True, help="the commit to compare with")
    ap.add_argument("--state", required=True, help="a trained model's parameters (train_step.py --save-state)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--steps", type=int, default=6, help="timed training steps per phase and process")
    ap.add_argument("--repeats", type=int, default=3, help="timed bakes per resolution and process")
    ap.add_argument("--preview-scale", type=float, default=0.5)
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    argv = [str(Path(args.data).resolve()), str(Path(args.state).resolve())]
    argv += [str(args.steps), str(args.repeats), str(args.preview_scale)]
    rounds: dict[str, list[dict[str, float]]] = {"before": [], "after": []}
    with tempfile.TemporaryDirectory() as tmp:
        before_tree = Path(tmp) / "before"
        git("worktree", "add", "--detach", str(before_tree), args.before)
        try:
            for r in range(args.rounds):
                for name, tree in (("before", before_tree), ("after", ROOT)):
                    rounds[name].append(run_in_tree(tree, MEASURE, *argv))
                    print(f"round {r + 1}: {name} {rounds[name][-1]}", flush=True)
        finally:
            git("worktree", "remove", "--force", str(before_tree))
    summary = {name: {k: statistics.median(r[k] for r in runs) for k in runs[0]} for name, runs in rounds.items()}
    for s in summary.values():
        s["bake_full_in_reconstruction_only_steps"] = s["bake_full"] / s["step_reconstruction_only"]
        s["bake_full_over_preview"] = s["bake_full"] / s["bake_preview"]
    report = {
        "command": "python bench/bake_time.py " + " ".join(sys.argv[1:]),
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "git_commit": git_commit(),
        "before_commit": git("rev-parse", "--short", args.before),
        "machine": machine(),
        "rounds": rounds,
        "median": summary,
    }
    Path(args.out).write_text(json.dumps(report, indent=1) + "\n")
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
