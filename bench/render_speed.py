"""CPU latency of the baked renderer (``BakedScene.render``) on a real-size fern bake.

Builds a 48-plane fern bake: the ``fast`` preset on LLFF fern's three training views (1, 10, 19),
``--steps`` training steps (default 400, the preset's), baked with all planes (``cmc.serving.baking.bake``,
merge 1). The CPU renderer's cost depends on the alphas (it skips empty texel tiles and stops
rays once opaque), so time a fully trained bake: this one, or ``--baked`` of a
``cmc bench llff --save-dir DIR`` run (``DIR/fast/fern/baked``). Then times ``BakedScene.render`` at the
native 504x378 size for the three held-out test poses (views 0, 8, 16) and the three input
poses: one warm-up render per pose, then ``--repeats`` timed renders each, reporting the median
and p90 per view and over all renders.

Usage (repository root)::

    .venv/bin/python bench/render_speed.py [--data ../shared/datasets/llff/fern] [--steps 3]
        [--repeats 7] [--baked DIR] [--before OLD_RENDERING.py] [--out bench/reports/current/render_speed_cpu.json]

``--baked DIR`` reuses a bake already in DIR (or writes the new bake there), so repeated
measurements time the same textures.

``--before OLD.py`` also times an older renderer, alternating with the current one render by
render, so that both see the same machine state (a shared CPU drifts by tens of percent within
minutes): either a version of :mod:`cmc.mpi.rendering` (e.g. ``git show HEAD~1:cmc/mpi/rendering.py >
/tmp/old.py``; its ``render_image`` over the same loaded scene) or of :mod:`cmc.serving.texture_kernel`:
one that takes packed textures (its ``PackedTextures`` built from the loaded textures, its
``render`` on ``--threads``), or one from before that (its ``render_baked_mpi`` per MPI, blended
by :func:`cmc.mpi.rendering.blend`). The report then has a ``before`` block and the agreement of the two
renders (colour PSNR, depth max relative error over covered pixels). Every report also has the
agreement of the current renderer with the torch renderer (:func:`cmc.mpi.rendering.render_image`,
untimed): the quality target.

``--before-baked DIR`` instead times the current renderer on an older bake of the same scene
(e.g. one made before a change to :func:`cmc.serving.baking.bake`), alternating in the same way; the
agreement block then compares the two bakes' renders.

``--threads N``: CPU threads per render of the current renderer (default: one per core).

Memory: the bytes a loaded scene keeps (``BakedScene.nbytes``, the 8-bit textures) and those of
the float32 ``TextureField`` copies the torch renderer samples (built for the agreement check); the
process's resident memory after loading one scene, the increase per four more loaded copies,
and after building the float copies.
"""

from __future__ import annotations

import argparse
import datetime as dt
import importlib.util
import inspect
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path
from types import ModuleType

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from cmc.config import preset_config  # noqa: E402
from cmc.data.datasets import load_llff  # noqa: E402
from cmc.eval.bench import git_commit  # noqa: E402
from cmc.eval.metrics import psnr  # noqa: E402
from cmc.method.training import Trainer  # noqa: E402
from cmc.mpi.rendering import ImageOutput, RayOutput, blend, blend_selection, render_image  # noqa: E402
from cmc.serving.baking import MANIFEST, BakedScene, bake  # noqa: E402


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def build_bake(data: Path, steps: int, out_dir: Path) -> dict:
    """Train the ``fast`` preset for ``steps`` steps on fern and bake all planes to ``out_dir``."""
    split = load_llff(data)
    t0 = time.perf_counter()
    trainer = Trainer(split.train, preset_config("fast", steps=steps))
    trainer.fit()
    bake(trainer.model, out_dir)
    return {"train_steps": steps, "build_seconds": time.perf_counter() - t0}


