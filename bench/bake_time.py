"""Time of baking fern's model, this tree against an earlier commit, and its cost in training steps.

Each tree is timed in its own process, the two alternating, ``--rounds`` times. A process builds
the ``fast`` model of fern's three training views (``images_8``, RegNeRF split; without the plane
sweep, then the parameters of ``--state``, a trained model written by
``python bench/train_step.py --save-state``), times ``--steps`` training steps of each loss phase
(reconstruction only from step 0, the full loss from step 150, after two warm-up steps) and
``--repeats`` bakes at full texel resolution and at a preview's (``--preview-scale``, the
``cmc.serving.baking.PREVIEW_TEXEL_SCALE``), and reports the medians: what ``cmc.method.eta.bake_steps``
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
from pathlib import Path

from train_step import STEP_TIMES, alternate, report_head

MEASURE = (
    STEP_TIMES
    + r"""
import tempfile
from cmc.serving.baking import bake
out = {"step_" + phase: s for phase, s in out.items()}
repeats, preview = int(sys.argv[4]), float(sys.argv[5])
trainer.model.load_state_dict(state)  # STEP_TIMES loaded it: bake the trained model, not the steps' changes
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
)


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
    argv = [str(Path(args.data).resolve()), str(args.steps), str(Path(args.state).resolve())]
    argv += [str(args.repeats), str(args.preview_scale)]
    rounds = alternate(args.before, args.rounds, MEASURE, *argv)
    summary = {name: {k: statistics.median(r[k] for r in runs) for k in runs[0]} for name, runs in rounds.items()}
    for s in summary.values():
        s["bake_full_in_reconstruction_only_steps"] = s["bake_full"] / s["step_reconstruction_only"]
        s["bake_full_over_preview"] = s["bake_full"] / s["bake_preview"]
    report = {
        **report_head(args.before),
        "rounds": rounds,
        "median": summary,
    }
    Path(args.out).write_text(json.dumps(report, indent=1) + "\n")
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
