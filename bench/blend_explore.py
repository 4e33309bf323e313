"""Ways of blending the per-view MPIs of one trained model, scored on the validation views.

Blending happens only at render time, so each scene is trained once (the ``fast`` preset, baked to
``--bakes/<scene>``, reused when there) and every blend is scored on the same bake. Each MPI's
render of a target view also carries how much of what it shows its reference photo saw: the
target's compositing weights over ``seen_k = T_ref,k * inside`` (``T_ref,k`` the transmittance
from the reference camera to plane k at the same texel, ``inside`` 1 where the texel lies in the
reference photo, 0 in the margin), rendered as a colour. A blend then weighs MPI i at a pixel by
the renderer's per-camera weight times a function of that share, or (``consensus_<sigma>``) by
how well its depth there agrees with the other MPIs' (:func:`consensus`), or
(``inverse_distance_<q>``) by a flatter or steeper power of the camera distance. Test views are scored
too (``--views``), only to see afterwards whether validation predicted them.

Usage::

    PYTHONPATH=. CMC_LPIPS_DIR=../shared/weights .venv/bin/python bench/blend_explore.py \\
        --scenes fern,room,trex --bakes /tmp/bakes --out bench/reports/current/blend_explore.json
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from cmc.config import preset_config
from cmc.data.datasets import load_llff
from cmc.eval.bench import report_header
from cmc.eval.metrics import LPIPS, _gaussian_taps, psnr, ssim
from cmc.method.training import Trainer
from cmc.mpi.rendering import RayOutput, blend_selection, render_texture_image
from cmc.serving.baking import MANIFEST, BakedScene, bake


def seen_maps(rgba: torch.Tensor, margin: tuple[float, float]) -> torch.Tensor:
    """[D, h, w]: per plane texel, the share of the reference camera's ray that reaches it
    (transmittance through the planes in front, nearest first) where the texel lies inside the
    reference photo, 0 in the margin. ``rgba`` [D, 4, h, w] straight alpha."""
    alpha = rgba[:, 3]
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:1]), 1 - alpha[:-1]]), 0)
    D, h, w = alpha.shape
    gy = (torch.arange(h, dtype=torch.float32) + 0.5) / h * 2 - 1
    gx = (torch.arange(w, dtype=torch.float32) + 0.5) / w * 2 - 1
    inside = ((gy.abs()[:, None] <= 1 / margin[1]) & (gx.abs()[None, :] <= 1 / margin[0])).float()
    return trans * inside


def per_mpi_renders(
    baked: BakedScene, K: np.ndarray, pose: np.ndarray
) -> tuple[torch.Tensor, list[RayOutput], list[torch.Tensor]]:
    """Per-camera blend weights [N], every MPI's render of the view, and every MPI's seen share [R]
    (the compositing weights over :func:`seen_maps`, divided by its coverage)."""
    K_t = torch.as_tensor(K, dtype=torch.float32)
    P_t = torch.as_tensor(pose, dtype=torch.float32)
    weights, _ = blend_selection(baked.frames, P_t)
    outs, seen = [], []
    for f, frame in zip(baked.fields, baked.frames, strict=True):
        bicubic = f.colour_interpolation == "bicubic"  # as cmc.mpi.rendering.render_image samples colour
        straight = f.rgba[:, :3] if bicubic else None
        outs.append(
            render_texture_image(f.premultiplied, frame, K_t, P_t, baked.width, baked.height, straight_rgb=straight)
        )
        s = seen_maps(f.rgba, frame.margin)[:, None]
        alpha = f.premultiplied[:, 3:]
        tex = torch.cat([s * alpha, s * alpha, s * alpha, alpha], 1)
        o = render_texture_image(tex, frame, K_t, P_t, baked.width, baked.height)
        seen.append(o.rgb[:, 0] / o.acc.clamp_min(1e-6))
    return weights, outs, seen


def blend_with(outs: list[RayOutput], weights: torch.Tensor, extra: list[torch.Tensor]) -> torch.Tensor:
    """Colour [R, 3]: ``sum_i w_i e_i C_i / sum_i w_i e_i a_i`` times the largest coverage, with
    per-ray factors ``e_i`` (all 1: :func:`cmc.mpi.rendering.blend`)."""
    acc_all = torch.stack([o.acc for o in outs])
    W = torch.stack([weights[i] * extra[i] for i in range(len(outs))])  # [N, R]
    total = (acc_all * W).sum(0).clamp_min(1e-8)
    rgb = sum(W[i][:, None] * o.rgb for i, o in enumerate(outs)) / total[:, None]
    return (rgb * acc_all.max(0).values[:, None]).clamp(0, 1)


def consensus(
    outs: list[RayOutput], weights: torch.Tensor, sigma: float, near: float, far: float
) -> list[torch.Tensor]:
    """Per-ray factors ``e_i``: how well MPI i's depth agrees with the others', the blend-weighted
    mean over MPIs j (itself included) of ``exp(-((s_i - s_j) / sigma)^2 / 2)`` on normalised
    disparity ``s = (1/z - 1/far) / (1/near - 1/far)`` (``sigma`` in those units; a plane spacing
    is 1 / (D - 1)). Where two MPIs agree on a surface and a third does not, the third weighs less."""
    s = torch.stack([(1 / o.depth.clamp_min(0.5 * near) - 1 / far) / (1 / near - 1 / far) for o in outs])  # [N, R]
    w = torch.stack([weights[j] * outs[j].acc for j in range(len(outs))])  # [N, R]
    agree = torch.exp(-0.5 * ((s[:, None] - s[None]) / sigma) ** 2)  # [N, N, R]
    return list((agree * w[None]).sum(1) / w.sum(0).clamp_min(1e-8))


def _gaussian_blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """x [C, H, W] blurred by a Gaussian of ``sigma`` pixels (radius 3 sigma, zero outside, separable)."""
    k = _gaussian_taps(sigma, 3.0).float()
    radius = len(k) // 2
    x = torch.nn.functional.conv2d(x[:, None], k.view(1, 1, 1, -1), padding=(0, radius))
    return torch.nn.functional.conv2d(x, k.view(1, 1, -1, 1), padding=(radius, 0))[:, 0]


def blend_multiband(
    outs: list[RayOutput], weights: torch.Tensor, height: int, width: int, sigma: float, q: float
) -> torch.Tensor:
    """Colour [R, 3], two bands blended apart: each MPI's image split at a Gaussian of ``sigma``
    pixels (normalised by its blurred coverage), the low band blended with the renderer's weights
    (:func:`blend_with` with factors 1), the detail with the per-camera weights raised to q / 2 (q
    = 2: the renderer's blend exactly; ``q = inf``: at each pixel the detail of the covering MPI
    the renderer weighs most), then times the largest coverage. Where the MPIs' details disagree
    (misregistered texture), the average blurs it; this keeps one MPI's detail."""
    acc = torch.stack([o.acc for o in outs]).reshape(-1, height, width)  # [N, H, W]
    prem = torch.stack([o.rgb.T.reshape(3, height, width) for o in outs])  # [N, 3, H, W]
    straight = prem / acc[:, None].clamp_min(1e-6)
    low = torch.stack([_gaussian_blur(p, sigma) for p in prem]) / torch.stack(
        [_gaussian_blur(a[None], sigma) for a in acc]
    ).clamp_min(1e-6)
    detail = straight - low
    w = weights[:, None, None] * acc  # [N, H, W]
    if q == float("inf"):
        v = torch.zeros_like(w).scatter_(0, w.argmax(0, keepdim=True), 1.0) * (acc > 0)
    else:
        v = weights[:, None, None] ** (q / 2) * acc
    low_b = (w[:, None] * low).sum(0) / w.sum(0).clamp_min(1e-8)
    detail_b = (v[:, None] * detail).sum(0) / v.sum(0).clamp_min(1e-8)
    rgb = (low_b + detail_b) * acc.max(0).values
    return rgb.clamp(0, 1).reshape(3, -1).T


