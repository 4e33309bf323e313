"""Novel views and depth maps from baked MPIs, with an in-memory cache of loaded scenes.

Rendering uses :class:`cmc.serving.baking.BakedScene` (the baked atlases alone, no trained model).
That needs torch, imported on the first render only; the rest of the API does not load it.
Renders run on their own threads (:class:`RenderQueue`), never on the thread pool the other
routes share, so probes and status polls answer whatever the render load: at most
``render_concurrency`` at once (each on ``render_threads`` CPU threads), ``render_queue`` more
waiting their turn, and beyond that 503 with ``Retry-After``.

Depth encodings (``POST /v1/scenes/{id}/depth``, by ``Accept``):

* ``image/png`` (default): 16-bit greyscale PNG, ``depth = value * scale`` in scene units
  (target-camera z), ``scale`` in the ``Depth-Scale`` header (``2 * far / 65535``, so every
  depth up to twice the far bound is exact to ``scale / 2``); 0 means no surface.
* ``application/x-npy``: float32 NumPy array [H, W], scene units, 0 where nothing was hit.
* ``?preview=true``: an 8-bit colour map of inverse depth (PNG) for people.

``?coverage=true`` (render and depth) marks the pixels whose point no input photo saw
(:meth:`cmc.serving.baking.BakedScene.coverage`): an alpha channel (0 there, opaque elsewhere) in every
PNG, NaN in the ``.npy``; a JPEG render cannot carry it (406).

Scene units are those of the cameras: arbitrary (SfM) for estimated poses, metres for ARKit.
"""

from __future__ import annotations

import asyncio
import io
import struct
import threading
import zlib
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
from PIL import Image

from service.errors import APIError, ErrorCode
from service.storage import Storage

T = TypeVar("T")


@dataclass
class Rendered:
    rgb: np.ndarray  # [H, W, 3] float32 in [0, 1]
    depth: np.ndarray  # [H, W] float32, target-camera z in scene units, 0 where nothing was hit
    near: float
    far: float
    coverage: np.ndarray | None = None  # [H, W] bool: an input photo saw the pixel's point (when asked)


class BakedCache:
    """LRU cache of loaded baked scenes, keyed by their storage folder (a scene's final bake or its
    preview), bounded by their bytes in memory (:attr:`cmc.serving.baking.BakedScene.nbytes`); the scene
    just loaded always stays, and loading one folder of a scene drops the scene's others (the
    preview once the final bake is served)."""

    def __init__(self, storage: Storage, capacity_bytes: int, threads: int = 1):
        self.storage, self.capacity_bytes, self.threads = storage, capacity_bytes, threads
        self._scenes: OrderedDict[str, Any] = OrderedDict()
        self._lock = threading.Lock()
        self._load_locks: dict[str, threading.Lock] = {}

    def get(self, folder: str) -> Any:
        """The baked scene in storage folder ``folder``; FileNotFoundError if none is stored there
        (a preview removed once its scene became ready)."""
        from cmc.serving.baking import BakedScene

        with self._lock:
            if folder in self._scenes:
                self._scenes.move_to_end(folder)
                return self._scenes[folder]
            load_lock = self._load_locks.setdefault(folder, threading.Lock())
        with load_lock:  # one load per scene, however many requests arrive together
            with self._lock:
                if folder in self._scenes:
                    return self._scenes[folder]
            with self.storage.reading(folder) as local:
                if not local.exists():
                    raise FileNotFoundError(folder)
                baked = BakedScene.load(local)
            with self._lock:
                self._drop(folder.split("/", 1)[0])
                self._scenes[folder] = baked
                while len(self._scenes) > 1 and self.nbytes > self.capacity_bytes:
                    self._scenes.popitem(last=False)
                self._load_locks.pop(folder, None)
        return baked

    @property
    def nbytes(self) -> int:
        """Bytes held by the loaded scenes."""
        return sum(s.nbytes for s in self._scenes.values())

    def evict(self, scene_id: str) -> None:
        """Drop every loaded folder of scene ``scene_id``."""
        with self._lock:
            self._drop(scene_id)

    def _drop(self, scene_id: str) -> None:
        """Forget every loaded folder of scene ``scene_id`` (the lock held)."""
        for key in [k for k in self._scenes if k.split("/", 1)[0] == scene_id]:
            del self._scenes[key]

    def render(
        self,
        folder: str,
        K: np.ndarray,
        world_from_cam: np.ndarray,
        width: int,
        height: int,
        coverage: bool = False,
    ) -> Rendered:
        """Colour and depth of one camera (OpenCV convention, pixels, see cmc.geometry.cameras) from the
        baked scene in storage folder ``folder``, and with ``coverage`` which pixels show a point
        an input photo saw (:meth:`BakedScene.coverage`)."""
        baked = self.get(folder)
        out = baked.render(K, world_from_cam, width, height, threads=self.threads)
        seen = baked.coverage(K, world_from_cam, out.depth) if coverage else None
        return Rendered(out.rgb, out.depth, baked.near, baked.far, seen)


