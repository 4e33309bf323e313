"""The ``cmc`` command line: train, render, bench, demo. Run ``cmc COMMAND --help``."""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import sys
from dataclasses import replace
from importlib.metadata import entry_points
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from cmc.config import PRESETS, preset_config, with_settings
from cmc.data.datasets import CAMERAS_FILE, WIDE_SCENES, load_scene_folder, save_image
from cmc.errors import CMCError, ConfigError
from cmc.geometry.camera_paths import PATH_KINDS
from cmc.geometry.cameras import load_camera_file
from cmc.method.training import Progress, Trainer, TrainingCancelled
from cmc.serving.baking import BakedScene, bake


class ProgressBar:
    """A tqdm bar fed by training progress hooks."""

    def __init__(self, desc: str, total: int):
        self.bar = tqdm(total=total, desc=desc, unit="step", dynamic_ncols=True)

    def __call__(self, p: Progress) -> None:
        self.bar.n = p.step
        shown = {k: f"{v:.4f}" for k, v in p.losses.items() if k in ("mse", "ac", "dc") and (k == "mse" or v)}
        self.bar.set_postfix(shown, refresh=False)
        self.bar.refresh()

    def close(self) -> None:
        self.bar.close()


def _device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError("--device cuda asked for, but torch sees no CUDA device")
    return torch.device(name)


def _config(args: argparse.Namespace):
    overrides = {k: v for k, v in (("steps", args.steps), ("seed", args.seed)) if v is not None}
    return with_settings(preset_config(args.preset, **overrides), getattr(args, "set", None) or [])


def cmd_train(args: argparse.Namespace) -> None:
    scene = load_scene_folder(args.scene)
    cfg = _config(args)
    out = Path(args.out)
    trainer = Trainer(scene, cfg, _device(args.device))
    bar = ProgressBar("train", cfg.steps)
    stop = []  # Ctrl-C asks the trainer to checkpoint and stop at the end of the step
    previous = signal.signal(signal.SIGINT, lambda *_: stop.append(True))
    try:
        result = trainer.fit(
            on_progress=bar,
            should_stop=lambda: bool(stop),
            checkpoint_path=out / "checkpoint.pt",
            resume=not args.restart,
        )
    finally:
        signal.signal(signal.SIGINT, previous)
        bar.close()
    baked = bake(trainer.model, out / "baked", scale=args.bake_scale, merge=args.bake_merge)
    (out / "train.json").write_text(
        json.dumps(
            {"steps": result.steps, "seconds_this_run": result.seconds, "config": cfg.to_dict(), "baked": str(baked)},
            indent=1,
        )
    )
    print(f"trained {result.steps} steps; baked MPIs in {baked}")


def cmd_render(args: argparse.Namespace) -> None:
    if (args.cameras is None) == (args.path is None):
        raise ConfigError("give exactly one of --cameras FILE (still views) or --path spiral|orbit|dolly (a video)")
    if args.path is None and (args.frames is not None or args.fps is not None):
        raise ConfigError("--frames and --fps apply to --path videos only")
    baked = BakedScene.load(args.baked)
    if args.path is not None:
        _render_video(baked, args)
        return
    cams = load_camera_file(args.cameras)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    from cmc.eval.diagnostics import depth_preview

    for i, name in enumerate(tqdm(cams.file_paths, desc="render", unit="view")):
        c = cams.cameras[i]
        r = baked.render(c.K[0], c.world_from_cam[0], c.width, c.height)
        stem = Path(name).stem
        save_image(out / f"{stem}.png", r.rgb)
        np.save(out / f"{stem}_depth.npy", r.depth)
        save_image(out / f"{stem}_depth.png", depth_preview(r.depth, baked.near, baked.far))
    print(f"rendered {len(cams.file_paths)} views to {out} (depth: float32 .npy, camera z in scene units)")


def _render_video(baked: BakedScene, args: argparse.Namespace) -> None:
    from cmc.serving.video import DEFAULT_FPS, DEFAULT_FRAMES, render_path_video

    frames = DEFAULT_FRAMES if args.frames is None else args.frames
    fps = DEFAULT_FPS if args.fps is None else args.fps
    if frames < 1:
        raise ConfigError(f"--frames must be at least 1, got {frames}")
    if not fps > 0:
        raise ConfigError(f"--fps must be positive, got {fps}")
    out = Path(args.out)
    if out.is_dir():
        out = out / f"{args.path}.mp4"
    out.parent.mkdir(parents=True, exist_ok=True)
    bar = tqdm(total=frames, desc=f"render {args.path}", unit="frame", dynamic_ncols=True)
    try:
        render_path_video(baked, args.path, out, num_frames=frames, fps=fps, on_frame=lambda i, n: bar.update(1))
    finally:
        bar.close()
    print(f"wrote {out}: {frames} frames at {fps:g} fps (H.264 MP4)")