MULTIBAND = [(1.0, 8.0), (2.0, 8.0), (4.0, 8.0), (2.0, 4.0), (2.0, float("inf")), (1.0, float("inf"))]  # (sigma, q)


BLENDS: dict[str, Callable[[torch.Tensor], torch.Tensor]] = {
    "renderer": lambda s: torch.ones_like(s),
    "seen_eps0.3": lambda s: s + 0.3,
    "seen_eps0.1": lambda s: s + 0.1,
    "seen_eps0.03": lambda s: s + 0.03,
    "seen_sq_eps0.03": lambda s: s * s + 0.03,
}
CONSENSUS_SIGMAS = (0.5, 1.0, 2.0, 4.0)  # in plane spacings: the blends "consensus_<sigma>"
# The renderer's per-camera weights (inverse squared distance) raised to q / 2 and renormalised:
# the blends "inverse_distance_<q>" (q = 2: the renderer's; 0: the MPIs alike).
DISTANCE_POWERS = (0.0, 0.5, 1.0)


def train_or_load(scene: str, data: Path, bakes: Path) -> tuple[Any, BakedScene, float]:
    split = load_llff(data / scene)
    folder = bakes / scene
    train_s = float("nan")
    if not (folder / MANIFEST).exists():
        t0 = time.perf_counter()
        trainer = Trainer(split.train, preset_config("fast"), torch.device("cpu"))
        trainer.fit()
        train_s = time.perf_counter() - t0
        bake(trainer.model, folder)
    return split, BakedScene.load(folder), train_s


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default="../shared/datasets/llff")
    ap.add_argument("--scenes", default="fern,room,trex")
    ap.add_argument("--bakes", default="/tmp/bakes")
    ap.add_argument("--train-only", action="store_true")
    ap.add_argument("--views", default="val,test", help="which views to score: val, test or both")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    torch.set_num_threads(2)
    lpips = None if args.train_only else LPIPS("vgg", weights_dir=os.environ.get("CMC_LPIPS_DIR"))
    report: dict[str, Any] = {**report_header(preset_config("fast"), torch.device("cpu")), "scenes": {}}
    for scene in args.scenes.split(","):
        split, baked, train_s = train_or_load(scene, Path(args.data), Path(args.bakes))
        print(scene, "trained" if train_s == train_s else "loaded", train_s, flush=True)
        if args.train_only:
            continue
        rec: dict[str, Any] = {"train_s": train_s}
        for kind, views in (("val", split.val), ("test", split.test)):
            if kind not in args.views.split(","):
                continue
            scores: dict[str, list[tuple[float, float, float]]] = {}
            depths = torch.cat([f.depths for f in baked.frames])
            near, far, spacing = float(depths.min()), float(depths.max()), 1 / (len(baked.frames[0].depths) - 1)
            for k in range(len(views.names)):
                weights, outs, seen = per_mpi_renders(baked, views.cameras.K[k], views.cameras.world_from_cam[k])
                gt = views.images[k]
                extras = {name: [fn(s) for s in seen] for name, fn in BLENDS.items()}
                for sigma in CONSENSUS_SIGMAS:
                    extras[f"consensus_{sigma}"] = consensus(outs, weights, sigma * spacing, near, far)
                for q in DISTANCE_POWERS:  # factors w_i^(q / 2 - 1): the weights become w_i^(q / 2)
                    extras[f"inverse_distance_{q}"] = [
                        torch.full_like(s, float(weights[i]) ** (q / 2 - 1)) for i, s in enumerate(seen)
                    ]
                blends = {name: blend_with(outs, weights, extra) for name, extra in extras.items()}
                for sigma, q in MULTIBAND:
                    blends[f"multiband_{sigma}_{q}"] = blend_multiband(
                        outs, weights, baked.height, baked.width, sigma, q
                    )
                for name, flat in blends.items():
                    rgb = flat.reshape(baked.height, baked.width, 3).numpy()
                    scores.setdefault(name, []).append((psnr(rgb, gt), ssim(rgb, gt), lpips(rgb, gt)))
            rec[kind] = {b: [round(float(x), 4) for x in np.mean(v, 0)] for b, v in scores.items()}
            print(scene, kind, json.dumps(rec[kind]), flush=True)
        report["scenes"][scene] = rec
        Path(args.out).write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
