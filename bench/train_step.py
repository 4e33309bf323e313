"""Time of one training step on fern, this tree against an earlier commit.

The job: fern's three training views (``images_8``, RegNeRF split), ``fast`` preset. Each tree is
timed in its own process, the two alternating, ``--rounds`` times; a process times ``--steps``
steps of each loss phase (reconstruction only, from step 0; the full loss, from step 150) after
two warm-up steps, and reports their medians. The plane-sweep start is off
(``model.pyramid.init_from_sweep=false``), which spares each process the sweep. Then every plane
of every ray weighs alike, while a trained model's rays put their weight on a few planes, and
the backward pass skips the colours of the faint ones (``TrainConfig.colour_grad_min_weight``):
``--state`` starts both trees from the parameters of a trained model instead, written once by
``--save-state`` (this tree, the preset with its sweep, ``--state-steps`` steps).

Usage (from the repository root; writes the report and prints it)::

    python bench/train_step.py --data ../shared/datasets/llff/fern --save-state /tmp/fern150.pt
    python bench/train_step.py --data ../shared/datasets/llff/fern --before 72b0bd5 \
        --state /tmp/fern150.pt --out bench/reports/current/train_step_cpu.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from datetime import UTC, datetime
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from cmc.eval.bench import git_commit, machine_info  # noqa: E402

# Times the two phases' steps into `out` (argv: data, steps, state); bake_time.py goes on from here.
STEP_TIMES = r"""
import json, statistics, sys, time, torch
from cmc.config import preset_config, with_settings
from cmc.data.datasets import load_llff
from cmc.method.training import Trainer
data, steps, state = sys.argv[1], int(sys.argv[2]), sys.argv[3]
torch.manual_seed(0)
cfg = with_settings(preset_config("fast"), ["model.pyramid.init_from_sweep=false"])
trainer = Trainer(load_llff(data).train, cfg)
if state:
    state, expected = torch.load(state), trainer.model.state_dict()
    # The pyramid levels as this tree keeps them: RGBA in one ("levels", until 2026-11-29)
    # or colour and alpha apart ("colour_levels", "alpha_levels").
    for key in [k for k in state if ".levels." in k and k not in expected]:
        rgba = state.pop(key)
        state[key.replace(".levels.", ".colour_levels.")] = rgba[:, :3]
        state[key.replace(".levels.", ".alpha_levels.")] = rgba[:, 3:]
    if any(".levels." in k for k in expected):
        for key in [k for k in state if ".colour_levels." in k and k not in expected]:
            alpha = state.pop(key.replace(".colour_levels.", ".alpha_levels."))
            state[key.replace(".colour_levels.", ".levels.")] = torch.cat([state.pop(key), alpha], 1)
    # Colour levels matched by size (for trees or settings with other `colour_scales`); a level the
    # state lacks starts at 0, as in a fresh field.
    colour = {k: state.pop(k) for k in [k for k in state if ".colour_levels." in k]}
    for key in [k for k in expected if ".colour_levels." in k]:
        prefix = key.split(".colour_levels.")[0]
        same = [v for k, v in colour.items() if k.startswith(prefix + ".") and v.shape == expected[key].shape]
        state[key] = same[0] if same else torch.zeros_like(expected[key])
    trainer.model.load_state_dict(state)
out = {}
for phase, start in (("reconstruction_only", 0), ("full", 150)):
    trainer.step = start
    times = []
    for i in range(steps + 2):
        t = time.perf_counter()
        trainer.train_step()
        if i >= 2:
            times.append(time.perf_counter() - t)
    out[phase] = statistics.median(times)
"""
MEASURE = STEP_TIMES + "print(json.dumps(out))\n"


def git(*args: str, cwd: Path = ROOT) -> str:
    return subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True, text=True).stdout.strip()


SAVE_STATE = r"""
import sys, torch
from cmc.config import preset_config
from cmc.data.datasets import load_llff
from cmc.method.training import Trainer
data, steps, path = sys.argv[1], int(sys.argv[2]), sys.argv[3]
torch.manual_seed(0)
trainer = Trainer(load_llff(data).train, preset_config("fast"))
for _ in range(steps):
    trainer.train_step()
torch.save(trainer.model.state_dict(), path)
"""


def run_in_tree(tree: Path, script: str, *args: str) -> dict[str, float]:
    """Run ``script`` (Python source) with ``args`` in a fresh process importing the ``cmc`` of
    ``tree``; the JSON object its last line of output prints."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    done = subprocess.run([sys.executable, "-c", script, *args], cwd=tree, env=env, capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"timing {tree} failed:\n{done.stderr}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def alternate(before: str, rounds: int, script: str, *args: str) -> dict[str, list[dict[str, float]]]:
    """``script`` run (:func:`run_in_tree`) in a worktree of commit ``before`` and in this tree,
    alternating, ``rounds`` times: each tree's results in order."""
    results: dict[str, list[dict[str, float]]] = {"before": [], "after": []}
    with tempfile.TemporaryDirectory() as tmp:
        before_tree = Path(tmp) / "before"
        git("worktree", "add", "--detach", str(before_tree), before)
        try:
            for r in range(rounds):
                for name, tree in (("before", before_tree), ("after", ROOT)):
                    results[name].append(run_in_tree(tree, script, *args))
                    print(f"round {r + 1}: {name} {results[name][-1]}", flush=True)
        finally:
            git("worktree", "remove", "--force", str(before_tree))
    return results


def report_head(before: str) -> dict[str, object]:
    """The command (this script's), date, commits and machine a report starts with."""
    return {
        "command": f"python bench/{Path(sys.argv[0]).name} " + " ".join(sys.argv[1:]),
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "git_commit": git_commit(),
        "before_commit": git("rev-parse", "--short", before),
        "machine": machine_info(),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", required=True, help="the fern scene folder")
    ap.add_argument("--before", help="the commit to compare with")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--steps", type=int, default=12, help="timed steps per phase and process")
    ap.add_argument("--state", default="", help="model parameters both trees start from (--save-state)")
    ap.add_argument("--save-state", help="write a trained model's parameters here, and time nothing")
    ap.add_argument("--state-steps", type=int, default=150, help="training steps of --save-state")
    ap.add_argument("--out")
    args = ap.parse_args()
    data = str(Path(args.data).resolve())
    if args.save_state:
        subprocess.run([sys.executable, "-c", SAVE_STATE, data, str(args.state_steps), args.save_state], check=True)
        return
    if not (args.before and args.out):
        ap.error("--before and --out are needed to time")
    state = str(Path(args.state).resolve()) if args.state else ""
    rounds = alternate(args.before, args.rounds, MEASURE, data, str(args.steps), state)
    summary = {
        name: {phase: statistics.median(r[phase] for r in runs) for phase in runs[0]} for name, runs in rounds.items()
    }
    report = {
        **report_head(args.before),
        "steps_per_process": args.steps,
        "start": args.state or "the preset without its sweep",
        "rounds": rounds,
        "median_step_s": summary,
    }
    Path(args.out).write_text(json.dumps(report, indent=1) + "\n")
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