ABLATIONS = {
    "mse": dict(lambda_dc_input=0.0, lambda_ac=0.0, lambda_dc=0.0),
    "mse+dcI": dict(lambda_dc_input=1.0, lambda_ac=0.0, lambda_dc=0.0),
    "mse+dcI+ac": dict(lambda_dc_input=1.0, lambda_ac=1.0, lambda_dc=0.0),
    "full": dict(lambda_dc_input=1.0, lambda_ac=1.0, lambda_dc=1.0),
}


def _input_gains(text: str) -> list[float]:
    try:
        gains = [float(g) for g in text.split(",")]
    except ValueError:
        gains = []
    if len(gains) != 3 or not all(0 < g < 10 for g in gains):
        raise ConfigError(f"--input-gains needs three factors between 0 and 10, e.g. 1,1.15,0.87; got {text!r}")
    return gains


def cmd_bench(args: argparse.Namespace) -> None:
    from cmc.eval.bench import run_llff_bench, run_synthetic_bench, write_report

    if args.dataset == "llff" and not args.data:
        raise ConfigError("the llff benchmark needs --data (the folder holding the LLFF scene folders)")
    lpips_dir = args.lpips_weights or os.environ.get("CMC_LPIPS_DIR")
    if not lpips_dir:
        raise ConfigError("LPIPS weights needed: pass --lpips-weights DIR or set CMC_LPIPS_DIR")
    device = _device(args.device)
    gains = _input_gains(args.input_gains) if args.input_gains else None
    if gains is not None and args.dataset != "synthetic":
        raise ConfigError("--input-gains is for the synthetic benchmark")
    if args.views != "test" and args.dataset != "llff":
        raise ConfigError("--views is for the llff benchmark (the synthetic set has no validation views)")
    if not 0 < args.near_scale <= 1:
        raise ConfigError(f"--near-scale must be in (0, 1], got {args.near_scale}")
    base = _config(args)
    variants = {"": base}
    if args.ablation:
        variants = {f"-{k}": replace(base, loss=replace(base.loss, **v)) for k, v in ABLATIONS.items()}
    for suffix, cfg in variants.items():
        bar: dict[str, ProgressBar] = {}

        def hook(scene: str, p: Progress, bar=bar, suffix=suffix, steps=cfg.steps) -> None:
            if scene not in bar:
                bar[scene] = ProgressBar(f"{scene}{suffix}", steps)
            bar[scene](p)

        save = Path(args.save_dir) / (args.preset + suffix) if args.save_dir else None
        if args.dataset == "llff":
            scenes = (args.scenes or "fern").split(",")
            report = run_llff_bench(
                Path(args.data), scenes, cfg, device, lpips_dir, save, hook, args.views, args.near_scale
            )
        else:
            scenes = args.scenes.split(",") if args.scenes else list(WIDE_SCENES)
            report = run_synthetic_bench(
                scenes, cfg, device, lpips_dir, save, hook, input_gains=gains, near_scale=args.near_scale
            )
        for b in bar.values():
            b.close()
        if suffix:
            report["ablation"] = suffix[1:]
        out = Path(args.out)
        out = out.with_name(out.stem + suffix + out.suffix)
        write_report(report, out)
        print(out.with_suffix(".md").read_text())
        print(f"wrote {out} and {out.with_suffix('.md')}")


def cmd_export(args: argparse.Namespace) -> None:
    from cmc.serving.gltf import export_glb

    data, index = export_glb(args.baked, args.mpi)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(data)
    print(f"wrote {out} ({len(data) / 1e6:.1f} MB): the planes of MPI {index} and the input cameras")


def cmd_demo(args: argparse.Namespace) -> None:
    from cmc.demo import run_demo

    bar = ProgressBar("demo", args.steps)
    try:
        summary = run_demo(Path(args.out), steps=args.steps, on_progress=bar)
    finally:
        bar.close()
    print(json.dumps(summary, indent=1))
    print(f"outputs in {args.out}/")


