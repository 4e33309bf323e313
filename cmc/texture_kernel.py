"""Compiled CPU renderer of baked MPIs: the serving renderer.

:func:`render` computes what :func:`cmc.rendering.render_image` computes (that function's and
:func:`cmc.rendering.render_texture_image`'s docstrings derive the warp and the composite),
straight from the 8-bit textures, so a loaded scene needs no float copy.

Memory (:class:`PackedTextures`): every plane of every MPI in one buffer of 32-bit words, one
RGBA texel (straight alpha, as in the atlases) per word, each plane framed by one transparent
texel. A bilinear sample is four word loads, and a tap beyond the plane's edge reads the frame:
zero padding without a branch or a clamp.

Order of work: the target rows go in bands of ``ROWS``; per band, MPI by MPI, plane by plane
over the band's pixels (the plane's texels under the band stay in the CPU's caches while its
samples are taken), each pixel's transmittance and sums in small per-band arrays, and the blend
of the MPIs (:func:`cmc.rendering.blend`) at the end of the band, so the output is written once.
Pixel-major order (every plane per pixel, sums in registers) was 1.3x slower on fern: a row's
144 planes do not fit in the caches. Indices are unsigned (numba then adds no negative-index
wrap-around) and multiply-adds may fuse (``fastmath={"contract"}``, nothing else): each took
about a tenth off the render. Work it skips:

* **rays that see nothing of a plane**: a plane crossing behind the target camera (a ray only
  visits the planes on its side of the target centre: a contiguous range, no per-plane test),
  or outside the plane.
* **empty tiles**: an occupancy byte per 8x8 texel tile per plane says whether a bilinear sample
  whose top-left tap lies in the tile can have any alpha (its four taps cover the tile grown by
  one texel to the right and below). Elsewhere the sample is exactly zero (premultiplied
  colour), so skipping it changes nothing.
* **opaque rays**: a ray leaves the band's list of live rays once its transmittance is below
  ``min_transmittance`` (default 1e-4); what is left changes a pixel by less than that.

What it cannot skip, on fern (bench/RESULTS.md): the alphas are spread thin (most planes hold
faint alpha in front of and behind the surfaces), so a ray crosses 37 of the 48 planes of an
MPI before it is opaque and 25 of those crossings hold alpha; a threshold of 1e-3 would save
only a tenth of them. The render is bound by those 14 million bilinear RGBA samples.

Threads: :func:`render` splits the rows into bands of ``ROWS`` over ``threads`` threads (the
kernel releases the GIL); renders on several threads at once are safe.

Pixel and grid conventions are those of the torch twin: pixel centres at (u + 0.5, v + 0.5),
``grid_sample(align_corners=False)`` texel centres, zero outside the plane, crossings behind the
target camera transparent.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numba
import numpy as np

TILE_SHIFT = 3
TILE = 1 << TILE_SHIFT  # texels per occupancy tile side
ROWS = 4  # target rows per band (the unit of work a thread takes)


@dataclass(frozen=True)
class PackedTextures:
    """The textures of N MPIs in one buffer, as the kernel samples them.

    Attributes:
        texels: flat little-endian uint32, one RGBA texel a word (R in the low byte, straight
            alpha in the high byte); plane k of MPI i is an (h_i + 2) x (w_i + 2) block starting
            at ``base[i, k]``, its texels framed by a transparent border.
        base: [N, Dmax] int64 start of each plane's block.
        shapes: [N, 3] int64 (D_i, h_i, w_i) of each MPI.
        occ: flat uint8 occupancy (:func:`occupancy`), plane k of MPI i at ``obase[i, k]``.
        obase: [N, Dmax] int64; otiles: [N] int64 tiles per occupancy row of MPI i.
    """

    texels: np.ndarray
    base: np.ndarray
    shapes: np.ndarray
    occ: np.ndarray
    obase: np.ndarray
    otiles: np.ndarray

    @staticmethod
    def allocate(shapes: Sequence[tuple[int, int, int]]) -> PackedTextures:
        """Zeroed buffers for MPIs of (D, h, w) planes; fill them with :meth:`fill`."""
        n, dmax = len(shapes), max(s[0] for s in shapes)
        base, obase = np.zeros((n, dmax), np.int64), np.zeros((n, dmax), np.int64)
        otiles = np.zeros(n, np.int64)
        size = osize = 0
        for i, (D, h, w) in enumerate(shapes):
            th, tw = _tiles(h, w)
            base[i, :D] = size + np.arange(D) * (h + 2) * (w + 2)
            obase[i, :D] = osize + np.arange(D) * th * tw
            otiles[i] = tw
            size += D * (h + 2) * (w + 2)
            osize += D * th * tw
        return PackedTextures(
            np.zeros(size, np.dtype("<u4")),
            base,
            np.asarray(shapes, np.int64),
            np.zeros(osize, np.uint8),
            obase,
            otiles,
        )

    @staticmethod
    def pack(textures: Sequence[np.ndarray]) -> PackedTextures:
        """From [D, h, w, 4] uint8 straight-alpha textures, one per MPI."""
        packed = PackedTextures.allocate([t.shape[:3] for t in textures])
        for i, tex in enumerate(textures):
            packed.fill(i, tex)
        return packed

    def fill(self, i: int, tex: np.ndarray) -> None:
        """Store MPI i's [D, h, w, 4] uint8 textures and their occupancy."""
        D, h, w = (int(s) for s in self.shapes[i])
        assert tex.shape == (D, h, w, 4) and tex.dtype == np.uint8
        self._padded(i)[:, 1:-1, 1:-1] = tex
        th, tw = _tiles(h, w)
        self.occ[self.obase[i, 0] : self.obase[i, 0] + D * th * tw] = occupancy(tex).reshape(-1)

    def _padded(self, i: int) -> np.ndarray:
        D, h, w = (int(s) for s in self.shapes[i])
        start = self.base[i, 0]
        return self.texels[start : start + D * (h + 2) * (w + 2)].view(np.uint8).reshape(D, h + 2, w + 2, 4)

    def texture(self, i: int) -> np.ndarray:
        """[D, h, w, 4] uint8 view (no copy) of MPI i's textures."""
        return self._padded(i)[:, 1:-1, 1:-1]

    @property
    def nbytes(self) -> int:
        return self.texels.nbytes + self.occ.nbytes + self.base.nbytes + self.obase.nbytes


