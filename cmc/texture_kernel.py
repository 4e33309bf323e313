"""Compiled CPU compositing of baked MPIs: the serving renderer.

:func:`render_baked_mpi` computes what :func:`cmc.rendering.render_image` computes for one MPI
(that function's docstring derives the warp and the composite), straight from the 8-bit textures
([D, h, w, 4], straight alpha, as in the atlases, premultiplied on the fly), so a loaded scene
needs no float copy: an eighth of the memory of the torch path's two float32 copies. Blocks of
target rows run in parallel (numba, compiled on first use and cached on disk); within a block,
planes go one at a time over its pixels, so a plane's texels stay in cache. Work it skips:

* **empty tiles**: an occupancy map per plane (:func:`occupancy`) says which 8x8 texel tiles
  hold any alpha, after growing the alpha by one texel so that all four taps of a bilinear
  sample fall inside the tile of its top-left tap. A sample there is exactly zero (the textures
  are premultiplied), so skipping it changes nothing.
* **opaque rays**: compositing stops once the transmittance is below ``min_transmittance``
  (default 1e-4); what is left changes a pixel by less than that.

How much that saves depends on the scene: on fern (bench/RESULTS.md) most texels of most planes
hold some faint alpha, and the render is only about 1.1x faster than the torch path.

Pixel and grid conventions are those of the torch twin: pixel centres at (u + 0.5, v + 0.5),
``grid_sample(align_corners=False)`` texel centres, zero outside the plane, crossings behind the
target camera transparent.
"""

from __future__ import annotations

import math
import threading

import numba
import numpy as np

TILE_SHIFT = 3
TILE = 1 << TILE_SHIFT  # texels per occupancy tile side
# One kernel call at a time: each already uses every core, and numba's fallback threading layer
# (workqueue, used where neither OpenMP nor TBB is installed) aborts on concurrent calls.
_KERNEL_LOCK = threading.Lock()
ROWS = 8  # target rows per block (the unit of parallel work; its accumulators stay in cache)