def cmd_poses(args: argparse.Namespace) -> None:
    from cmc.poses import IMAGES_DIR, PoseOptions, estimate_poses, poses_from_client

    out = Path(args.out)
    scene_dir = out.parent if out.suffix.lower() == ".json" else out
    options = PoseOptions(
        long_side=args.long_side,
        max_sift_size=args.max_sift_size,
        seed=args.seed,
        work_dir=args.work_dir,
        convention=args.convention,
        verbose=args.verbose,
    )
    if args.cameras:
        result = poses_from_client(args.images, args.cameras, scene_dir, options)
    else:
        result = estimate_poses(args.images, scene_dir, options)
    written = result.cameras_path
    if out.suffix.lower() == ".json" and out.name != CAMERAS_FILE:
        shutil.copyfile(written, out)
        written = out
    nf = result.camera_file.near_far
    assert nf is not None
    cams = result.camera_file.cameras
    print(
        f"poses ({result.stats['method']}): {len(cams)} photos at {cams.width}x{cams.height}, "
        f"near {nf[:, 0].min():.4g}, far {nf[:, 1].max():.4g}"
    )
    for stage, seconds in result.timings.items():
        print(f"  {stage:<14}{seconds:8.2f} s")
    images = scene_dir / IMAGES_DIR
    print(f"wrote {written} and {len(result.image_paths)} images in {images}; train with: cmc train {scene_dir}")


def _train_options(sp: argparse.ArgumentParser) -> None:
    """The options of every command that trains: preset, steps, seed, device."""
    sp.add_argument("--preset", choices=PRESETS, default="fast", help="model/training preset (default fast)")
    sp.add_argument("--steps", type=int, help="training steps (default: the preset's)")
    sp.add_argument("--seed", type=int, help="random seed (default 0)")
    sp.add_argument("--device", default="auto", help="cpu, cuda, cuda:N or auto (default)")


def _add_train(sub: argparse._SubParsersAction) -> None:
    """``cmc train``."""
    t = sub.add_parser("train", help="train on a scene folder (images + cameras.json), checkpoint and bake")
    t.add_argument("scene", help="scene folder with cameras.json (transforms.json shape, near/far)")
    t.add_argument("--out", required=True, help="output folder: checkpoint.pt, baked/, train.json")
    t.add_argument("--restart", action="store_true", help="ignore an existing checkpoint instead of resuming")
    t.add_argument("--bake-scale", type=float, default=1.0, help="baked texture resolution factor")
    t.add_argument(
        "--bake-merge",
        type=int,
        default=1,
        help="composite this many adjacent planes into one when baking (faster renders)",
    )
    _train_options(t)
    t.set_defaults(func=cmd_train)


def _add_render(sub: argparse._SubParsersAction) -> None:
    """``cmc render``."""
    r = sub.add_parser(
        "render",
        help="render a baked MPI: colour and depth of every camera in a cameras file, or a camera-path video",
    )
    r.add_argument("baked", help="baked folder (mpi.json + atlases)")
    r.add_argument("--cameras", help="cameras file (transforms.json shape): one PNG + depth per camera")
    r.add_argument("--path", choices=PATH_KINDS, help="instead of --cameras: an H.264 MP4 along this camera path")
    r.add_argument("--out", required=True, help="output folder (--cameras) or .mp4 file (--path)")
    r.add_argument("--frames", type=int, help="video frames along the path (default 120)")
    r.add_argument("--fps", type=float, help="video frames per second (default 30)")
    r.set_defaults(func=cmd_render)


def _add_export(sub: argparse._SubParsersAction) -> None:
    """``cmc export``."""
    x = sub.add_parser("export", help="export a baked MPI as glTF (.glb): textured planes and the input cameras")
    x.add_argument("baked", help="baked folder (mpi.json + atlases)")
    x.add_argument("--out", required=True, help="the .glb file to write")
    x.add_argument("--mpi", type=int, help="which MPI (default: the one nearest the mean input camera)")
    x.set_defaults(func=cmd_export)


