"""Write bench/EXPLORE.md: the GPU explorations of `fast` variants on three real scenes' validation
views (bench/explore_gpu.py), one table per round, from their JSON-lines reports.

Usage: python bench/explore_table.py  (rewrites bench/EXPLORE.md; numbers come only from the reports)
"""

from __future__ import annotations

import json
from pathlib import Path

BENCH = Path(__file__).resolve().parent
REPORTS = BENCH / "reports" / "history"  # the rounds' JSON-lines reports
SCENES = ("fern", "room", "trex")
# (report, command, what the round asked); every row is compared with its round's `base` (the
# preset of that day, trained on the same machine; training is deterministic), or where the round
# has none, with the latest round's before it.
ROUNDS = [
    (
        "explore_gpu_round3.jsonl",
        "GIT_COMMIT=118a6c7 VARIANTS=bench/reports/history/explore_gpu_round3_variants.json "
        "bash bench/gpu_run.sh 560 profile explore",
        "the sweep's semi-global penalties (P1, P2), with and without P2 falling at the photo's edges "
        "(`stereo_smoothness_edges`, since deleted); a Charbonnier reconstruction penalty (deleted); "
        "fewer steps, more planes, a lower final learning rate",
    ),
    (
        "explore_gpu_round4.jsonl",
        "PYTHONPATH=. CMC_LPIPS_DIR=.gpudata/weights python3 bench/explore_gpu.py "
        "bench/reports/history/explore_gpu_round4_variants.json $OUT --data .gpudata/llff "
        "--scenes fern,room,trex --lpips "
        "--workers 9 --seconds 15 --grace 185",
        "round 3's gains together: (0.2, 2.0) with 300 steps and/or 64 planes",
    ),
    (
        "explore_gpu_round5.jsonl",
        "python3 bench/gpudata.py unpack; CMC_GIT_COMMIT=e09d801 PYTHONPATH=. CMC_LPIPS_DIR=.gpudata/weights "
        "python3 bench/explore_gpu.py bench/reports/history/explore_gpu_round5_variants.json $OUT "
        "--data .gpudata/llff --scenes fern,room,trex --lpips --workers 9 --seconds 350 --grace 200",
        "a full-resolution texture level, more base colour groups, more rays per step (at the same and at "
        "1.5x the rays in all), a higher learning rate, a weaker concentration prior, a wider sweep window, "
        "two unseen poses a step. Three calls on one warm machine: the command below, then the same with "
        "rays6144, rays8192_steps225 and rays8192_groups14 alone (`--seconds 20`), then "
        "rays8192_steps150 and rays12288_steps150 (`--workers 6`) beside base and rays8192_steps225 on the "
        "synthetic scene posts (`--scenes '' --synthetic posts --workers 2`)",
    ),
    (
        "explore_gpu_round6.jsonl",
        "python3 bench/gpudata.py unpack; CMC_GIT_COMMIT=9d62d55 PYTHONPATH=. CMC_LPIPS_DIR=.gpudata/weights "
        "python3 bench/explore_gpu.py bench/reports/history/explore_gpu_round6_variants.json $OUT "
        "--data .gpudata/llff --scenes fern,room,trex --lpips --workers 9 --seconds 330 --grace 200",
        "how a step draws its rays (stratified over the photo, or slices of a random order of its pixels: "
        "each pixel once before any twice), the base colours' learning rate (a factor on it; "
        "`base_lr_factor`, since deleted), Adam's beta2 (`adam_beta2`, since deleted), a lower learning rate, "
        "more rays at the unseen pose. Three calls on one warm machine: the command below with the first "
        "nine variants, then with the next three and the last three (`--seconds 20`; the variants file "
        "holds all fifteen)",
    ),
    (
        "explore_gpu_round7.jsonl",
        "python3 bench/gpudata.py unpack; CMC_GIT_COMMIT=d9b00a9 PYTHONPATH=. CMC_LPIPS_DIR=.gpudata/weights "
        "python3 bench/explore_gpu.py bench/reports/history/explore_gpu_round7_variants.json $OUT "
        "--data .gpudata/llff --scenes fern,room,trex --lpips --workers 9 --seconds 285 --grace 150",
        "the weights of the entropy and concentration priors, an extra coarse texture level (1/32) or "
        "one fewer (no 1/16), the sweep's window (3 instead of 5) and softmin temperature (0.5 instead "
        "of 0.3), and colour gradients for every plane sample (`colour_grad_min_weight=0`: is the "
        "backward pass's shortcut free?). The `git_commit` the reports name is the training code's "
        "(f7d09df; d9b00a9 added only the variants file)",
    ),
    (
        "explore_gpu_round8.jsonl",
        "python3 bench/gpudata.py unpack; CMC_GIT_COMMIT=d9b00a9 PYTHONPATH=. CMC_LPIPS_DIR=.gpudata/weights "
        "python3 bench/explore_gpu.py bench/reports/history/explore_gpu_round8_variants.json $OUT "
        "--data .gpudata/llff --scenes fern,room,trex --lpips --workers 9 --seconds 235 --grace 120",
        "round 7's leads together and apart: the extra coarse level with a weaker entropy prior, the "
        "smaller sweep window or the sweep's larger semi-global penalties (0.3, 3.0), a sixth level "
        "(1/64). The same warm machine right after round 7, whose `base` is the reference here; the "
        "ninth variant (levels5_window3_ent0002) did not start before the deadline",
    ),
]
ADOPTED = {"sgm2_steps300", "rays6144", "permutation_lr004"}  # the variants the preset took up


