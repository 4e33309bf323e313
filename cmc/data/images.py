"""Photo intake: decide by content what an upload is, read its EXIF, and write resized copies.

Convention: sizes are (width, height) in pixels *after* the EXIF orientation is applied (what a
person sees), and focal lengths are in pixels of that upright full-resolution image. Resized
copies map the image's outer corners onto each other (the ``cmc.geometry.cameras`` pixel convention), so
intrinsics scale by ``new_size / old_size`` per axis (:meth:`cmc.geometry.cameras.Cameras.scaled`).

Accepted: JPEG, PNG, WebP and HEIC/HEIF (decoded by ``pillow-heif``, a dependency; an install
without it refuses HEIC and says so). The format is taken from the file's bytes, never from its
name. Everything unusable raises
:class:`cmc.data.datasets.SceneError` with the photo's name in the message.
"""

from __future__ import annotations

import ctypes
import math
import threading
import warnings
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import ExifTags, Image, UnidentifiedImageError

from cmc.errors import SceneError


def to_uint8(image):
    """Colours in [0, 1] (any shape; NumPy array or torch tensor) -> uint8, clipped and rounded
    to the nearest level; the one float-to-8-bit conversion of the project."""
    if isinstance(image, np.ndarray):
        return (np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)
    import torch

    return image.clamp(0, 1).mul_(255).add_(0.5).to(torch.uint8)  # in place on clamp's copy


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
FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)  # "35 mm equivalent" focal lengths refer to this
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
        candidates.append((f35 * math.hypot(stored_width, stored_height) / FULL_FRAME_DIAGONAL_MM, "35mm-equivalent"))
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
        # Pillow's PNG reader decodes the whole image to look for EXIF after the pixels; only
        # the EXIF before them is read here (an upload check must not decode at full size).
        exif = Image.Image.getexif(im) if im.format == "PNG" else im.getexif()
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


class MemoryBudget:
    """Bytes that decodes in this process may hold at once: :meth:`reserve` waits until the
    request fits beside those running (a request larger than the whole budget runs alone)."""

    def __init__(self, capacity: int):
        self.capacity = capacity
        self.in_use = 0
        self._cond = threading.Condition()

    @contextmanager
    def reserve(self, nbytes: int) -> Iterator[None]:
        """Hold ``nbytes`` of the budget while the block runs; free what it allocated by its end."""
        with self._cond:
            self._cond.wait_for(lambda: self.in_use == 0 or self.in_use + nbytes <= self.capacity)
            self.in_use += nbytes
        try:
            yield
        finally:
            _give_back_freed_memory()
            with self._cond:
                self.in_use -= nbytes
                self._cond.notify_all()


def _libc_malloc_trim() -> Callable[[int], int] | None:
    try:
        return ctypes.CDLL(None).malloc_trim  # glibc
    except (AttributeError, OSError, TypeError):  # pragma: no cover - other C libraries
        return None


_MALLOC_TRIM = _libc_malloc_trim()


def _give_back_freed_memory() -> None:
    """Return the heap memory freed by this process to the system. glibc keeps what a thread
    freed in that thread's own arena, so without this each thread that ever decoded a large
    photo would keep its size resident, and the next decode on another thread would add to it."""
    if _MALLOC_TRIM is not None:
        _MALLOC_TRIM(0)


_TRANSPOSE = {
    2: Image.Transpose.FLIP_LEFT_RIGHT,
    3: Image.Transpose.ROTATE_180,
    4: Image.Transpose.FLIP_TOP_BOTTOM,
    5: Image.Transpose.TRANSPOSE,
    6: Image.Transpose.ROTATE_270,
    7: Image.Transpose.TRANSVERSE,
    8: Image.Transpose.ROTATE_90,
}


def decode_bytes(im: Image.Image, full_size: tuple[int, int]) -> int:
    """Peak bytes :func:`load_resized` holds while it decodes the opened image ``im`` (after any
    JPEG draft; ``full_size`` is the size before it): the pixels as Pillow stores them, an RGB
    copy for modes other than RGB and greyscale, the codec's own buffers, and 8 MiB for tables
    and the resized copies. WebP is decoded through an animation decoder that keeps its canvas,
    frame and output (12 bytes per pixel), HEIC through libheif's output (4 bytes per pixel);
    progressive JPEGs keep every DCT coefficient of the full-size image (2 bytes per sample, 3
    samples per pixel at most). ``tests/test_images.py`` measures that no format exceeds it."""
    w, h = im.size
    stored = 1 if im.mode in ("1", "L", "P") else 2 if im.mode.startswith("I;16") else 4
    per_pixel = stored + (0 if im.mode in ("RGB", "L") else 4)
    codec = {"WEBP": 12, "HEIF": 4}.get(im.format or "", 0) * w * h
    if im.format == "JPEG" and (im.info.get("progressive") or im.info.get("progression")):
        codec = 6 * full_size[0] * full_size[1]
    return per_pixel * w * h + codec + (8 << 20)


def load_resized(
    info: PhotoInfo,
    sizes: Sequence[tuple[int, int]],
    max_pixels: int = MAX_PIXELS,
    budget: MemoryBudget | None = None,
) -> list[Image.Image]:
    """Decode a photo once: upright (EXIF orientation applied), RGB, resized to each of ``sizes``.

    JPEGs are decoded at a reduced DCT scale when the largest requested size allows it. The
    decoded image is resized before it is turned upright, so it is held once (plus an RGB copy
    for palette, alpha and 16-bit images); the decode waits for its :func:`decode_bytes` in
    ``budget``, which bounds the memory of concurrent decodes.

    Args:
        info: from :func:`read_photo_info`.
        sizes: (width, height) pairs in pixels, e.g. from :func:`resized_size`.
        budget: the budget the process's decodes share (the service's: ``CMC_DECODE_MEMORY_BYTES``);
            None: this decode waits for no other.
    Returns:
        RGB images, in the order of ``sizes``.
    Raises:
        SceneError: the file cannot be decoded (e.g. a truncated upload).
    """
    transpose = _TRANSPOSE.get(info.orientation)
    swap = info.orientation in (5, 6, 7, 8)  # sizes are upright; the file is stored turned by 90 degrees
    with _open(info.path, max_pixels) as im:
        full_size = im.size
        try:
            if im.format == "JPEG":  # draft keeps the decoded size >= the requested one
                s = max(max(wh) for wh in sizes) / max(info.width, info.height)
                im.draft("RGB", (math.ceil(im.size[0] * s), math.ceil(im.size[1] * s)))
            with (budget or MemoryBudget(0)).reserve(decode_bytes(im, full_size)):
                im.load()
                full = im if im.mode in ("RGB", "L") else im.convert("RGB")  # LANCZOS needs RGB or L
                if full is not im:
                    im.close()  # frees the decoded pixels now, not when the RGB copy is done with
                out = []
                for w, h in sizes:
                    stored = (h, w) if swap else (w, h)
                    small = full.copy() if full.size == stored else full.resize(stored, Image.Resampling.LANCZOS)
                    small = small.convert("RGB") if small.mode != "RGB" else small
                    out.append(small if transpose is None else small.transpose(transpose))
                full.close()
                im.close()  # the reservation ends with these pixels given back (MemoryBudget.reserve)
        except (OSError, ValueError, SyntaxError) as e:
            raise SceneError(f"cannot decode {info.path.name} (damaged or truncated file?): {e}") from None
    return out


def save_png(image: Image.Image, path: Path, fast: bool = False) -> None:
    """Write an RGB PIL image as PNG (``fast``: light compression for scratch files)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    image.save(path, format="PNG", compress_level=1 if fast else 6)