def load_rendering(path: Path) -> ModuleType:
    """Another version of cmc/mpi/rendering.py, imported beside the current one."""
    spec = importlib.util.spec_from_file_location("rendering_before", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def rss_mb() -> float:
    """This process's resident memory now, MiB (Linux /proc)."""
    return int(Path("/proc/self/statm").read_text().split()[1]) * 4096 / 2**20


def summary(ms: list[float]) -> dict:
    return {"median_ms": statistics.median(ms), "p90_ms": float(np.percentile(np.asarray(ms), 90))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared/datasets/llff/fern")
    ap.add_argument("--steps", type=int, default=400, help="training steps before baking")
    ap.add_argument("--repeats", type=int, default=7, help="timed renders per pose (after one warm-up)")
    ap.add_argument("--baked", type=Path, default=None, help="reuse / keep the bake in this folder")
    ap.add_argument(
        "--before",
        type=Path,
        default=None,
        help="an older cmc/mpi/rendering.py or texture_kernel.py to time alternately",
    )
    ap.add_argument(
        "--before-baked",
        type=Path,
        default=None,
        help="an older bake of the same scene to time alternately, with the current renderer",
    )
    ap.add_argument("--threads", type=int, default=None, help="CPU threads per render (default: one per core)")
    ap.add_argument("--out", type=Path, default=ROOT / "bench/reports/current/render_speed_cpu.json")
    args = ap.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        baked_dir = args.baked or Path(tmp) / "baked"
        build = {"reused_bake": True}
        if not (baked_dir / MANIFEST).exists():
            build = {"reused_bake": False, **build_bake(args.data, args.steps, baked_dir)}
        rss_before_load = rss_mb()
        baked = BakedScene.load(baked_dir)
        memory = {"rss_before_load_mb": rss_before_load, "rss_loaded_mb": rss_mb(), "scene_mb": baked.nbytes / 2**20}
        # Resident memory per further loaded scene (what a render cache pays per scene).
        extra = [BakedScene.load(baked_dir) for _ in range(4)]
        memory["rss_per_more_scene_mb"] = (rss_mb() - memory["rss_loaded_mb"]) / len(extra)
        del extra
    split = load_llff(args.data)
    poses = [("test", split.test_ids[k], split.test.cameras, k) for k in range(len(split.test))]
    poses += [("input", split.train_ids[k], split.train.cameras, k) for k in range(len(split.train))]

    renderers = {"after": lambda K, pose, w, h: baked.render(K, pose, w, h, threads=args.threads)}
    if args.before and args.before_baked:
        ap.error("--before and --before-baked: one at a time")
    if args.before_baked:
        baked_before = BakedScene.load(args.before_baked)
        renderers["before"] = lambda K, pose, w, h: baked_before.render(K, pose, w, h, threads=args.threads)
    if args.before:
        old = load_rendering(args.before)
        if hasattr(old, "PackedTextures"):  # a texture_kernel of packed textures: its own copy of them
            old_packed = old.PackedTextures.pack([np.ascontiguousarray(t) for t in baked.textures])
            old_geometry = [old.MPIGeometry.from_frame(f) for f in baked.frames]
            # The bake's colour sampling, where the old kernel has a choice (bicubic came later).
            sampling = (
                {"colour_interpolation": baked.colour_interpolation}
                if "colour_interpolation" in inspect.signature(old.render).parameters
                else {}
            )

            def render_before(K, pose, w, h):
                P_t = torch.as_tensor(np.asarray(pose), dtype=torch.float32)
                weights, use = blend_selection(baked.frames, P_t)
                rgb, depth, acc = old.render(
                    old_packed, old_geometry, weights.numpy(), use, K, pose, w, h, threads=args.threads, **sampling
                )
                return ImageOutput(torch.from_numpy(rgb), torch.from_numpy(depth), torch.from_numpy(acc))

            renderers["before"] = render_before
        elif hasattr(old, "render_baked_mpi"):  # a texture_kernel: 8-bit textures per MPI, then the blend
            textures = [np.ascontiguousarray(t) for t in baked.textures]
            occupancy = [old.occupancy(t) for t in textures]

            def render_before(K, pose, w, h):
                P_t = torch.as_tensor(np.asarray(pose), dtype=torch.float32)
                weights, use = blend_selection(baked.frames, P_t)
                outs = []
                for i in use:
                    rgb, depth, acc = old.render_baked_mpi(textures[i], occupancy[i], baked.frames[i], K, pose, w, h)
                    outs.append(
                        RayOutput(
                            torch.from_numpy(rgb).reshape(-1, 3),
                            torch.from_numpy(depth).reshape(-1),
                            torch.from_numpy(acc).reshape(-1),
                        )
                    )
                out = blend(outs, weights[use])
                return ImageOutput(out.rgb.reshape(h, w, 3), out.depth.reshape(h, w), out.acc.reshape(h, w))

            renderers["before"] = render_before
        else:
            renderers["before"] = lambda K, pose, w, h: old.render_image(baked.fields, baked.frames, K, pose, w, h)
    fields = baked.fields
    memory["float_fields_mb"] = sum(b.nbytes for f in fields for b in f.buffers()) / 2**20
    memory["rss_with_float_fields_mb"] = rss_mb()
    views: dict[str, list[dict]] = {name: [] for name in renderers}
    all_ms: dict[str, list[float]] = {name: [] for name in renderers}
    agreement, agreement_torch = [], []

    def agree(a, b, view):
        """How far render ``a`` is from ``b`` (each a BakedRender of NumPy arrays or an ImageOutput of tensors)."""
        a_rgb, a_depth, b_rgb, b_depth, b_acc = (np.asarray(x) for x in (a.rgb, a.depth, b.rgb, b.depth, b.acc))
        covered = b_acc > 1e-3
        rel = (np.abs(a_depth - b_depth) / b_depth)[covered]
        return {
            "view": int(view),
            "psnr_db": psnr(a_rgb, b_rgb),
            "depth_max_rel": float(rel.max()) if len(rel) else 0.0,
            "covered": float(covered.mean()),
        }

    for kind, view, cams, k in poses:
        K, pose, w, h = cams.K[k], cams.world_from_cam[k], cams.width, cams.height
        outs = {name: render(K, pose, w, h) for name, render in renderers.items()}  # warm-up
        agreement_torch.append(agree(outs["after"], render_image(baked.fields, baked.frames, K, pose, w, h), view))
        if "before" in outs:
            agreement.append(agree(outs["after"], outs["before"], view))
        ms: dict[str, list[float]] = {name: [] for name in renderers}
        for r in range(args.repeats):
            for name in list(renderers)[:: 1 if r % 2 == 0 else -1]:  # alternate the order
                t = time.perf_counter()
                renderers[name](K, pose, w, h)
                ms[name].append(1000 * (time.perf_counter() - t))
        line = f"{kind:5s} view {view:2d}:"
        for name, times in ms.items():
            all_ms[name] += times
            views[name].append({"kind": kind, "view": int(view), **summary(times), "ms": times})
            line += f"  {name} median {summary(times)['median_ms']:6.1f} ms p90 {summary(times)['p90_ms']:6.1f} ms"
        print(line)
    frame = baked.frames[0]
    report = {
        "benchmark": "baked render latency (BakedScene.render), LLFF fern, CPU",
        "command": "python bench/render_speed.py " + " ".join(sys.argv[1:]),
        "date": dt.datetime.now().isoformat(timespec="seconds"),
        "git_commit": git_commit(),
        "torch": torch.__version__,
        "machine": {
            "cpu": cpu_model(),
            "cores": torch.multiprocessing.cpu_count(),
            "torch_threads": torch.get_num_threads(),
            "cpu_capability": torch.backends.cpu.get_cpu_capability(),
            "python": platform.python_version(),
        },
        "scene": {
            "name": args.data.name,
            "render_size": [baked.width, baked.height],
            "mpis": len(baked.frames),
            "planes_per_mpi": len(frame.depths),
            "tile": list(baked.textures[0].shape[1:3]),
            "margin": list(frame.margin),
            **build,
        },
        "memory": memory,
        "repeats_per_view": args.repeats,
        "warmup_per_view": 1,
        "threads": args.threads or (os.cpu_count() or 1),
        "overall": summary(all_ms["after"]),
        "views": views["after"],
        "agreement_with_torch": agreement_torch,
    }
    if "before" in renderers:
        report["before"] = {
            "rendering": str(args.before) if args.before else "the current renderer",
            "baked": str(args.before_baked) if args.before_baked else None,
            "interleaved": True,
            "overall": summary(all_ms["before"]),
            "views": views["before"],
            "agreement_with_after": agreement,
        }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=1) + "\n")
    for name in renderers:
        s = summary(all_ms[name])
        print(f"overall {name}: median {s['median_ms']:.1f} ms  p90 {s['p90_ms']:.1f} ms")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
