"""Seconds to build the `fast` model of an LLFF scene (the plane sweeps before the first training
step), with the sweep's compiled CPU kernels (cmc/method/sweep_kernel.py) and with their torch twins,
and with ``--before REV`` also as that commit builds it (in a git worktree, its own process),
alternating, so all are measured under the same load. The report says how far the parameters of
the compiled build lie from the torch build's (the kernels whose float rounding differs from
torch's: cmc/method/sweep_kernel.py).

Usage::

    PYTHONPATH=. .venv/bin/python bench/model_build_time.py --data ../shared/datasets/llff/fern \\
        --repeats 2 [--before REV] --out bench/reports/current/model_build_time_fern.json
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as dt
import functools
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import torch

import cmc.method.planesweep as planesweep
from cmc.config import preset_config
from cmc.data.datasets import load_llff
from cmc.eval.bench import git_commit
from cmc.method.model import CMCModel


@contextlib.contextmanager
def torch_twins() -> Iterator[None]:
    """The sweep as it was before the kernels: every compiled path replaced by its torch twin."""
    names = ("census_distance", "semi_global", "_combined_window_cost", "_texel_cost")
    saved = [getattr(planesweep, name) for name in names]
    planesweep.census_distance = planesweep.census_distance_torch
    planesweep.semi_global = planesweep.semi_global_torch
    planesweep._combined_window_cost = functools.partial(saved[2], compiled=False)
    planesweep._texel_cost = functools.partial(saved[3], compiled=False)
    try:
        yield
    finally:
        for name, function in zip(names, saved, strict=True):
            setattr(planesweep, name, function)


BUILD = r"""
import sys, time, torch
from cmc.config import preset_config
from cmc.data.datasets import load_llff
from cmc.method.model import CMCModel
torch.set_num_threads(2)
scene = load_llff(sys.argv[1]).train
CMCModel(scene, preset_config("fast").model)
t0 = time.perf_counter()
model = CMCModel(scene, preset_config("fast").model)
print(time.perf_counter() - t0)
torch.save([p.detach() for p in model.parameters()], sys.argv[2])
"""


def time_commit(tree: Path, data: Path, params: Path) -> float:
    """Seconds of one model build by the code in ``tree`` (after one untimed build), in its own
    process; the model's parameters are saved to ``params``."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    command = [sys.executable, "-c", BUILD, str(data.resolve()), str(params)]
    done = subprocess.run(command, cwd=tree, env=env, capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"building with {tree} failed:\n{done.stderr}")
    return float(done.stdout.split()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=Path("../shared/datasets/llff/fern"))
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--before", help="a commit to time as well (git worktree, own process)")
    ap.add_argument("--without-torch", action="store_true", help="skip the torch twins (about 6x slower)")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    torch.set_num_threads(2)
    scene = load_llff(args.data).train
    cfg = preset_config("fast")
    CMCModel(scene, cfg.model)  # compile (or load) the kernels outside the timings
    seconds: dict[str, list[float]] = {"compiled": []} if args.without_torch else {"torch": [], "compiled": []}
    alphas: dict[str, list[torch.Tensor]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        before = Path(tmp) / "before"
        if args.before:
            seconds["before"] = []
            subprocess.run(["git", "worktree", "add", "--detach", str(before), args.before], check=True)
        try:
            for _ in range(args.repeats):
                for mode in seconds:
                    if mode == "before":
                        seconds[mode].append(time_commit(before, args.data, Path(tmp) / "before.pt"))
                        alphas[mode] = torch.load(Path(tmp) / "before.pt")
                    else:
                        with torch_twins() if mode == "torch" else contextlib.nullcontext():
                            t0 = time.perf_counter()
                            model = CMCModel(scene, cfg.model)
                            seconds[mode].append(time.perf_counter() - t0)
                        alphas[mode] = [p.detach().clone() for p in model.parameters()]
                    print(mode, round(seconds[mode][-1], 2), flush=True)
        finally:
            if args.before:
                subprocess.run(["git", "worktree", "remove", "--force", str(before)], check=True)
    same, largest = {}, {}
    for other in set(alphas) - {"compiled"}:
        pairs = list(zip(alphas[other], alphas["compiled"], strict=True))
        same[other] = all(torch.equal(a, b) for a, b in pairs)
        largest[other] = max(float((a - b).abs().max()) for a, b in pairs)
    report = {
        "task": "model build (plane sweeps) of the fast preset: torch twins, compiled sweep kernels"
        + (f", commit {args.before}" if args.before else "")
        + ", alternating",
        "command": "python bench/model_build_time.py "
        + " ".join(f"--{k.replace('_', '-')} {v}" for k, v in vars(args).items()),
        "scene": args.data.name,
        "seconds": seconds,
        "median_s": {k: statistics.median(v) for k, v in seconds.items()},
        "compiled_same_model_to_the_bit_as": same,
        "compiled_largest_parameter_difference_from": largest,
        "device": f"cpu ({platform.processor() or platform.machine()}, {os.cpu_count()} cores, 2 torch threads)",
        "git_commit": git_commit(),
        "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d"),
    }
    args.out.write_text(json.dumps(report, indent=1) + "\n")
    print(json.dumps(report["median_s"]), "same model:", same, "largest difference:", largest)


if __name__ == "__main__":
    main()
