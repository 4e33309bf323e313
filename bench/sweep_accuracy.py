"""How often the plane sweep's best plane is right, for each photo-consistency cost.

The ``fast`` preset starts every MPI's alpha from a plane sweep (``cmc.method.planesweep``). This scores
the sweep alone, before any training, against depth it never saw:

* the wide-baseline synthetic scenes (``cmc.data.datasets.wide_baseline_split``): exact depth at every
  other pixel of each input view;
* LLFF fern with the RegNeRF split: the SfM points of ``sparse/0/points3D.bin`` whose track holds
  an input view (COLMAP image ids follow the sorted image names, as ``poses_bounds.npy`` rows do),
  triangulated from all 20 photos. Points sit on textured spots, so fern's shares are optimistic.

Per cost (and sweep grid): the share of targets whose best plane lies within 1 (and 2) plane
spacings of the true depth, and, after the softmin at the cost's temperature, the share of texels
inside the image where the sweep is confident (most probable plane above 0.5, the hidden layers'
gate) and the share of confident targets within one plane (precision). Nothing trains and nothing is rendered
at a test view (fern's points were triangulated by COLMAP from all 20 photos, test views included).

Usage (repository root)::

    .venv/bin/python bench/sweep_accuracy.py [--data ../shared/datasets/llff/fern] \\
        [--out bench/reports/current/sweep_accuracy.json]
"""

from __future__ import annotations

import argparse
import datetime
import json
import struct
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from cmc.config import preset_config
from cmc.data.datasets import WIDE_SCENES, Scene, load_llff, wide_baseline_split
from cmc.eval.bench import git_commit
from cmc.method.planesweep import plane_sweep_weights, texel_pixels
from cmc.mpi.rendering import MPIFrame

# (label, cost, softmin temperature, supersample, (P1, P2) of semi-global aggregation, occlusion
# aware: the best-matching other view's cost, else the mean of the views'): the starts of the
# `fast` presets in turn, the fourth that of `fast` now; the last with the two other views' costs
# averaged (tried, not adopted: bench/reports/history/RESULTS-until-2026-11-27.md).
COSTS = (
    ("ad", "ad", 0.01, 1, (0.0, 0.0), True),
    ("ad_census", "ad_census", 0.1, 1, (0.0, 0.0), True),
    ("ad_census_2x", "ad_census", 0.1, 2, (0.0, 0.0), True),
    ("ad_census_2x_sgm", "ad_census", 0.2, 2, (0.1, 1.0), True),
    ("ad_census_2x_sgm_mean", "ad_census", 0.2, 2, (0.1, 1.0), False),
)


def read_points3d(path: Path) -> tuple[np.ndarray, list[np.ndarray]]:
    """COLMAP ``points3D.bin`` -> (xyz [N, 3] world, per point the image ids of its track)."""
    xyz, tracks = [], []
    with open(path, "rb") as f:
        (n,) = struct.unpack("<Q", f.read(8))
        for _ in range(n):
            _, x, y, z, _, _, _, _, length = struct.unpack("<QdddBBBdQ", f.read(51))
            track = np.frombuffer(f.read(8 * length), dtype=np.uint32).reshape(-1, 2)
            xyz.append((x, y, z))
            tracks.append(track[:, 0].copy())
    return np.array(xyz), tracks


def fern_targets(folder: Path) -> tuple[Scene, list[tuple[np.ndarray, np.ndarray]]]:
    """The fern inputs and, per input, the pixels [n, 2] and depths [n] of the SfM points it sees."""
    split = load_llff(folder)
    xyz, tracks = read_points3d(folder / "sparse" / "0" / "points3D.bin")
    targets = []
    for k, i in enumerate(split.train_ids):
        seen = np.array([(i + 1) in t for t in tracks])
        uv, z = split.train.cameras[k : k + 1].project(xyz[seen])
        targets.append((uv[0], z[0]))
    return split.train, targets


def synthetic_targets(name: str) -> tuple[Scene, list[tuple[np.ndarray, np.ndarray]]]:
    """A synthetic scene's inputs and, per input, every other pixel centre with its exact depth."""
    scene = wide_baseline_split(name).train
    h, w = scene.cameras.height, scene.cameras.width
    v, u = np.mgrid[0:h:2, 0:w:2]
    pixels = np.stack([u.ravel() + 0.5, v.ravel() + 0.5], 1)
    return scene, [(pixels, d[v.ravel(), u.ravel()]) for d in scene.depths]


