"""The service's PNG encoder: what Pillow decodes is exactly what went in."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from service.renders import png_bytes


@pytest.mark.parametrize("size", [(37, 53), (1, 1), (378, 504)])
def test_rgb_png_decodes_to_the_same_pixels(size) -> None:
    rng = np.random.default_rng(0)
    smooth = np.linspace(0, 255, size[0] * size[1] * 3).reshape(*size, 3)
    image = np.clip(smooth + rng.integers(-3, 4, smooth.shape), 0, 255).astype(np.uint8)
    image[: size[0] // 2, : size[1] // 3] = 255  # a flat region and a hard edge
    decoded = Image.open(io.BytesIO(png_bytes(image)))
    assert decoded.mode == "RGB" and decoded.size == (size[1], size[0])
    np.testing.assert_array_equal(np.asarray(decoded), image)


def test_16_bit_png_decodes_to_the_same_counts() -> None:
    rng = np.random.default_rng(1)
    counts = rng.integers(0, 65536, (29, 41)).astype(np.uint16)
    counts[0, :4] = [0, 255, 256, 65535]  # both bytes of a sample matter
    decoded = Image.open(io.BytesIO(png_bytes(counts)))
    assert decoded.size == (41, 29)
    np.testing.assert_array_equal(np.asarray(decoded).astype(np.uint16), counts)


def test_rgba_and_grey_alpha_pngs_decode_to_the_same_samples() -> None:
    """The coverage mask's encodings: RGBA renders exactly; 16-bit grey + alpha depth (Pillow
    reads it as 8-bit RGBA, grey repeated: the high byte of each sample)."""
    rng = np.random.default_rng(2)
    rgba = rng.integers(0, 256, (23, 31, 4)).astype(np.uint8)
    decoded = Image.open(io.BytesIO(png_bytes(rgba)))
    assert decoded.mode == "RGBA"
    np.testing.assert_array_equal(np.asarray(decoded), rgba)
    la = rng.integers(0, 65536, (23, 31, 2)).astype(np.uint16)
    decoded = Image.open(io.BytesIO(png_bytes(la)))
    assert decoded.size == (31, 23)
    np.testing.assert_array_equal(np.asarray(decoded.convert("LA")), (la >> 8).astype(np.uint8))


def test_other_arrays_are_refused() -> None:
    with pytest.raises(ValueError, match="png_bytes takes"):
        png_bytes(np.zeros((4, 4, 5), np.uint8))
    with pytest.raises(ValueError, match="png_bytes takes"):
        png_bytes(np.zeros((4, 4, 3), np.uint16))
    with pytest.raises(ValueError, match="png_bytes takes"):
        png_bytes(np.zeros((4, 4), np.float32))
