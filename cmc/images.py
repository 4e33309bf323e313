"""Photo intake: decide by content what an upload is, read its EXIF, and write resized copies.

Convention: sizes are (width, height) in pixels *after* the EXIF orientation is applied (what a
person sees), and focal lengths are in pixels of that upright full-resolution image. Resized
copies map the image's outer corners onto each other (the ``cmc.cameras`` pixel convention), so
intrinsics scale by ``new_size / old_size`` per axis (:meth:`cmc.cameras.Cameras.scaled`).

Accepted: JPEG, PNG, WebP and HEIC/HEIF (decoded by ``pillow-heif``, a dependency; an install
without it refuses HEIC and says so). The format is taken from the file's bytes, never from its
name. Everything unusable raises
:class:`cmc.datasets.SceneError` with the photo's name in the message.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from PIL import ExifTags, Image, ImageOps, UnidentifiedImageError

from cmc.datasets import SceneError


class UnsupportedImageError(SceneError):
    """The bytes are not an image of a supported format (decided by content, not name)."""


class ImageTooLargeError(SceneError):
    """The image has more pixels than allowed (decompression-bomb guard)."""


try:  # HEIC/HEIF (the iPhone default), decoded by pillow-heif (a dependency)
    from pillow_heif import register_heif_opener

    register_heif_opener()
    HEIF_SUPPORTED = True
except ImportError:  # pragma: no cover - depends on the environment
    HEIF_SUPPORTED = False

# PIL format names we decode; every other parser is kept away from untrusted uploads.
SUPPORTED_FORMATS: tuple[str, ...] = ("JPEG", "PNG", "WEBP") + (("HEIF",) if HEIF_SUPPORTED else ())


def accepted_formats() -> str:
    """The accepted formats as people name them, e.g. 'JPEG, PNG, WebP or HEIC'."""
    names = [{"WEBP": "WebP", "HEIF": "HEIC"}.get(f, f) for f in SUPPORTED_FORMATS]
    return ", ".join(names[:-1]) + " or " + names[-1]


MAX_PIXELS = 120_000_000  # refuse larger images (decompression bombs); a 108 MP phone photo passes
_FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)  # "35 mm equivalent" focal lengths refer to this
_MM_PER_UNIT = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}  # EXIF FocalPlaneResolutionUnit: inch, cm, mm, um
_T = ExifTags.Base


@dataclass(frozen=True)
class PhotoInfo:
    """What the header and EXIF of one photo say (nothing decoded yet).

    Attributes:
        path: the original file (never modified).
        format: PIL format name detected from the content ('JPEG', 'PNG', 'WEBP', 'HEIF').
        width, height: upright size in pixels (EXIF orientation applied).
        orientation: EXIF orientation tag, 1 (upright) when absent.
        focal_px: focal length prior in pixels of the upright full-resolution image, or None.
        focal_source: '35mm-equivalent', 'focal-plane' or None: which EXIF tags gave ``focal_px``.
        device: 'Make Model' from EXIF, or None.
    """

    path: Path
    format: str
    width: int
    height: int
    orientation: int
    focal_px: float | None
    focal_source: str | None
    device: str | None


def _open(path: Path, max_pixels: int) -> Image.Image:
    """Open (header only) a supported image, refusing non-images and oversized images."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)  # we apply our own limit
            im = Image.open(path, formats=list(SUPPORTED_FORMATS))
    except FileNotFoundError:
        raise SceneError(f"photo not found: {path}") from None
    except IsADirectoryError:
        raise SceneError(f"{path} is a directory, not a photo") from None
    except Image.DecompressionBombError:
        raise ImageTooLargeError(f"{path.name}: image dimensions are too large (over {max_pixels} pixels)") from None
    except UnidentifiedImageError:
        raise UnsupportedImageError(f"{path.name} is not a supported image (accepted: {accepted_formats()})") from None
    except OSError as e:
        raise SceneError(f"cannot read {path.name}: {e}") from None
    w, h = im.size
    if w <= 0 or h <= 0 or w * h > max_pixels:
        im.close()
        raise ImageTooLargeError(f"{path.name}: {w}x{h} image is too large (limit {max_pixels} pixels)")
    return im


def _positive(value: object) -> float | None:
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return v if math.isfinite(v) and v > 0 else None


