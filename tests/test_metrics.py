"""Tests of cmc.eval.metrics: known answers, and agreement with the official implementations' values.

The reference values (``reference/metric_reference.json``), images and LPIPS weights live in the
shared folder: ``$CMC_SHARED_DIR`` or else ``../shared`` next to the repository.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import SHARED_DIR
from PIL import Image

from cmc.eval.metrics import LPIPS, LPIPS_DIR_ENV, image_metrics, psnr, ssim

REFERENCE_FILE = SHARED_DIR / "reference" / "metric_reference.json"
WEIGHTS_DIR = SHARED_DIR / "weights"

needs_reference = pytest.mark.skipif(
    not REFERENCE_FILE.is_file(),
    reason=f"shared reference data not found at {REFERENCE_FILE} (set CMC_SHARED_DIR)",
)
needs_weights = pytest.mark.skipif(
    not (WEIGHTS_DIR / "lpips_alex.pth").is_file() or not (WEIGHTS_DIR / "lpips_vgg.pth").is_file(),
    reason=f"LPIPS weights not found in {WEIGHTS_DIR} (set CMC_SHARED_DIR)",
)


def _load_png(relative: str) -> np.ndarray:
    """[H, W, 3] float32 in [0, 1]."""
    with Image.open(SHARED_DIR / "datasets" / relative) as image:
        return np.asarray(image.convert("RGB"), dtype=np.float32) / 255.0


def _reference_pairs() -> list[dict]:
    if not REFERENCE_FILE.is_file():
        return []
    return json.loads(REFERENCE_FILE.read_text())["pairs"]


def _random_image(seed: int, height: int = 40, width: int = 48) -> np.ndarray:
    return np.random.default_rng(seed).random((height, width, 3))


# --- agreement with the official implementations ---------------------------------------------


@needs_reference
@needs_weights
@pytest.mark.parametrize("pair", _reference_pairs(), ids=lambda p: f"{p['a']}-{p['b']}")
def test_metrics_match_reference(pair: dict) -> None:
    a, b = _load_png(pair["a"]), _load_png(pair["b"])
    got = image_metrics(a, b, lpips_weights_dir=WEIGHTS_DIR)
    assert got["psnr"] == pytest.approx(pair["psnr"], abs=1e-3)
    assert got["ssim"] == pytest.approx(pair["ssim"], abs=1e-3)
    assert got["lpips_alex"] == pytest.approx(pair["lpips_alex"], abs=1e-4)
    assert got["lpips_vgg"] == pytest.approx(pair["lpips_vgg"], abs=1e-4)


# --- PSNR ------------------------------------------------------------------------------------


def test_psnr_identical_is_inf() -> None:
    image = _random_image(0)
    assert psnr(image, image.copy()) == math.inf


def test_psnr_constant_offset() -> None:
    a = np.full((8, 9, 3), 0.25)
    b = a + 0.125  # exact in binary: MSE = 1/64
    assert psnr(a, b) == pytest.approx(-10 * math.log10(1 / 64), abs=1e-12)
    c = _random_image(1) * 0.8
    assert psnr(c, c + 0.1) == pytest.approx(20.0, abs=1e-9)


def test_psnr_accepts_torch_and_numpy_alike() -> None:
    a, b = _random_image(2), _random_image(3)
    assert psnr(torch.from_numpy(a).float(), torch.from_numpy(b).float()) == pytest.approx(psnr(a, b), abs=1e-4)


# --- SSIM ------------------------------------------------------------------------------------


def _ssim_loop_reference(a: np.ndarray, b: np.ndarray) -> float:
    """Slow twin of scikit-image's Gaussian SSIM: scipy-'reflect' (numpy 'symmetric') padding,
    explicit separable Gaussian filtering, then a 5-pixel crop, per channel then mean."""
    sigma, radius = 1.5, 5
    offsets = np.arange(-radius, radius + 1)
    taps = np.exp(-0.5 * (offsets / sigma) ** 2)
    taps /= taps.sum()

    def blur(plane: np.ndarray) -> np.ndarray:
        height, width = plane.shape
        padded = np.pad(plane, radius, mode="symmetric")
        rows = sum(t * padded[radius + o : radius + o + height, :] for t, o in zip(taps, offsets, strict=False))
        return sum(t * rows[:, radius + o : radius + o + width] for t, o in zip(taps, offsets, strict=False))

    c1, c2 = 0.01**2, 0.03**2
    per_channel = []
    for ch in range(a.shape[2]):
        x, y = a[..., ch].astype(np.float64), b[..., ch].astype(np.float64)
        mx, my = blur(x), blur(y)
        vx, vy, cxy = blur(x * x) - mx**2, blur(y * y) - my**2, blur(x * y) - mx * my
        s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx**2 + my**2 + c1) * (vx + vy + c2))
        per_channel.append(s[radius:-radius, radius:-radius].mean())
    return float(np.mean(per_channel))


def test_ssim_identical_is_one() -> None:
    image = _random_image(4)
    assert ssim(image, image) == pytest.approx(1.0, abs=1e-12)


def test_ssim_matches_loop_reference() -> None:
    a = _random_image(5, 23, 31)
    b = np.clip(a + 0.2 * _random_image(6, 23, 31) - 0.1, 0.0, 1.0)
    expected = _ssim_loop_reference(a, b)
    assert ssim(a, b) == pytest.approx(expected, abs=1e-12)
    assert ssim(a, b) < 0.99


def test_ssim_rejects_too_small_images() -> None:
    with pytest.raises(ValueError, match="at least 11x11"):
        ssim(np.zeros((10, 20, 3)), np.zeros((10, 20, 3)))


# --- LPIPS -----------------------------------------------------------------------------------


@needs_weights
@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_lpips_identical_is_zero_and_symmetric(net: str) -> None:
    metric = LPIPS(net, WEIGHTS_DIR)
    a, b = _random_image(7, 64, 64), _random_image(8, 64, 64)
    assert metric(a, a) == 0.0
    d_ab, d_ba = metric(a, b), metric(b, a)
    assert d_ab > 0.05
    assert d_ab == pytest.approx(d_ba, abs=1e-6)


@needs_weights
def test_lpips_batch_matches_single_and_uses_env(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv(LPIPS_DIR_ENV, str(WEIGHTS_DIR))
    metric = LPIPS("alex")
    a = torch.from_numpy(np.stack([_random_image(9, 64, 64), _random_image(10, 64, 64)])).float()
    b = torch.from_numpy(np.stack([_random_image(11, 64, 64), _random_image(12, 64, 64)])).float()
    with torch.no_grad():
        batched = metric.batch(a.permute(0, 3, 1, 2), b.permute(0, 3, 1, 2))
    assert batched.shape == (2,)
    for i in range(2):
        assert batched[i].item() == pytest.approx(metric(a[i], b[i]), abs=1e-6)


def test_lpips_without_weights_dir_names_both_ways(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.delenv(LPIPS_DIR_ENV, raising=False)
    with pytest.raises(FileNotFoundError) as excinfo:
        LPIPS("vgg")
    assert "weights_dir" in str(excinfo.value)
    assert LPIPS_DIR_ENV in str(excinfo.value)


def test_lpips_missing_file_names_path(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="lpips_alex.pth"):
        LPIPS("alex", tmp_path)