def _add_bench(sub: argparse._SubParsersAction) -> None:
    """``cmc bench``."""
    b = sub.add_parser("bench", help="benchmark: LLFF with the paper's protocol, or the wide-baseline synthetic scenes")
    b.add_argument("dataset", choices=["llff", "synthetic"])
    b.add_argument("--data", help="llff: folder holding the LLFF scene folders")
    b.add_argument(
        "--scenes", help=f"comma-separated scene names (default: llff fern; synthetic {','.join(WIDE_SCENES)})"
    )
    b.add_argument("--out", required=True, help="report path (.json; a .md table is written beside it)")
    b.add_argument("--lpips-weights", help="folder with lpips_alex.pth and lpips_vgg.pth (or CMC_LPIPS_DIR)")
    b.add_argument("--save-dir", help="also keep baked MPIs and test renders here")
    b.add_argument("--ablation", action="store_true", help="run the paper's loss ablation (4 runs)")
    b.add_argument(
        "--input-gains",
        help="synthetic: comma-separated factors on the three input photos' colours (per-shot exposure, "
        "as phones set it; the test views keep theirs), e.g. 1,1.15,0.87",
    )
    b.add_argument(
        "--views",
        choices=["test", "val"],
        default="test",
        help="llff: score the test views (the protocol's) or the validation views, neither trained on nor "
        "tested (choose settings on these)",
    )
    b.add_argument(
        "--near-scale",
        type=float,
        default=1.0,
        help="train with every near bound times this (e.g. 0.25: bounds 4x too loose, as a stray SfM point gives)",
    )
    _train_options(b)
    b.add_argument(
        "--set",
        action="append",
        metavar="KEY=VALUE",
        help="override a configuration field, e.g. loss.lambda_ac=0.5 or model.num_planes=32 (repeatable)",
    )
    b.set_defaults(func=cmd_bench)


def _add_demo(sub: argparse._SubParsersAction) -> None:
    """``cmc demo``."""
    d = sub.add_parser("demo", help="reconstruct a synthetic scene from 3 views on the CPU")
    d.add_argument("--out", default="demo-output", help="output folder (default demo-output)")
    d.add_argument("--steps", type=int, default=300, help="training steps (default 300)")
    d.set_defaults(func=cmd_demo)


def _add_poses(sub: argparse._SubParsersAction) -> None:
    """``cmc poses``."""
    ps = sub.add_parser(
        "poses",
        help="cameras and near/far for a few photos (pycolmap SfM, or the app's poses); writes a scene folder",
    )
    ps.add_argument("images", nargs="+", help="the photos (JPEG, PNG, WebP or HEIC)")
    ps.add_argument(
        "--out",
        required=True,
        help="scene folder to write (images/, cameras.json, originals/); a path ending in .json names "
        "the cameras file and its folder is the scene folder",
    )
    ps.add_argument("--cameras", help="the app's cameras (transforms.json shape) instead of structure from motion")
    ps.add_argument("--long-side", type=int, default=504, help="long side of the working images, pixels (default 504)")
    ps.add_argument("--max-sift-size", type=int, default=1600, help="long side SIFT runs at, pixels (default 1600)")
    ps.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    ps.add_argument(
        "--convention", choices=["opengl", "opencv"], help="camera axes to write (default opengl, or the input file's)"
    )
    ps.add_argument("--work-dir", help="keep COLMAP's database and sparse model here (default: a temporary folder)")
    ps.add_argument("--verbose", action="store_true", help="show COLMAP's log")
    ps.set_defaults(func=cmd_poses)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="cmc", description="Few-shot novel view synthesis with per-view MPIs (CMC).")
    sub = p.add_subparsers(dest="command", required=True)
    for add in (_add_train, _add_render, _add_export, _add_bench, _add_demo, _add_poses):
        add(sub)
    _register_plugin_commands(sub)
    return p


def _register_plugin_commands(sub: argparse._SubParsersAction) -> None:
    """Commands other packages add through the ``cmc.commands`` entry point (pyproject.toml):
    ``cmc serve`` and ``cmc new-api-key`` of the REST service. Each entry is a function taking
    the subparsers; the library imports none of them itself."""
    for entry in entry_points(group="cmc.commands"):
        entry.load()(sub)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        args.func(args)
    except (CMCError, FileNotFoundError) as e:
        print(f"cmc {args.command}: error: {e}", file=sys.stderr)
        return 2
    except TrainingCancelled as e:
        print(f"cmc {args.command}: {e}; run again to resume", file=sys.stderr)
        return 130
    except KeyboardInterrupt:
        print(f"cmc {args.command}: interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