def exif_focal_px(exif: Image.Exif, stored_width: int, stored_height: int) -> tuple[float | None, str | None]:
    """Focal length prior in pixels from EXIF, and which tags gave it.

    Prefers ``FocalLengthIn35mmFilm`` (defined by the diagonal: f_px = f35 * diag_px / 43.27 mm),
    then ``FocalLength`` with ``FocalPlaneXResolution`` (pixels per unit on the sensor, rescaled
    when the stored width differs from ``ExifImageWidth``). Values implying a field of view across
    the long side outside about 6-127 degrees (f outside 0.25-10 long sides) are ignored.

    Args:
        exif: the image's EXIF (``Image.getexif()``).
        stored_width, stored_height: the image size as stored (before EXIF orientation).
    Returns:
        (focal_px, source) or (None, None).
    """
    sub = exif.get_ifd(ExifTags.IFD.Exif)
    tags = {**dict(exif), **dict(sub)}
    long_side = max(stored_width, stored_height)
    candidates: list[tuple[float | None, str]] = []
    f35 = _positive(tags.get(_T.FocalLengthIn35mmFilm))
    if f35 is not None:
        candidates.append((f35 * math.hypot(stored_width, stored_height) / _FULL_FRAME_DIAGONAL_MM, "35mm-equivalent"))
    f_mm = _positive(tags.get(_T.FocalLength))
    res = _positive(tags.get(_T.FocalPlaneXResolution))
    unit = _MM_PER_UNIT.get(int(_positive(tags.get(_T.FocalPlaneResolutionUnit)) or 2))  # EXIF default: inch
    if f_mm is not None and res is not None and unit is not None:
        scale = 1.0
        exif_w = _positive(tags.get(_T.ExifImageWidth))
        if exif_w is not None and exif_w != stored_width:
            scale = stored_width / exif_w
        candidates.append((f_mm * res / unit * scale, "focal-plane"))
    for f, source in candidates:
        if f is not None and 0.25 * long_side < f < 10.0 * long_side:
            return f, source
    return None, None


def read_photo_info(path: str | Path, max_pixels: int = MAX_PIXELS) -> PhotoInfo:
    """Identify a photo by its content and read its size, orientation and EXIF focal prior.

    Raises:
        SceneError: missing file, not a supported image, or more than ``max_pixels`` pixels.
    """
    path = Path(path)
    with _open(path, max_pixels) as im:
        exif = im.getexif()
        orientation = int(exif.get(_T.Orientation, 1) or 1)
        w, h = im.size
        focal, source = exif_focal_px(exif, w, h)
        make = str(exif.get(_T.Make, "") or "").strip("\x00 ")
        model = str(exif.get(_T.Model, "") or "").strip("\x00 ")
        fmt = im.format or "?"
    if orientation in (5, 6, 7, 8):  # rotated by 90 degrees: upright size is transposed
        w, h = h, w
    device = f"{make} {model}".strip() or None
    return PhotoInfo(path, fmt, w, h, orientation, focal, source, device)


def resized_size(width: int, height: int, long_side: int) -> tuple[int, int]:
    """(width, height) scaled so the long side is ``long_side`` pixels; never enlarges."""
    s = min(1.0, long_side / max(width, height))
    return max(1, round(width * s)), max(1, round(height * s))


def load_resized(info: PhotoInfo, sizes: Sequence[tuple[int, int]], max_pixels: int = MAX_PIXELS) -> list[Image.Image]:
    """Decode a photo once: upright (EXIF orientation applied), RGB, resized to each of ``sizes``.

    JPEGs are decoded at a reduced DCT scale when the largest requested size allows it.

    Args:
        info: from :func:`read_photo_info`.
        sizes: (width, height) pairs in pixels, e.g. from :func:`resized_size`.
    Returns:
        RGB images, in the order of ``sizes``.
    Raises:
        SceneError: the file cannot be decoded (e.g. a truncated upload).
    """
    with _open(info.path, max_pixels) as im:
        try:
            if im.format == "JPEG":  # draft keeps the decoded size >= the requested one
                s = max(max(wh) for wh in sizes) / max(info.width, info.height)
                im.draft("RGB", (math.ceil(im.size[0] * s), math.ceil(im.size[1] * s)))
            im.load()
            upright = ImageOps.exif_transpose(im).convert("RGB")
        except (OSError, ValueError, SyntaxError) as e:
            raise SceneError(f"cannot decode {info.path.name} (damaged or truncated file?): {e}") from None
    return [
        upright if upright.size == tuple(wh) else upright.resize(tuple(wh), Image.Resampling.LANCZOS) for wh in sizes
    ]


def save_png(image: Image.Image, path: Path, fast: bool = False) -> None:
    """Write an RGB PIL image as PNG (``fast``: light compression for scratch files)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    image.save(path, format="PNG", compress_level=1 if fast else 6)
