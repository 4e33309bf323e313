"""Would a visibility-aware blend of the MPIs help? Measured on baked synthetic scenes.

Today's blend weighs MPI i per pixel by its camera weight times its coverage. The candidate also
multiplies by ``(V_i / A_i) ** gamma``, the share of MPI i's composite that its own reference
camera saw: with reference transmittance ``T_ref(k) = prod_{j<k} (1 - a_j)`` at the same texel
(the planes are fronto-parallel in the reference camera, so its ray through a texel crosses every
plane at that texel), ``V_i = sum_k T_k a_k T_ref(k)``. Content behind an occluder in the
reference view, which the MPI only learned from the other views, then weighs less.

Usage (after ``cmc bench synthetic --save-dir RUNS``; scenes are read from RUNS/<preset>/<scene>/baked)::

    PYTHONPATH=. python bench/visibility_blend.py --runs RUNS/fast --out bench/reports/current/visibility_blend.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from cmc.config import preset_config
from cmc.data.datasets import WIDE_SCENES, wide_baseline_split
from cmc.eval.bench import report_header
from cmc.eval.metrics import psnr
from cmc.geometry.planes import blend_weights, mean_baseline
from cmc.mpi.rendering import render_texture_image
from cmc.serving.baking import BakedScene

GAMMAS = (0, 1, 2, 4, 8)  # 0 = today's blend


def visible_coverage_texture(premultiplied: torch.Tensor) -> torch.Tensor:
    """[D, 4, h, w] premultiplied RGBA -> [D, 4, h, w] whose composite colour is V (all channels)."""
    a = premultiplied[:, 3:4]
    t_ref = torch.cumprod(torch.cat([torch.ones_like(a[:1]), 1 - a[:-1]]), 0)  # exclusive product
    return torch.cat([(a * t_ref).expand(-1, 3, -1, -1), a], 1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", required=True, help="the preset folder of a `cmc bench synthetic --save-dir` run")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    scores: dict[str, dict[int, list[float]]] = {"halfway": {}, "near": {}}
    for name in WIDE_SCENES:
        split = wide_baseline_split(name)
        baked = BakedScene.load(Path(args.runs) / name / "baked")
        vis_tex = [visible_coverage_texture(f.premultiplied) for f in baked.fields]
        centers = torch.stack([fr.world_from_ref[:3, 3] for fr in baked.frames])
        baseline = mean_baseline(centers)
        for k, kind in enumerate(split.test_kinds):
            K = torch.as_tensor(split.test.cameras.K[k], dtype=torch.float32)
            pose = torch.as_tensor(split.test.cameras.world_from_cam[k], dtype=torch.float32)
            w = blend_weights(centers, pose[:3, 3], baseline)
            W, H = baked.width, baked.height
            outs = [
                render_texture_image(f.premultiplied, fr, K, pose, W, H)
                for f, fr in zip(baked.fields, baked.frames, strict=True)
            ]
            vis = [
                render_texture_image(t, fr, K, pose, W, H).rgb[:, 0]
                for t, fr in zip(vis_tex, baked.frames, strict=True)
            ]
            for gamma in GAMMAS:
                num, den = 0.0, 0.0
                for i, o in enumerate(outs):
                    share = (vis[i] / o.acc.clamp_min(1e-6)).clamp(0, 1)
                    wi = w[i] * o.acc * (share + 1e-3) ** gamma
                    num = num + wi[:, None] * o.rgb / o.acc.clamp_min(1e-6)[:, None]
                    den = den + wi
                rgb = (num / den.clamp_min(1e-8)[:, None]).clamp(0, 1).reshape(H, W, 3).numpy()
                scores[kind].setdefault(gamma, []).append(psnr(rgb, split.test.images[k]))
    report = {
        **report_header(preset_config("fast"), torch.device("cpu")),
        "runs": args.runs,
        "psnr": {kind: {str(g): float(np.mean(v)) for g, v in d.items()} for kind, d in scores.items()},
    }
    Path(args.out).write_text(json.dumps(report, indent=1))
    print(json.dumps(report["psnr"], indent=1))


if __name__ == "__main__":
    main()
