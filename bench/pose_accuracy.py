"""How close `cmc.poses.estimate_poses` comes to the dataset's cameras from three photos of a real scene.

For each scene and each of several evenly spaced triples of non-test views (the RegNeRF training
triple first), estimate the poses from the three ``images_8`` PNGs (with the EXIF focal length a
phone writes when ``--exif-focal``), align them to the dataset's cameras by a similarity, and
report: registered or the error, 3D points, focal length error (%), and the largest rotation
error (degrees) and camera-centre error (fraction of the mean baseline) after alignment. The
dataset's poses come from COLMAP on every photo of the scene, so they stand for the truth here.
No training: a few seconds per triple. ``--upscale PX`` enlarges the PNGs to PX pixels on the long
side first (Lanczos): photos of a phone's size with no more detail than 504 pixels hold, the worst
case for SIFT at that size.

    PYTHONPATH=. .venv/bin/python bench/pose_accuracy.py --data ../shared/datasets/llff \
        --scenes fern room trex --out bench/reports/current/pose_accuracy.json
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import platform
import statistics
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from bench.poses_e2e import alignment, with_exif_focal
from bench.results import pose_accuracy_table
from cmc.data.datasets import load_llff
from cmc.errors import PoseEstimationError
from cmc.eval.bench import git_commit
from cmc.geometry.cameras import cameras_from_llff
from cmc.poses import estimate_poses


def triples(rest: list[int], spans: tuple[float, ...] = (1.0, 0.75, 0.5), starts: int = 2) -> list[list[int]]:
    """Evenly spaced triples of ``rest`` (the RegNeRF one first): for each span (fraction of the
    sequence the triple covers), ``starts`` start positions."""
    n = len(rest)
    out: list[list[int]] = []
    for span in spans:
        width = round(span * (n - 1))
        for s in np.linspace(0, n - 1 - width, starts if width < n - 1 else 1):
            pick = np.round(np.linspace(s, s + width, 3)).astype(int)
            triple = [rest[i] for i in pick]
            if triple not in out:
                out.append(triple)
    return out


def enlarged(photos: list[Path], long_side: int, folder: Path) -> list[Path]:
    """Copies in ``folder`` of ``photos`` resized (Lanczos) to ``long_side`` pixels on the long side."""
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for p in photos:
        with Image.open(p) as im:
            s = long_side / max(im.size)
            im.resize((round(im.size[0] * s), round(im.size[1] * s)), Image.Resampling.LANCZOS).save(folder / p.name)
        out.append(folder / p.name)
    return out


def score_triple(data: Path, ids: list[int], exif_focal: bool, seed: int, upscale: int | None) -> dict[str, Any]:
    files = sorted(p for p in (data / "images_8").iterdir() if p.suffix.lower() == ".png")
    photos = [files[i] for i in ids]
    width, height = Image.open(photos[0]).size
    gt, _ = cameras_from_llff(np.load(data / "poses_bounds.npy")[ids], width, height)
    record: dict[str, Any] = {"views": ids}
    with tempfile.TemporaryDirectory() as tmp:
        if upscale:
            photos = enlarged(photos, upscale, Path(tmp) / "enlarged")
        if exif_focal:
            scale = upscale / max(width, height) if upscale else 1.0  # the focal at the photos' size
            photos = with_exif_focal(photos, float(gt.K[0, 0, 0]) * scale, Path(tmp) / "exif")
        try:
            est = estimate_poses(photos, Path(tmp) / "scene", seed=seed, keep_originals=False)
        except PoseEstimationError as e:
            record["error"] = str(e)[:200]
            return record
    a = alignment(gt, est.camera_file.cameras.scaled(gt.width, gt.height))
    record.update(
        points3D=est.stats["points3D"],
        reprojection_px=round(est.stats["mean_reprojection_error_px"], 3),
        focal_error_pct=round(100 * (a["focal_px_estimated"][0] / a["focal_px_dataset"][0] - 1), 2),
        rotation_error_deg=round(max(a["rotation_error_deg"]), 3),
        centre_error_baseline=round(max(a["centre_error_fraction_of_baseline"]), 4),
        seconds=round(est.timings["total"], 2),
    )
    return record


def summary(records: list[dict[str, Any]]) -> dict[str, Any]:
    ok = [r for r in records if "error" not in r]
    med = lambda key: round(statistics.median(abs(r[key]) for r in ok), 3) if ok else None  # noqa: E731
    return {
        "registered": f"{len(ok)}/{len(records)}",
        "median_abs_focal_error_pct": med("focal_error_pct"),
        "median_rotation_error_deg": med("rotation_error_deg"),
        "median_centre_error_baseline": med("centre_error_baseline"),
        "median_points3D": med("points3D"),
    }


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=Path("../shared/datasets/llff"), help="folder of LLFF scenes")
    ap.add_argument("--scenes", nargs="+", default=["fern", "room", "trex"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--upscale", type=int, help="enlarge the photos to this long side (pixels) first")
    ap.add_argument("--out", type=Path, help="JSON report")
    args = ap.parse_args(argv)
    report: dict[str, Any] = {
        "command": "bench/pose_accuracy.py " + " ".join(argv if argv is not None else __import__("sys").argv[1:]),
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "machine": platform.node(),
        "commit": git_commit(),
        "scenes": {},
    }
    for scene in args.scenes:
        data = args.data / scene
        split = load_llff(data)
        rest = sorted(split.train_ids + split.val_ids)
        for exif in (False, True):
            key = f"{scene}/{'exif' if exif else 'no_exif'}"
            records = [score_triple(data, ids, exif, args.seed, args.upscale) for ids in triples(rest)]
            report["scenes"][key] = {"summary": summary(records), "triples": records}
            print(key, json.dumps(report["scenes"][key]["summary"]), flush=True)
            for r in records:
                print("   ", json.dumps(r), flush=True)
    if args.out:
        args.out.write_text(json.dumps(report, indent=1) + "\n")
        args.out.with_suffix(".md").write_text(markdown_table(report))
    return report


def markdown_table(report: dict[str, Any]) -> str:
    """The summary per scene and EXIF case as a Markdown table, with the command, date and commit."""
    lines = [f"`{report['command']}` ({report['commit']}, {report['date']}, {report['machine']})", ""]
    lines += pose_accuracy_table(report)
    return (
        "\n".join(lines)
        + "\n\nMedians over the triples (absolute focal error; the largest error of the three cameras).\n"
    )


if __name__ == "__main__":
    main()
