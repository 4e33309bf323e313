"""Pictures that show where a novel view goes wrong: depth colour maps, error maps, and one
diagnostic sheet per test view with every MPI's own render and depth.

Images are float [H, W, 3] in [0, 1]; depths are target-camera z in scene units (0 = no hit).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from PIL import Image, ImageDraw

from cmc.data.images import to_uint8


def depth_preview(depth: np.ndarray, near: float, far: float) -> np.ndarray:
    """[H, W, 3] colour map of inverse depth (near = bright yellow, far = dark blue)."""
    t = np.clip((1 / np.maximum(depth, 1e-6) - 1 / far) / (1 / near - 1 / far), 0, 1)[..., None]
    lo, mid, hi = np.array([0.05, 0.03, 0.35]), np.array([0.85, 0.25, 0.3]), np.array([1.0, 0.95, 0.3])
    return np.where(t < 0.5, lo + (mid - lo) * (2 * t), mid + (hi - mid) * (2 * t - 1))


def with_depth_legend(preview: np.ndarray, near: float, far: float, ticks: int = 5) -> np.ndarray:
    """``preview`` (:func:`depth_preview`, [H, W, 3]) with a legend strip below it: the colour
    ramp from near (left) to far (right), evenly in inverse depth as the colours are, and
    ``ticks`` depths written under it in scene units -> [H + 28, W, 3]."""
    h, w = preview.shape[:2]
    inv = 1 / near + (1 / far - 1 / near) * (np.arange(w) + 0.5) / w
    ramp = depth_preview(np.broadcast_to(1 / inv, (10, w)), near, far)
    strip = Image.new("RGB", (w, 18))
    draw = ImageDraw.Draw(strip)
    for k in range(ticks):
        x = round((w - 1) * k / (ticks - 1))
        z = 1 / (1 / near + (1 / far - 1 / near) * k / (ticks - 1))
        label = f"{z:.3g}"
        width = draw.textlength(label)
        draw.text((min(max(0.0, x - width / 2), w - width), 4), label, fill=(220, 220, 220))
    return np.concatenate([preview, ramp, np.asarray(strip, dtype=np.float64) / 255], 0)


def heat(x: np.ndarray, scale: float) -> np.ndarray:
    """[H, W] non-negative values -> [H, W, 3] black-red-yellow-white ramp saturating at ``scale``."""
    t = np.clip(x / scale, 0, 1)[..., None]
    return np.clip(np.concatenate([3 * t, 3 * t - 1, 3 * t - 2], -1), 0, 1)


def error_map(pred: np.ndarray, gt: np.ndarray, scale: float = 0.25) -> np.ndarray:
    """[H, W, 3] heat map of the mean absolute colour error per pixel (white at ``scale``)."""
    return heat(np.abs(pred - gt).mean(-1), scale)


def depth_error_map(depth: np.ndarray, gt_depth: np.ndarray, scale: float = 0.25) -> np.ndarray:
    """[H, W, 3] heat map of the relative depth error |z - z_gt| / z_gt (white at ``scale``)."""
    return heat(np.abs(depth - gt_depth) / np.maximum(gt_depth, 1e-6), scale)


def contact_sheet(tiles: Sequence[Sequence[tuple[str, np.ndarray | None]]]) -> np.ndarray:
    """Rows of labelled [H, W, 3] tiles (None leaves a blank) -> one [rows * H, cols * W, 3] image."""
    h, w = next(t for row in tiles for _, t in row if t is not None).shape[:2]
    cols = max(len(r) for r in tiles)
    sheet = Image.new("RGB", (cols * w, len(tiles) * h))
    draw = ImageDraw.Draw(sheet)
    for r, row in enumerate(tiles):
        for c, (label, tile) in enumerate(row):
            if tile is None:
                continue
            sheet.paste(Image.fromarray(to_uint8(tile)), (c * w, r * h))
            draw.rectangle((c * w, r * h, c * w + 7 * len(label) + 4, r * h + 12), fill=(0, 0, 0))
            draw.text((c * w + 2, r * h), label, fill=(255, 255, 255))
    return np.asarray(sheet, dtype=np.float32) / 255.0
