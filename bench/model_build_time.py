"""Seconds to build the `fast` model of an LLFF scene (the plane sweeps before the first training
step), with the sweep's compiled CPU kernels (cmc/method/sweep_kernel.py) and with their torch twins,
alternating, so both are measured under the same load. The two builds give the same model to the
bit (checked here on the alpha of every MPI).

Usage::

    PYTHONPATH=. .venv/bin/python bench/model_build_time.py --data ../shared/datasets/llff/fern \\
        --repeats 2 --out bench/reports/current/model_build_time_fern.json
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
    saved = planesweep.census_distance, planesweep.semi_global, planesweep._window_mean
    planesweep.census_distance = planesweep.census_distance_torch
    planesweep.semi_global = planesweep.semi_global_torch
    planesweep._window_mean = functools.partial(saved[2], compiled=False)
    try:
        yield
    finally:
        planesweep.census_distance, planesweep.semi_global, planesweep._window_mean = saved


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=Path("../shared/datasets/llff/fern"))
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    torch.set_num_threads(2)
    scene = load_llff(args.data).train
    cfg = preset_config("fast")
    CMCModel(scene, cfg.model)  # compile (or load) the kernels outside the timings
    seconds: dict[str, list[float]] = {"torch": [], "compiled": []}
    alphas: dict[str, list[torch.Tensor]] = {}
    for _ in range(args.repeats):
        for mode in ("torch", "compiled"):
            with torch_twins() if mode == "torch" else contextlib.nullcontext():
                t0 = time.perf_counter()
                model = CMCModel(scene, cfg.model)
                seconds[mode].append(time.perf_counter() - t0)
            alphas[mode] = [p.detach().clone() for p in model.parameters()]
            print(mode, round(seconds[mode][-1], 2), flush=True)
    same = all(torch.equal(a, b) for a, b in zip(alphas["torch"], alphas["compiled"], strict=True))
    report = {
        "task": "model build (plane sweeps) of the fast preset, torch twins vs compiled sweep kernels, alternating",
        "command": "python bench/model_build_time.py "
        + " ".join(f"--{k.replace('_', '-')} {v}" for k, v in vars(args).items()),
        "scene": args.data.name,
        "seconds": seconds,
        "median_s": {k: statistics.median(v) for k, v in seconds.items()},
        "same_model_to_the_bit": same,
        "device": f"cpu ({platform.processor() or platform.machine()}, {os.cpu_count()} cores, 2 torch threads)",
        "git_commit": git_commit(),
        "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d"),
    }
    args.out.write_text(json.dumps(report, indent=1) + "\n")
    print(json.dumps(report["median_s"]), "same model:", same)


if __name__ == "__main__":
    main()
