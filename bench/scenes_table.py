"""bench/SCENES.md: view quality on every real scene (and the synthetic set), one row per run.

    python bench/scenes_table.py

Each report is one ``cmc bench`` run (its command in the page's header, the one changed setting
in its row); ``EXPERIMENTS`` lists them, grouped by the question they answer, with what the
change is relative to the preset of that day and whether it was adopted. Rows of one question
are on the same scenes and views; training is deterministic (the same code, seed and scene give
the same model, bit for bit), so a report from an earlier day of the same preset is still its
"before".
"""

from __future__ import annotations

import json
from pathlib import Path

HERE = Path(__file__).resolve().parent
OUT = HERE / "SCENES.md"

# Changes that several rows share.
BOUNDS = "before: planes over the scene's bounds"
FITTED = "planes fitted to the sweep"
SGM3 = "sweep's semi-global penalties (P1, P2) (0.1, 1.0) -> (0.3, 3.0)"
SGM2_300 = "penalties (0.1, 1.0) -> (0.2, 2.0), 400 -> 300 steps"

# (question, [(report, change vs the preset of its day, verdict)]); "" = the preset itself.
EXPERIMENTS: list[tuple[str, list[tuple[str, str, str]]]] = [
    (
        "Planes over the depths the first sweep finds (`model.fit_depth_range`), 2026-11-26/27",
        [
            ("view_quality_fern_now.json", BOUNDS, ""),
            ("bounds_fern_val_before.json", BOUNDS, ""),
            ("bounds_room_val_before.json", BOUNDS, ""),
            ("bounds_trex_val_before.json", BOUNDS, ""),
            ("view_quality_synthetic_now.json", "before (the fit leaves tight bounds as they are)", ""),
            ("bounds_fern_val_fit.json", FITTED, "adopted"),
            ("bounds_room_val_fit.json", FITTED, "adopted"),
            ("bounds_trex_val_fit.json", FITTED, "adopted"),
            ("bounds_fern_test_fit.json", FITTED, "adopted"),
            ("bounds_room_test_fit.json", FITTED, "adopted"),
            ("bounds_trex_test_fit.json", FITTED, "adopted"),
            ("bounds_fern_test_q4_fit.json", "fitted, every near bound / 4", "within 0.02 dB"),
            ("bounds_synthetic_q4_fit.json", "fitted, every near bound / 4", "within 0.14 dB on average"),
        ],
    ),
    (
        "Smoother depth where the photos leave it open, 2026-11-27 (before: the rows fitted to the sweep above)",
        [
            ("scenes_room_val_rerun.json", "the preset again: the same numbers to the last digit", ""),
            (
                "scenes_room_val_depth_smoothness.json",
                "+ depth smoothness on 8x8 patches at the unseen poses (RegNeRF's prior), weight 1",
                "not adopted: no change (the sweep's blobs stay); code removed, in the commit message",
            ),
            (
                "scenes_room_val_sgm3.json",
                SGM3,
                "room +0.37 dB: walls and ceiling take one depth",
            ),
            (
                "scenes_trex_val_sgm3.json",
                SGM3,
                "trex -0.07 dB, LPIPS-vgg -0.006",
            ),
            (
                "scenes_fern_val_sgm3.json",
                SGM3,
                "not adopted: fern -0.13 dB, SSIM -0.004",
            ),
            (
                "scenes_fern_val_sgm3_edges.json",
                "(0.3, 3.0), P2 falling at the photo's edges (`stereo_smoothness_edges=0.05`)",
                "not adopted: trex -0.33 dB on its validation views (bench/EXPLORE.md); option deleted",
            ),
        ],
    ),
    (
        "Sweep penalties (0.2, 2.0) and 300 steps, chosen on the validation views in bench/EXPLORE.md, 2026-11-27 "
        "(before: the rows fitted to the sweep above; train seconds of the two sessions' machines are not comparable)",
        [
            ("view_quality_synthetic_sgm2_steps300.json", SGM2_300, "adopted: synthetic -0.01 / -0.01 / +0.10 dB"),
            ("bounds_fern_test_fit.json", "before (test views)", ""),
            ("bounds_room_test_fit.json", "before (test views)", ""),
            ("bounds_trex_test_fit.json", "before (test views)", ""),
            (
                "scenes_fern_test_sgm2_steps300.json",
                SGM2_300,
                "fern test -0.07 dB, LPIPS-vgg +0.005 (validation: +0.00 dB)",
            ),
            ("scenes_room_test_sgm2_steps300.json", SGM2_300, "room test +0.24 dB, LPIPS-vgg -0.008"),
            ("scenes_trex_test_sgm2_steps300.json", SGM2_300, "trex test +0.07 dB, LPIPS-vgg -0.001"),
        ],
    ),
]


def _cells(r: dict) -> tuple[str, str, list[str]]:
    """(scene, views, [main, near, beyond]) of a report."""
    scene = "+".join(s["scene"] for s in r["scenes"])
    if "halfway" in r["mean"]:  # the synthetic set: halfway / near / beyond
        groups = [r["mean"][k] for k in ("halfway", "near", "beyond")]
        return scene, "synthetic", [f"{m['psnr']:.2f} / {m['ssim']:.3f} / {m['lpips_vgg']:.3f}" for m in groups]
    m = r["mean"]
    return scene, r.get("scored_views", "test"), [f"{m['psnr']:.2f} / {m['ssim']:.3f} / {m['lpips_vgg']:.3f}", "", ""]


def main() -> None:
    head = ["scene", "views", "change", "PSNR / SSIM / LPIPS-vgg (synthetic: halfway)", "near", "beyond"]
    head += ["train s", "verdict", "date", "report"]
    lines = [
        "# View quality per scene: the experiments of issue 38",
        "",
        "Generated by `python bench/scenes_table.py` from the reports listed in it, each written by",
        "`CMC_LPIPS_DIR=../shared/weights cmc bench llff --data ../shared/datasets/llff --scenes S --views V"
        " [--near-scale X] [--set KEY=VALUE] --out bench/....json`",
        "(or `cmc bench synthetic ...`) on the 2-core CPU of these machines. Validation views (`val`)",
        "chose the settings; test views only report them. `near x 0.25` rows: every near bound divided",
        "by 4. Training seconds compare only within one day: the machines differ (2026-11-27's took",
        "about 2x as long for the same run as 2026-11-26's) and are void where another process ran.",
        "",
    ]
    for question, runs in EXPERIMENTS:
        lines += [f"## {question}", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for name, change, verdict in runs:
            r = json.loads((HERE / name).read_text())
            scene, views, cells = _cells(r)
            if r.get("near_scale", 1.0) != 1.0:
                views += f", near x {r['near_scale']:g}"
            train_s = f"{r['mean']['train_seconds']:.0f}"
            lines.append("| " + " | ".join([scene, views, change, *cells, train_s, verdict, r["date"], name]) + " |")
        lines.append("")
    OUT.write_text("\n".join(lines))
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
