"""The data a lent GPU machine needs, packed into ``.gpudata/`` (ignored by git) to travel with the
device tool's ``carry`` (the tree may carry 64 MiB; ../shared stays behind).

``pack`` (here): the LLFF scenes' ``images_8`` and ``poses_bounds.npy`` under ``.gpudata/llff/``,
LPIPS-alex in float16 and LPIPS-vgg in int8 with one float scale per output channel (14.8 MB
instead of 57 MB; LPIPS-vgg of photo pairs moves by at most 3e-4), under ``.gpudata/weights/``.
``unpack`` (there): writes ``.gpudata/weights/lpips_vgg.pth`` back in float32 from the int8 file.

Usage: python bench/gpudata.py pack [--scenes fern,room,trex] | python bench/gpudata.py unpack
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
DEST = ROOT / ".gpudata"
SHARED = ROOT.parent / "shared"


def pack(scenes: list[str]) -> None:
    for scene in scenes:
        src, dst = SHARED / "datasets/llff" / scene, DEST / "llff" / scene
        shutil.rmtree(dst, ignore_errors=True)
        shutil.copytree(src / "images_8", dst / "images_8")
        shutil.copy(src / "poses_bounds.npy", dst / "poses_bounds.npy")
    weights = DEST / "weights"
    weights.mkdir(parents=True, exist_ok=True)
    alex = torch.load(SHARED / "weights/lpips_alex.pth")
    torch.save({k: v.half() for k, v in alex.items()}, weights / "lpips_alex.pth")
    vgg = {}
    for k, v in torch.load(SHARED / "weights/lpips_vgg.pth").items():
        if v.ndim == 4 and v.numel() > 10000:  # the backbone's convolutions
            scale = v.abs().amax(dim=(1, 2, 3), keepdim=True) / 127
            vgg[k] = {"int8": torch.round(v / scale).to(torch.int8), "scale": scale}
        else:
            vgg[k] = v
    torch.save(vgg, weights / "lpips_vgg_int8.pt")
    (weights / "lpips_vgg.pth").unlink(missing_ok=True)


def unpack() -> None:
    weights = DEST / "weights"
    vgg = torch.load(weights / "lpips_vgg_int8.pt")
    sd = {k: v["int8"].float() * v["scale"] if isinstance(v, dict) else v for k, v in vgg.items()}
    torch.save(sd, weights / "lpips_vgg.pth")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("action", choices=["pack", "unpack"])
    ap.add_argument("--scenes", default="fern,room,trex")
    args = ap.parse_args()
    pack(args.scenes.split(",")) if args.action == "pack" else unpack()


if __name__ == "__main__":
    main()