class RenderQueue:
    """``concurrency`` render threads of their own and at most ``waiting`` requests queued for
    them; a request beyond that is refused at once (503, ``Retry-After``)."""

    RETRY_AFTER_S = 1

    def __init__(self, concurrency: int, waiting: int):
        self._pool = ThreadPoolExecutor(concurrency, thread_name_prefix="cmc-render")
        self._capacity = concurrency + waiting
        self._admitted = 0  # running or waiting; a request that went away still counts until its render ends
        self._lock = threading.Lock()

    async def run(self, fn: Callable[[], T]) -> T:
        with self._lock:
            if self._admitted >= self._capacity:
                retry = {"Retry-After": str(self.RETRY_AFTER_S)}
                raise APIError(503, ErrorCode.renderer_busy, "every render slot is taken; retry shortly", headers=retry)
            self._admitted += 1
        future = self._pool.submit(fn)
        future.add_done_callback(self._release)
        return await asyncio.wrap_future(future)  # cancelled with the request if it has not started

    def _release(self, _: Future) -> None:
        with self._lock:
            self._admitted -= 1

    def close(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)


def encode_image(rgb: np.ndarray, media_type: str, alpha: np.ndarray | None = None) -> bytes:
    """[H, W, 3] float in [0, 1] -> PNG or JPEG bytes; with ``alpha`` [H, W] bool an RGBA PNG
    (opaque where True)."""
    from cmc.data.images import to_uint8

    rgb8 = to_uint8(rgb)
    if alpha is not None:
        if media_type == "image/jpeg":
            raise ValueError("JPEG has no alpha channel")
        return png_bytes(np.concatenate([rgb8, (alpha * 255).astype(np.uint8)[..., None]], -1))
    if media_type != "image/jpeg":
        return png_bytes(rgb8)
    buf = io.BytesIO()
    Image.fromarray(rgb8).save(buf, "JPEG", quality=90)
    return buf.getvalue()


def png_bytes(image: np.ndarray) -> bytes:
    """[H, W, 3] uint8 (RGB), [H, W, 4] uint8 (RGBA), [H, W] uint16 (greyscale) or [H, W, 2]
    uint16 (greyscale and alpha) -> PNG bytes, made for speed.

    Every row gets the PNG "sub" filter (each byte minus the one a pixel to its left), then zlib
    level 1 with its run-length strategy. Pillow tries all five PNG filters on every row and keeps
    the best (as libpng does): on a 504x378 view that took 14 ms against 6 ms here, for 4 % fewer
    bytes (bench/reports/history/RESULTS-until-2026-11-27.md, serving cost).
    """
    channels = 1 if image.ndim == 2 else image.shape[2]
    colour_type = {1: 0, 2: 4, 3: 2, 4: 6}.get(channels)  # grey, grey + alpha, RGB, RGBA
    if image.dtype == np.uint8 and image.ndim == 3 and channels in (3, 4):
        bits, bpp, data = 8, channels, image
    elif image.dtype == np.uint16 and (image.ndim == 2 or channels == 2):
        bits, bpp, data = 16, 2 * channels, image.astype(">u2").view(np.uint8)  # big-endian samples
    else:
        raise ValueError(
            f"png_bytes takes [H, W, 3 or 4] uint8 or [H, W (, 2)] uint16, not {image.dtype} {image.shape}"
        )
    h, w = image.shape[:2]
    rows = np.ascontiguousarray(data).reshape(h, -1)
    filtered = np.empty((h, rows.shape[1] + 1), np.uint8)
    filtered[:, 0] = 1  # filter type "sub"
    filtered[:, 1 : bpp + 1] = rows[:, :bpp]
    np.subtract(rows[:, bpp:], rows[:, :-bpp], out=filtered[:, bpp + 1 :])  # wraps modulo 256, as PNG wants
    deflate = zlib.compressobj(1, zlib.DEFLATED, 15, 9, zlib.Z_RLE)
    idat = deflate.compress(filtered.data) + deflate.flush()

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    header = struct.pack(">IIBBBBB", w, h, bits, colour_type, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def depth_scale(far: float) -> float:
    """Scene units per count of the 16-bit depth PNG."""
    return 2.0 * far / 65535.0


def encode_depth_png16(depth: np.ndarray, far: float, coverage: np.ndarray | None = None) -> bytes:
    """16-bit greyscale (:func:`depth_scale` per count), with ``coverage`` greyscale + alpha
    (alpha 65535 where True, 0 elsewhere)."""
    counts = np.clip(np.round(depth / depth_scale(far)), 0, 65535).astype(np.uint16)
    if coverage is None:
        return png_bytes(counts)
    return png_bytes(np.stack([counts, coverage.astype(np.uint16) * 65535], -1))


def encode_depth_npy(depth: np.ndarray, coverage: np.ndarray | None = None) -> bytes:
    """float32 [H, W]; with ``coverage`` NaN where it is False and a surface was hit."""
    depth = depth.astype(np.float32)
    if coverage is not None:
        depth = np.where(coverage | (depth == 0), depth, np.float32(np.nan))
    buf = io.BytesIO()
    np.save(buf, depth)
    return buf.getvalue()


def encode_depth_preview(depth: np.ndarray, near: float, far: float, coverage: np.ndarray | None = None) -> bytes:
    from cmc.eval.diagnostics import depth_preview

    return encode_image(depth_preview(depth, near, far) * (depth > 0)[..., None], "image/png", coverage)
