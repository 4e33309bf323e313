"""Tests of cmc.data.images: formats decided by content, EXIF orientation and focal priors, size limits,
damaged files, and resizing. Everything is generated here except the fern JPEG known answer, which
is skipped when the shared folder (``$CMC_SHARED_DIR`` or ``../shared``) is absent.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import SHARED_DIR
from PIL import ExifTags, Image

from cmc.data.datasets import SceneError
from cmc.data.images import (
    HEIF_SUPPORTED,
    PhotoInfo,
    accepted_formats,
    exif_focal_px,
    load_resized,
    read_photo_info,
    resized_size,
)

FERN_JPEG = SHARED_DIR / "datasets" / "llff" / "fern" / "images" / "IMG_4027.JPG"


def make_exif(orientation: int | None = None, **exif_tags: float) -> Image.Exif:
    """EXIF with an optional orientation (IFD0) and Exif sub-IFD tags given by their PIL names."""
    exif = Image.Exif()
    exif[ExifTags.Base.Make] = "Acme"
    if orientation is not None:
        exif[ExifTags.Base.Orientation] = orientation
    sub = exif.get_ifd(ExifTags.IFD.Exif)
    for name, value in exif_tags.items():
        sub[ExifTags.Base[name]] = value
    return exif


def quadrants(width: int = 64, height: int = 48) -> Image.Image:
    """Four flat colours: red top-left, green top-right, blue bottom-left, white bottom-right."""
    a = np.zeros((height, width, 3), np.uint8)
    h2, w2 = height // 2, width // 2
    a[:h2, :w2] = (255, 0, 0)
    a[:h2, w2:] = (0, 255, 0)
    a[h2:, :w2] = (0, 0, 255)
    a[h2:, w2:] = (255, 255, 255)
    return Image.fromarray(a)


@pytest.mark.parametrize("fmt", ["JPEG", "PNG", "WEBP"])
def test_format_is_read_from_content_not_name(tmp_path: Path, fmt: str) -> None:
    path = tmp_path / "upload.bin"  # misleading / missing extension on purpose
    quadrants().save(path, format=fmt)
    info = read_photo_info(path)
    assert (info.format, info.width, info.height, info.orientation) == (fmt, 64, 48, 1)
    wrong = tmp_path / ("photo.png" if fmt == "JPEG" else "photo.jpg")
    quadrants().save(wrong, format=fmt)
    assert read_photo_info(wrong).format == fmt


def test_heic_is_accepted(tmp_path: Path) -> None:
    """iPhone photos: HEIC is decoded by the default install (pillow-heif is a dependency), and
    the error for an unsupported file says so."""
    assert HEIF_SUPPORTED and accepted_formats() == "JPEG, PNG, WebP or HEIC"
    path = tmp_path / "IMG_0001.HEIC"
    quadrants().save(path, format="HEIF", quality=90)
    info = read_photo_info(path)
    assert (info.format, info.width, info.height) == ("HEIF", 64, 48)
    (img,) = load_resized(info, [(32, 24)])
    assert img.size == (32, 24)


@pytest.mark.parametrize(
    "content, message",
    [
        (b"this is not an image\n" * 50, "not a supported image"),
        (b"", "not a supported image"),
        (b"\xff\xd8\xff" + b"\x00" * 10, "not a supported image"),  # a JPEG signature and nothing else
    ],
)
def test_non_images_are_refused(tmp_path: Path, content: bytes, message: str) -> None:
    path = tmp_path / "photo.jpg"
    path.write_bytes(content)
    with pytest.raises(SceneError, match=message) as e:
        read_photo_info(path)
    assert "photo.jpg" in str(e.value)


def test_other_image_formats_are_refused(tmp_path: Path) -> None:
    path = tmp_path / "anim.jpg"
    quadrants().save(path, format="GIF")
    with pytest.raises(SceneError, match="not a supported image"):
        read_photo_info(path)


def test_missing_file_and_directory(tmp_path: Path) -> None:
    with pytest.raises(SceneError, match="not found"):
        read_photo_info(tmp_path / "nope.jpg")
    with pytest.raises(SceneError, match="directory"):
        read_photo_info(tmp_path)


def test_decompression_bombs_are_refused_from_the_header(tmp_path: Path) -> None:
    path = tmp_path / "bomb.png"
    Image.new("1", (20000, 10000)).save(path)  # ~25 KB on disk, 200 MP decoded
    assert path.stat().st_size < 100_000
    with pytest.raises(SceneError, match="too large"):
        read_photo_info(path)
    small = tmp_path / "small.png"
    quadrants().save(small)
    with pytest.raises(SceneError, match="too large"):
        read_photo_info(small, max_pixels=1000)


def test_truncated_jpeg_is_a_clear_error(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    full = tmp_path / "full.jpg"
    Image.fromarray(rng.integers(0, 255, (240, 320, 3), dtype=np.uint8)).save(full, quality=90)
    cut = tmp_path / "cut.jpg"
    cut.write_bytes(full.read_bytes()[: full.stat().st_size // 2])
    info = read_photo_info(cut)  # the header is intact
    with pytest.raises(SceneError, match="cut.jpg.*truncated"):
        load_resized(info, [(160, 120)])


@pytest.mark.parametrize(
    "orientation, size, corners",
    [
        # colours at the upright image's (top-left, top-right, bottom-left) after EXIF rotation
        (1, (64, 48), ("red", "green", "blue")),
        (3, (64, 48), ("white", "blue", "green")),  # rotated 180 degrees
        (6, (48, 64), ("blue", "red", "white")),  # stored rotated 90 degrees counter-clockwise
        (8, (48, 64), ("green", "white", "red")),  # stored rotated 90 degrees clockwise
    ],
)
def test_exif_orientation_is_honoured(tmp_path: Path, orientation: int, size: tuple, corners: tuple) -> None:
    colours = {"red": (255, 0, 0), "green": (0, 255, 0), "blue": (0, 0, 255), "white": (255, 255, 255)}
    path = tmp_path / "phone.jpg"
    quadrants().save(path, quality=95, exif=make_exif(orientation))
    info = read_photo_info(path)
    assert (info.width, info.height, info.orientation) == (*size, orientation)
    full, half = load_resized(info, [size, resized_size(*size, 32)])
    assert full.size == size and half.size == tuple(s // 2 for s in size)
    (quarter,) = load_resized(info, [resized_size(*size, 16)])  # JPEG decoded at a reduced DCT scale
    assert quarter.size == tuple(s // 4 for s in size)
    for img in (full, quarter):
        a = np.asarray(img, dtype=int)
        for (r, c), name in zip([(1, 1), (1, -2), (-2, 1)], corners, strict=True):
            assert np.abs(a[r, c] - colours[name]).max() < 40, (orientation, img.size, name, a[r, c])


def test_exif_focal_from_35mm_equivalent(tmp_path: Path) -> None:
    path = tmp_path / "p.jpg"
    quadrants(400, 300).save(path, exif=make_exif(FocalLengthIn35mmFilm=28, FocalLength=4.0))
    info = read_photo_info(path)
    assert info.focal_source == "35mm-equivalent"
    assert info.focal_px == pytest.approx(28 * 500 / math.hypot(36, 24))  # diagonal 500 px


def test_exif_focal_from_focal_plane_resolution(tmp_path: Path) -> None:
    # 5 mm lens, 1000 pixels per cm on the sensor: f = 5 mm * 100 px/mm = 500 px at the sensor's width,
    # and the stored image is half the EXIF width, so 250 px.
    exif = make_exif(FocalLength=5.0, FocalPlaneXResolution=1000.0, FocalPlaneResolutionUnit=3, ExifImageWidth=800)
    path = tmp_path / "p.png"
    quadrants(400, 300).save(path, exif=exif)
    info = read_photo_info(path)
    assert (info.focal_source, info.focal_px) == ("focal-plane", pytest.approx(250.0))


@pytest.mark.parametrize("tags", [{}, {"FocalLength": 4.0}, {"FocalLengthIn35mmFilm": 0}, {"FocalLengthIn35mmFilm": 2}])
def test_missing_or_absurd_focal_gives_no_prior(tmp_path: Path, tags: dict) -> None:
    path = tmp_path / "p.jpg"
    quadrants(400, 300).save(path, exif=make_exif(**tags))
    assert read_photo_info(path).focal_px is None
    assert exif_focal_px(Image.Exif(), 400, 300) == (None, None)


def test_exif_focal_does_not_depend_on_orientation(tmp_path: Path) -> None:
    path = tmp_path / "p.jpg"
    quadrants(400, 300).save(path, exif=make_exif(6, FocalLengthIn35mmFilm=26))
    info = read_photo_info(path)
    assert (info.width, info.height) == (300, 400)
    assert info.focal_px == pytest.approx(26 * 500 / math.hypot(36, 24))


def test_resized_size() -> None:
    assert resized_size(4032, 3024, 504) == (504, 378)
    assert resized_size(3024, 4032, 504) == (378, 504)
    assert resized_size(320, 240, 504) == (320, 240)  # never enlarged
    assert resized_size(1000, 3, 100) == (100, 1)


def test_resizing_keeps_the_corner_convention(tmp_path: Path) -> None:
    """A 2x reduction averages 2x2 blocks, so a feature at continuous pixel x maps to x / 2."""
    a = np.zeros((40, 80, 3), np.uint8)
    a[10:20, 30:50] = 255  # box spanning continuous x in [30, 50], y in [10, 20]
    path = tmp_path / "box.png"
    Image.fromarray(a).save(path)
    (small,) = load_resized(read_photo_info(path), [(40, 20)])
    col = np.asarray(small, dtype=float)[:, :, 0].mean(axis=0)
    x_centre = (col * (np.arange(40) + 0.5)).sum() / col.sum()
    assert x_centre == pytest.approx(20.0, abs=0.05)


@pytest.mark.skipif(not FERN_JPEG.exists(), reason=f"shared dataset absent: {FERN_JPEG}")
def test_fern_exif_focal_matches_llff_calibration() -> None:
    info = read_photo_info(FERN_JPEG)
    assert isinstance(info, PhotoInfo)
    assert (info.width, info.height, info.device) == (4032, 3024, "Apple iPhone X")
    assert info.focal_px == pytest.approx(3260.5, rel=0.005)  # LLFF's COLMAP focal for these photos


DECODE_PEAK = """
import gc, json, sys
from pathlib import Path
import cmc.data.images as ci