def _load(name: str) -> list[dict]:
    return [json.loads(line) for line in (REPORTS / name).read_text().splitlines() if line.strip()]


def _cell(rec: dict | None, base: dict, kind: str) -> str:
    if rec is None or kind not in rec:
        return "not run"
    r, b = rec[kind], base[kind]
    return (
        f"{r['psnr']:.2f} / {r['ssim']:.3f} / {r['lpips_vgg']:.3f} "
        f"({r['psnr'] - b['psnr']:+.2f} / {r['ssim'] - b['ssim']:+.3f} / {r['lpips_vgg'] - b['lpips_vgg']:+.3f})"
    )


def main() -> None:
    rounds = [(_load(name), name, command, question) for name, command, question in ROUNDS]
    first = rounds[0][0][0]
    out = [
        "# `fast` variants on the validation views of fern, room and trex (lent GPU)",
        "",
        "Generated by `python bench/explore_table.py` from the reports named below. Each variant trained",
        "on a scene's three training views and was scored on its validation views (the images neither",
        "trained on nor tested: the columns a setting is chosen on) with the baked renderer; PSNR / SSIM /",
        "LPIPS-vgg, in brackets the change against the preset (`base`) of the same day. LPIPS-vgg here",
        "uses 8-bit weights (bench/gpudata.py; within 3e-4 of the float weights on photo pairs). The CUDA",
        "`base` scores what the CPU scores (fern 22.09 / 0.700 / 0.249 against 22.10 / 0.700 / 0.249 in",
        "bench/RESULTS.md). Test views are shown only to see afterwards whether validation predicted them.",
        f"Machine: {first['device']}, 16 CPU cores, lent through the device tool; nine trainings at once,",
        "so train seconds are not comparable.",
        "",
    ]
    base: dict[str, dict] = {}
    for recs, name, command, question in rounds:
        base = {r["scene"]: r for r in recs if r["variant"] == "base"} or base
        out += [
            f"## {name}: {question}",
            "",
            f"Command: `{command}`; commit {recs[0]['git_commit']}, {recs[0]['date']}.",
            "",
        ]
        out += [
            "| variant | settings | "
            + " | ".join(f"{s} val" for s in SCENES)
            + " | "
            + " | ".join(f"{s} test" for s in SCENES)
            + " |"
        ]
        out += ["|---|---|" + "---|" * (2 * len(SCENES))]
        variants = sorted(dict.fromkeys(r["variant"] for r in recs), key=lambda v: v != "base")
        for v in variants:
            by_scene = {r["scene"]: r for r in recs if r["variant"] == v}
            settings = " ".join(f"`{s}`" for s in next(iter(by_scene.values()))["settings"]) or "(the preset)"
            label = f"**{v}** (adopted)" if v in ADOPTED else v
            cells = [_cell(by_scene.get(s), base[s], "val") for s in SCENES]
            cells += [_cell(by_scene.get(s), base[s], "test") for s in SCENES]
            out.append(f"| {label} | {settings} | " + " | ".join(cells) + " |")
        out.append("")
        synthetic = [r for r in recs if "halfway" in r]
        if synthetic:
            groups = ("near", "halfway", "beyond")
            out += [f"| variant | scene | {' | '.join(groups)} |", "|---|---|" + "---|" * len(groups)]
            for r in synthetic:
                b = next(x for x in synthetic if x["variant"] == "base" and x["scene"] == r["scene"])
                out.append(f"| {r['variant']} | {r['scene']} | " + " | ".join(_cell(r, b, g) for g in groups) + " |")
            out.append("")
    recs = rounds[0][0]
    out += [
        "## The MPI blend: inverse distance to the power 2 (the renderer's), 4 or 8",
        "",
        "The same trained variants of round 3, their validation views rendered again with the blend weights",
        "raised to the power p/2 (nearer MPIs weigh more): every variant on every scene scores lower at 4",
        "and 8, so the blend stays as it is.",
        "",
        "| variant | scene | p = 2 | p = 4 | p = 8 |",
        "|---|---|---|---|---|",
    ]
    for r in recs:
        if "val_blend4" not in r:
            continue
        cells = [
            f"{r[k]['psnr']:.2f} / {r[k]['ssim']:.3f} / {r[k]['lpips_vgg']:.3f}"
            for k in ("val", "val_blend4", "val_blend8")
        ]
        out.append(f"| {r['variant']} | {r['scene']} | " + " | ".join(cells) + " |")
    (BENCH / "EXPLORE.md").write_text("\n".join(out) + "\n")


if __name__ == "__main__":
    main()