def _tiles(h: int, w: int) -> tuple[int, int]:
    """Occupancy tiles (rows, columns) of a plane of h x w texels, framed: (h + 2) x (w + 2)."""
    return -(-(h + 2) // TILE), -(-(w + 2) // TILE)


def occupancy(rgba: np.ndarray) -> np.ndarray:
    """[D, th, tw] uint8 over the framed planes ((h + 2) x (w + 2) texels, see
    :class:`PackedTextures`): 1 where a bilinear sample whose top-left tap lies in the tile can
    have alpha, i.e. where the tile grown by one texel to the right and below holds any.

    Shape: rgba [D, h, w, 4] uint8 (straight alpha) -> [D, ceil((h + 2) / 8), ceil((w + 2) / 8)].
    """
    D, h, w, _ = rgba.shape
    th, tw = _tiles(h, w)
    a = np.zeros((D, th * TILE + 1, tw * TILE + 1), dtype=bool)
    a[:, 1 : h + 1, 1 : w + 1] = rgba[..., 3] > 0
    reach = a[:, :-1, :-1] | a[:, 1:, :-1] | a[:, :-1, 1:] | a[:, 1:, 1:]  # taps of (y, x): (y..y+1, x..x+1)
    return reach.reshape(D, th, TILE, tw, TILE).any(axis=(2, 4)).astype(np.uint8)


@dataclass(frozen=True)
class MPIGeometry:
    """An MPI's reference camera and planes (:class:`cmc.rendering.MPIFrame` in float64 NumPy)."""

    K: np.ndarray  # [3, 3]
    ref_from_world: np.ndarray  # [4, 4]
    depths: np.ndarray  # [D], nearest first
    width: int
    height: int
    margin: float

    @staticmethod
    def from_frame(frame) -> MPIGeometry:
        f64 = lambda a: np.asarray(a.detach().cpu(), dtype=np.float64)  # noqa: E731
        return MPIGeometry(
            f64(frame.K),
            np.linalg.inv(f64(frame.world_from_ref)),
            f64(frame.depths),
            frame.width,
            frame.height,
            float(frame.margin),
        )


def _plane_params(g: MPIGeometry, h: int, w: int, K_tgt: np.ndarray, world_from_tgt: np.ndarray):
    """Per target pixel p = (u, v, 1): ``Q p = (M d(p), d_z(p))`` with d(p) the reference-frame
    ray direction and M reference pixels -> plane grid (see :func:`cmc.rendering.render_texture_image`);
    per plane k the framed texel coordinates ``(ax_k m_x + bx_k, ay_k m_y + by_k)`` of the crossing,
    ``m = M d / d_z``, and ``e_k`` (the crossing's target depth is ``e_k / d_z``); and the number
    of planes with ``e_k <= 0`` (behind the target centre: seen by rays with ``d_z < 0`` only)."""
    mg = g.margin
    M = np.array([[2 / (g.width * mg), 0, -1 / mg], [0, 2 / (g.height * mg), -1 / mg]]) @ g.K
    ref_from_tgt = g.ref_from_world @ world_from_tgt
    R, t = ref_from_tgt[:3, :3], ref_from_tgt[:3, 3]
    d_from_pixel = R @ np.linalg.inv(K_tgt)
    Q = np.concatenate([M @ d_from_pixel, d_from_pixel[2:]])
    z = g.depths
    e = z - t[2]
    scale = e / z
    off = (M @ t)[None] / z[:, None]  # [D, 2]
    off[e == 0] = 1e12  # a plane through the target centre is seen edge-on: transparent
    # grid x -> framed texel x: ((x + 1) w - 1) / 2 + 1 (align_corners=False, one texel of frame)
    ax, bx = scale * w / 2, ((off[:, 0] + 1) * w + 1) / 2
    ay, by = scale * h / 2, ((off[:, 1] + 1) * h + 1) / 2
    return Q, ax, bx, ay, by, e, int((e <= 0).sum())


@numba.njit(nogil=True, cache=True, boundscheck=False, error_model="numpy", fastmath={"contract"})
def _render_bands(
    texels, base, shapes, occ, obase, otiles, use, weights, Q, ax, bx, ay, by, e, split,
    width, height, band0, band_step, rows, min_trans, rgb, depth, acc,
):  # pragma: no cover - compiled  # fmt: skip
    n_mpi = use.shape[0]
    inv255 = np.float32(1.0 / 255.0)
    inv255sq = np.float32(1.0 / 255.0**2)
    zero, one, t_min = np.float32(0.0), np.float32(1.0), np.float32(min_trans)
    npx = rows * width
    # Per pixel of a band: m(p), d_z(p), this MPI's transmittance and sums, the blend's sums.
    mx, my, dz = np.empty(npx, np.float32), np.empty(npx, np.float32), np.empty(npx, np.float64)
    trans, cr, cg = np.empty(npx, np.float32), np.empty(npx, np.float32), np.empty(npx, np.float32)
    cb, cd = np.empty(npx, np.float32), np.empty(npx, np.float32)
    b_tot, b_r, b_g = np.empty(npx, np.float64), np.empty(npx, np.float64), np.empty(npx, np.float64)
    b_b, b_d, b_a = np.empty(npx, np.float64), np.empty(npx, np.float64), np.empty(npx, np.float64)
    live = np.empty(npx, np.uint32)  # the band's rays still compositing the current MPI
    for band in range(band0, (height + rows - 1) // rows, band_step):
        y_lo = band * rows
        n = (min(height, y_lo + rows) - y_lo) * width
        b_tot[:n], b_r[:n], b_g[:n], b_b[:n], b_d[:n], b_a[:n] = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
        for j in range(n_mpi):
            i = use[j]
            D, h, w = shapes[i, 0], shapes[i, 1], shapes[i, 2]
            xmax, ymax = np.float32(w + 1), np.float32(h + 1)
            stride, tiles = w + 2, otiles[i]
            for p in range(n):
                u, v = p % width + 0.5, y_lo + p // width + 0.5
                dz[p] = Q[j, 2, 0] * u + Q[j, 2, 1] * v + Q[j, 2, 2]
                mx[p] = (Q[j, 0, 0] * u + Q[j, 0, 1] * v + Q[j, 0, 2]) / dz[p]
                my[p] = (Q[j, 1, 0] * u + Q[j, 1, 1] * v + Q[j, 1, 2]) / dz[p]
                trans[p], cr[p], cg[p], cb[p], cd[p] = 1.0, 0.0, 0.0, 0.0, 0.0
            # Crossings in front of the target: planes with e_k > 0 for rays with d_z > 0, planes
            # with e_k <= 0 for rays with d_z < 0 (a target inside the MPI looking back).
            for forward in (True, False):
                n_live = 0
                for p in range(n):
                    if (dz[p] > 0.0) if forward else (dz[p] < 0.0):
                        live[n_live] = np.uint32(p)
                        n_live += 1
                k_lo, k_hi = (split[j], D) if forward else (0, split[j])
                for k in range(k_lo, k_hi):
                    if n_live == 0:
                        break
                    axk, bxk = np.float32(ax[j, k]), np.float32(bx[j, k])
                    ayk, byk = np.float32(ay[j, k]), np.float32(by[j, k])
                    ek, tex0, occ0 = np.float32(e[j, k]), base[i, k], obase[i, k]
                    kept = 0
                    for q in range(n_live):
                        p = np.uint64(live[q])
                        fx = axk * mx[p] + bxk
                        fy = ayk * my[p] + byk
                        # Outside the plane (or NaN), or in an empty tile: nothing to composite.
                        if fx > zero and fy > zero and fx < xmax and fy < ymax:
                            x0, y0 = np.int32(fx), np.int32(fy)  # framed top-left tap: 0 <= x0 <= w
                            if occ[np.uint64(occ0 + (y0 >> TILE_SHIFT) * tiles + (x0 >> TILE_SHIFT))] != 0:
                                t = np.uint64(tex0 + y0 * stride + x0)
                                p00, p01 = texels[t], texels[t + 1]
                                p10, p11 = texels[t + stride], texels[t + stride + 1]
                                wx, wy = fx - np.float32(x0), fy - np.float32(y0)
                                w00 = (one - wy) * (one - wx) * np.float32(p00 >> 24)
                                w01 = (one - wy) * wx * np.float32(p01 >> 24)
                                w10 = wy * (one - wx) * np.float32(p10 >> 24)
                                w11 = wy * wx * np.float32(p11 >> 24)
                                sa = w00 + w01 + w10 + w11
                                if sa != zero:
                                    T = trans[p]
                                    tc = T * inv255sq  # colour: texel colour x texel alpha, both 8-bit
                                    cr[p] += tc * (
                                        w00 * np.float32(p00 & 255)
                                        + w01 * np.float32(p01 & 255)
                                        + w10 * np.float32(p10 & 255)
                                        + w11 * np.float32(p11 & 255)
                                    )
                                    cg[p] += tc * (
                                        w00 * np.float32((p00 >> 8) & 255)
                                        + w01 * np.float32((p01 >> 8) & 255)
                                        + w10 * np.float32((p10 >> 8) & 255)
                                        + w11 * np.float32((p11 >> 8) & 255)
                                    )
                                    cb[p] += tc * (
                                        w00 * np.float32((p00 >> 16) & 255)
                                        + w01 * np.float32((p01 >> 16) & 255)
                                        + w10 * np.float32((p10 >> 16) & 255)
                                        + w11 * np.float32((p11 >> 16) & 255)
                                    )
                                    ta = T * sa * inv255
                                    cd[p] += ta * ek
                                    T -= ta
                                    trans[p] = T
                                    if T < t_min:
                                        continue  # opaque: the ray leaves the live list
                        live[kept] = np.uint32(p)
                        kept += 1
                    n_live = kept
            wj = weights[j]
            for p in range(n):
                if dz[p] != 0.0:  # else no ray: this MPI covers nothing here
                    a = 1.0 - trans[p]
                    b_tot[p] += wj * a
                    b_r[p] += wj * cr[p]
                    b_g[p] += wj * cg[p]
                    b_b[p] += wj * cb[p]
                    b_d[p] += wj * cd[p] / dz[p]
                    b_a[p] = max(b_a[p], a)
        # cmc.rendering.blend: sum_i w_i C_i / sum_i w_i a_i, times the largest coverage.
        for p in range(n):
            y, x = y_lo + p // width, p % width
            norm = 1.0 / max(b_tot[p], 1e-8)
            rgb[y, x, 0] = b_r[p] * norm * b_a[p]
            rgb[y, x, 1] = b_g[p] * norm * b_a[p]
            rgb[y, x, 2] = b_b[p] * norm * b_a[p]
            depth[y, x] = b_d[p] * norm if b_a[p] > 1e-3 else 0.0
            acc[y, x] = b_a[p]


_POOL: ThreadPoolExecutor | None = None
_POOL_LOCK = threading.Lock()


def default_threads() -> int:
    return os.cpu_count() or 1


def _pool() -> ThreadPoolExecutor:
    global _POOL
    with _POOL_LOCK:
        if _POOL is None:
            _POOL = ThreadPoolExecutor(max(1, default_threads() - 1), thread_name_prefix="cmc-kernel")
        return _POOL


def render(
    packed: PackedTextures,
    mpis: Sequence[MPIGeometry],
    weights: np.ndarray,
    use: Sequence[int],
    K_tgt: np.ndarray,
    world_from_tgt: np.ndarray,
    width: int,
    height: int,
    min_transmittance: float = 1e-4,
    threads: int | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The blend of MPIs ``use`` (blend weights ``weights[i]``) seen from a target camera.

    Args:
        packed: the MPIs' textures; mpis: their geometry, in the same order.
        weights: [N] blend weights (:func:`cmc.rendering.blend_selection`); use: MPIs to render.
        K_tgt [3, 3], world_from_tgt [4, 4]: the target camera (OpenCV convention, see
            cmc.cameras); width, height in pixels.
        min_transmittance: stop compositing an MPI's ray below this transmittance (0: never).
        threads: threads for this render (default: one per core); the result does not depend on it.
    Returns:
        as :func:`cmc.rendering.blend`: rgb [height, width, 3] (colour times coverage), depth
        [height, width] (target z, 0 where the coverage is below 1e-3), coverage [height, width],
        float32.
    """
    K_tgt, world_from_tgt = np.asarray(K_tgt, np.float64), np.asarray(world_from_tgt, np.float64)
    use_a = np.asarray(list(use), np.int64)
    dmax = packed.base.shape[1]
    Q = np.zeros((len(use_a), 3, 3))
    ax, bx, ay, by, e = (np.zeros((len(use_a), dmax)) for _ in range(5))
    split = np.zeros(len(use_a), np.int64)
    for j, i in enumerate(use_a):
        _, h, w = packed.shapes[i]
        D = len(mpis[i].depths)
        Q[j], ax[j, :D], bx[j, :D], ay[j, :D], by[j, :D], e[j, :D], split[j] = _plane_params(
            mpis[i], int(h), int(w), K_tgt, world_from_tgt
        )
    w_use = np.asarray(weights, np.float64)[use_a]
    rgb = np.empty((height, width, 3), np.float32)
    depth = np.empty((height, width), np.float32)
    acc = np.empty((height, width), np.float32)
    n = max(1, min(threads or default_threads(), -(-height // ROWS)))

    def part(band0: int) -> None:
        _render_bands(
            packed.texels, packed.base, packed.shapes, packed.occ, packed.obase, packed.otiles, use_a, w_use,
            Q, ax, bx, ay, by, e, split, width, height, band0, n, ROWS, float(min_transmittance), rgb, depth, acc,
        )  # fmt: skip

    others = [_pool().submit(part, t) for t in range(1, n)]
    part(0)
    for f in others:
        f.result()
    return rgb, depth, acc


def warm_up() -> None:
    """Compile the kernel now (numba caches it on disk beside this module when that is writable),
    so the first render of a fresh process does not pay the compile; the Dockerfiles call it."""
    K = np.array([[4.0, 0, 2], [0, 4.0, 2], [0, 0, 1]])
    packed = PackedTextures.pack([np.full((2, 4, 4, 4), 255, dtype=np.uint8)])
    g = MPIGeometry(K, np.eye(4), np.array([1.0, 2.0]), 4, 4, 1.0)
    render(packed, [g], np.ones(1), [0], K, np.eye(4), 4, 4)