def resident():
    fields = dict(line.split(":", 1) for line in Path("/proc/self/status").read_text().splitlines())
    return int(fields["VmRSS"].split()[0]) * 1024, int(fields["VmHWM"].split()[0]) * 1024

estimates = []
estimate = ci.decode_bytes
ci.decode_bytes = lambda im, full: estimates.append(estimate(im, full)) or estimates[-1]
out = {}
for path in sys.argv[1:]:
    gc.collect()
    ci._give_back_freed_memory()  # what the last photo's decoder freed late is not reused here
    Path("/proc/self/clear_refs").write_text("5")  # the high-water mark starts again from here
    before = resident()[0]
    info = ci.read_photo_info(path)
    ci.load_resized(info, [ci.resized_size(info.width, info.height, 64)])
    out[Path(path).name] = [resident()[1] - before, estimates[-1]]
print(json.dumps(out))
"""


@pytest.mark.skipif(not Path("/proc/self/clear_refs").exists(), reason="measures /proc (Linux)")
def test_decoding_stays_within_its_memory_estimate(tmp_path: Path) -> None:
    """What a decode holds at its peak (resident memory, measured) is within ``decode_bytes``,
    the amount it reserves from the decode budget, for every format and the costly modes."""
    w, h = 3000, 2000  # 6 MP: the fixed part of the estimate is small beside the pixels
    colour = (40, 90, 160, 200)
    photos = {
        "rgb.png": (Image.new("RGB", (w, h), colour[:3]), {}),
        "rgba.png": (Image.new("RGBA", (w, h), colour), {}),
        "palette.png": (Image.new("RGB", (w, h), colour[:3]).convert("P"), {}),
        "grey16.png": (Image.new("I;16", (w, h), 1000), {}),
        "progressive444.jpg": (Image.new("RGB", (w, h), colour[:3]), {"progressive": True, "subsampling": 0}),
        "baseline.jpg": (Image.new("RGB", (w, h), colour[:3]), {}),
        "rgb.webp": (Image.new("RGB", (w, h), colour[:3]), {}),
        "rgba.webp": (Image.new("RGBA", (w, h), colour), {}),
    }
    if HEIF_SUPPORTED:
        photos["rgba.heic"] = (Image.new("RGBA", (w, h), colour), {"quality": 50})
    for name, (im, options) in photos.items():
        im.save(tmp_path / name, **options)
    root = Path(__file__).resolve().parents[1]
    run = subprocess.run(
        [sys.executable, "-c", DECODE_PEAK, *(str(tmp_path / n) for n in photos)],
        capture_output=True,
        text=True,
        cwd=root,
        env={**os.environ, "PYTHONPATH": str(root), "OMP_NUM_THREADS": "1"},
        timeout=300,
    )
    assert run.returncode == 0, run.stderr
    for name, (peak, estimate) in json.loads(run.stdout).items():
        print(f"{name}: peak {peak / 2**20:.0f} MiB, estimate {estimate / 2**20:.0f} MiB")
        assert peak <= estimate, name