def score(scene: Scene, targets: list[tuple[np.ndarray, np.ndarray]]) -> dict[str, dict[str, float]]:
    cfg = preset_config("fast").model
    cams = scene.cameras
    frames = [
        MPIFrame.create(
            cams.K[i],
            cams.world_from_cam[i],
            scene.near,
            scene.far,
            cfg.num_planes,
            cams.width,
            cams.height,
            cfg.margin,
        )
        for i in range(len(scene))
    ]
    images = torch.as_tensor(scene.images).permute(0, 3, 1, 2).float()
    counts = {
        label: dict.fromkeys(("within1", "within2", "targets", "sure", "inside", "sure_targets", "sure_right"), 0)
        for label, *_ in COSTS
    }
    for k, fr in enumerate(frames):
        h, w = (max(2, round(e * cfg.pyramid.scales[0])) for e in fr.extent)
        grid = texel_pixels(fr, h, w).reshape(h, w, 2).numpy()
        inside = (grid >= 0).all(-1) & (grid[..., 0] <= fr.width) & (grid[..., 1] <= fr.height)
        uv, z = targets[k]
        # Nearest texel of each target pixel (the texel grid is regular in reference pixels).
        col = np.round((uv[:, 0] - grid[0, 0, 0]) / (grid[0, 1, 0] - grid[0, 0, 0])).astype(int).clip(0, w - 1)
        row = np.round((uv[:, 1] - grid[0, 0, 1]) / (grid[1, 0, 1] - grid[0, 0, 1])).astype(int).clip(0, h - 1)
        disparity = 1 / fr.depths.numpy()  # decreasing with the plane index
        true_plane = np.interp(1 / z, disparity[::-1], np.arange(len(disparity))[::-1].astype(float))
        for label, cost, temperature, supersample, smoothness, occlusion_aware in COSTS:
            sweep = replace(
                cfg.sweep,
                temperature=temperature,
                occlusion_aware=occlusion_aware,
                cost=cost,
                smoothness=smoothness,
                supersample=supersample,
            )
            probs = plane_sweep_weights(frames, images, k, h, w, sweep)
            best, plane = probs.max(0)
            sure = (best > 0.5).numpy()
            err = np.abs(plane.numpy()[row, col] - true_plane)
            c = counts[label]
            c["within1"] += int((err <= 1).sum())
            c["within2"] += int((err <= 2).sum())
            c["targets"] += len(err)
            c["sure"] += int(sure[inside].sum())
            c["inside"] += int(inside.sum())
            c["sure_targets"] += int(sure[row, col].sum())
            c["sure_right"] += int((sure[row, col] & (err <= 1)).sum())
    return {
        label: {
            "within_1_plane": c["within1"] / c["targets"],
            "within_2_planes": c["within2"] / c["targets"],
            "targets": c["targets"],
            "confident_share": c["sure"] / c["inside"],
            "confident_precision": c["sure_right"] / max(c["sure_targets"], 1),
        }
        for label, c in counts.items()
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=Path("../shared/datasets/llff/fern"))
    ap.add_argument("--out", type=Path, default=Path("bench/reports/current/sweep_accuracy.json"))
    args = ap.parse_args()
    torch.set_grad_enabled(False)
    scenes = {"fern": score(*fern_targets(args.data))}
    for name in WIDE_SCENES:
        scenes[name] = score(*synthetic_targets(name))
    report = {
        "command": "python bench/sweep_accuracy.py",
        "date": datetime.date.today().isoformat(),
        "git_commit": git_commit(),
        "costs": {
            label: {"cost": cost, "temperature": t, "supersample": ss, "smoothness": list(sm), "occlusion_aware": oa}
            for label, cost, t, ss, sm, oa in COSTS
        },
        "scenes": scenes,
    }
    args.out.write_text(json.dumps(report, indent=1) + "\n")
    for name, res in scenes.items():
        for label, r in res.items():
            print(f"{name:8s} {label:10s} " + " ".join(f"{k}={v:.3f}" for k, v in r.items() if k != "targets"))


if __name__ == "__main__":
    main()