def occupancy(rgba: np.ndarray, tile: int = TILE) -> np.ndarray:
    """[D, ceil(h / tile), ceil(w / tile)] bool: tiles whose texels, grown by one texel, hold alpha.

    Shape: rgba [D, h, w, 4] uint8 (straight alpha).
    """
    D, h, w, _ = rgba.shape
    a = rgba[..., 3] > 0
    grown = a.copy()
    grown[:, 1:] |= a[:, :-1]
    grown[:, :-1] |= a[:, 1:]
    g2 = grown.copy()
    g2[:, :, 1:] |= grown[:, :, :-1]
    g2[:, :, :-1] |= grown[:, :, 1:]
    th, tw = -(-h // tile), -(-w // tile)
    padded = np.zeros((D, th * tile, tw * tile), dtype=bool)
    padded[:, :h, :w] = g2
    return padded.reshape(D, th, tile, tw, tile).any(axis=(2, 4))


@numba.njit(parallel=True, cache=True, fastmath=False, boundscheck=False)
def _composite(
    tex, occ, tile, Q, scales, offsets, e, front, width, height, min_trans, rows, rgb, depth, acc
):  # pragma: no cover - compiled
    D, h, w = tex.shape[0], tex.shape[1], tex.shape[2]
    inv255 = np.float32(1.0 / 255.0)
    inv255sq = np.float32(1.0 / 255.0**2)
    n_blocks = (height + rows - 1) // rows
    for blk in numba.prange(n_blocks):
        y_lo = blk * rows
        y_hi = min(height, y_lo + rows)
        n = (y_hi - y_lo) * width
        # Per pixel of the block: m(p) (plane-independent), d_z(p), transmittance, accumulators.
        mxs = np.empty(n, np.float32)
        mys = np.empty(n, np.float32)
        dzs = np.empty(n, np.float32)
        trans = np.ones(n, np.float32)
        acc_rgb = np.zeros((n, 3), np.float32)
        dsum = np.zeros(n, np.float32)
        for j in range(n):
            u = j % width + 0.5
            v = y_lo + j // width + 0.5
            dz = Q[2, 0] * u + Q[2, 1] * v + Q[2, 2]
            dzs[j] = dz
            if dz != 0.0:
                mxs[j] = (Q[0, 0] * u + Q[0, 1] * v + Q[0, 2]) / dz
                mys[j] = (Q[1, 0] * u + Q[1, 1] * v + Q[1, 2]) / dz
            else:
                trans[j] = 0.0  # no ray: nothing to composite (coverage is set below)
        # Planes outer, pixels inner: one plane's texels stay in cache for the block.
        for k in range(D):
            sk, ox, oy, fk = np.float32(scales[k]), np.float32(offsets[k, 0]), np.float32(offsets[k, 1]), front[k]
            for j in range(n):
                T = trans[j]
                if T < min_trans or (dzs[j] > 0.0) != fk:
                    continue
                ix = ((sk * mxs[j] + ox + 1.0) * w - 1.0) * 0.5
                iy = ((sk * mys[j] + oy + 1.0) * h - 1.0) * 0.5
                if not (ix > -1.0 and iy > -1.0 and ix < w and iy < h):
                    continue
                fx, fy = math.floor(ix), math.floor(iy)
                x0, y0 = int(fx), int(fy)
                if not occ[k, max(y0, 0) >> TILE_SHIFT, max(x0, 0) >> TILE_SHIFT]:
                    continue
                # Bilinear taps (x0 | x1) x (y0 | y1); a tap outside the plane weighs 0 (zero padding).
                wx, wy = np.float32(ix - fx), np.float32(iy - fy)
                wx0 = 1.0 - wx if x0 >= 0 else 0.0
                wx1 = wx if x0 + 1 < w else 0.0
                wy0 = 1.0 - wy if y0 >= 0 else 0.0
                wy1 = wy if y0 + 1 < h else 0.0
                xa, xb, ya, yb = max(x0, 0), min(x0 + 1, w - 1), max(y0, 0), min(y0 + 1, h - 1)
                w00 = wy0 * wx0 * tex[k, ya, xa, 3]
                w01 = wy0 * wx1 * tex[k, ya, xb, 3]
                w10 = wy1 * wx0 * tex[k, yb, xa, 3]
                w11 = wy1 * wx1 * tex[k, yb, xb, 3]
                sa = (w00 + w01 + w10 + w11) * inv255
                if sa == 0.0:
                    continue
                for c in range(3):  # premultiplied colour: texel colour x texel alpha, both 8-bit
                    acc_rgb[j, c] += (
                        T
                        * inv255sq
                        * (
                            w00 * tex[k, ya, xa, c]
                            + w01 * tex[k, ya, xb, c]
                            + w10 * tex[k, yb, xa, c]
                            + w11 * tex[k, yb, xb, c]
                        )
                    )
                dsum[j] += T * sa * e[k]
                trans[j] = T * (1.0 - sa)
        for j in range(n):
            y, x = y_lo + j // width, j % width
            rgb[y, x, 0] = acc_rgb[j, 0]
            rgb[y, x, 1] = acc_rgb[j, 1]
            rgb[y, x, 2] = acc_rgb[j, 2]
            if dzs[j] != 0.0:
                depth[y, x] = dsum[j] / dzs[j]
                acc[y, x] = 1.0 - trans[j]
            else:
                depth[y, x] = 0.0
                acc[y, x] = 0.0


def render_baked_mpi(
    tex: np.ndarray,
    occ: np.ndarray,
    frame,
    K_tgt: np.ndarray,
    world_from_tgt: np.ndarray,
    width: int,
    height: int,
    min_transmittance: float = 1e-4,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One baked MPI seen from a target camera (OpenCV convention, see cmc.cameras).

    Args:
        tex: [D, h, w, 4] uint8 straight-alpha textures, nearest plane first, the back plane's
            alpha already 255 where the plane is covered (as baked).
        occ: :func:`occupancy` of ``tex``.
        frame: the MPI's :class:`cmc.rendering.MPIFrame`.
        K_tgt [3, 3], world_from_tgt [4, 4]: the target camera; width, height in pixels.
        min_transmittance: stop compositing a ray below this transmittance (0: never).
    Returns:
        premultiplied rgb [height, width, 3], depth [height, width] (target z, weighted by
        coverage), coverage [height, width], float32.
    """
    f64 = lambda a: np.asarray(a, dtype=np.float64)  # noqa: E731
    K_ref, z = f64(frame.K.cpu()), f64(frame.depths.cpu())
    mg = frame.margin
    grid_from_ref_pixels = np.array([[2 / (frame.width * mg), 0, -1 / mg], [0, 2 / (frame.height * mg), -1 / mg]])
    M = grid_from_ref_pixels @ K_ref  # [2, 3]
    ref_from_tgt = f64(frame.ref_from_world.cpu()) @ f64(world_from_tgt)
    R, t = ref_from_tgt[:3, :3], ref_from_tgt[:3, 3]
    d_from_pixel = R @ np.linalg.inv(f64(K_tgt))
    Q = np.concatenate([M @ d_from_pixel, d_from_pixel[2:]])  # pixel (u, v, 1) -> (M d(p), d_z(p))
    e = z - t[2]
    scales = e / z
    offsets = (M @ t)[None] / z[:, None]
    offsets[e == 0] = 1e12  # a plane through the target centre is seen edge-on: transparent
    rgb = np.empty((height, width, 3), dtype=np.float32)
    depth = np.empty((height, width), dtype=np.float32)
    acc = np.empty((height, width), dtype=np.float32)
    with _KERNEL_LOCK:
        _composite(
            np.ascontiguousarray(tex),
            occ,
            TILE,
            Q,
            scales,
            offsets,
            e,
            e > 0,
            width,
            height,
            min_transmittance,
            ROWS,
            rgb,
            depth,
            acc,
        )
    return rgb, depth, acc


def warm_up() -> None:
    """Compile the kernel now (numba caches it on disk beside this module when that is writable),
    so the first render of a fresh process does not pay the ~6 s compile; the Dockerfiles call it."""
    from cmc.rendering import MPIFrame

    K = np.array([[4.0, 0, 2], [0, 4.0, 2], [0, 0, 1]])
    tex = np.full((2, 4, 4, 4), 255, dtype=np.uint8)
    frame = MPIFrame.create(K, np.eye(4), 1.0, 2.0, 2, 4, 4, 1.0, "cpu")
    render_baked_mpi(tex, occupancy(tex), frame, K, np.eye(4), 4, 4)
