"""Compiled CPU renderer of baked MPIs: the serving renderer.

:func:`render` computes what :func:`cmc.mpi.rendering.render_image` computes (that function's and
:func:`cmc.mpi.rendering.render_texture_image`'s docstrings derive the warp and the composite),
straight from the 8-bit textures, so a loaded scene needs no float copy.

Memory (:class:`PackedTextures`): every plane of every MPI in one buffer of 32-bit words, one
RGBA texel (straight alpha, as in the atlases) per word, each plane framed by one transparent
texel. A bilinear sample is four word loads, and a tap beyond the plane's edge reads the frame:
zero padding without a branch or a clamp. A scene baked with bicubic colour
(``colour_interpolation``) takes alpha the same way and colour from 16 texels, their indices
clamped to the plane's edge, where the sample weighs at least ``bicubic_min_weight`` in its
pixel (:data:`cmc.mpi.rendering.BICUBIC_MIN_WEIGHT`), and from the four bilinear taps where it
weighs less: most samples with alpha weigh under 1 %, and the two extra texel rows a bicubic
sample reads (not its arithmetic) made a fern render with every sample bicubic 2.4 times as
long as with none. Beside the texels, per texel one reach bit and per 8x8 texel tile a
summed-area table of occupancy (4 % more memory), both computed when a scene is loaded.

Order of work: the target rows go in bands of ``ROWS``, a band in blocks of ``ROWS`` x ``COLS``
pixels (the live rays of a block are the set bits of one 64-bit word); per band, MPI by MPI,
plane by plane over the band's blocks (the plane's texels under the band stay in the CPU's
caches while its samples are taken), each pixel's transmittance and sums in small per-band
arrays, and the blend of the MPIs (:func:`cmc.mpi.rendering.blend`) at the end of the band, so the
output is written once. Pixel-major order (every plane per pixel, sums in registers) was 1.3x
slower on fern: a row's 144 planes do not fit in the caches. For a block and a plane, one loop
finds the live rays whose sample can have alpha (without a branch on the texels) and a second
one samples them: the second has no branch that depends on the data, so the CPU overlaps the
samples of several rays (on fern, 1.15x faster than one loop that branched on each ray's alpha;
the render is bound by that latency and by branches, not by memory: textures a quarter the size
render no faster). Indices are unsigned (numba then adds no negative-index wrap-around) and
multiply-adds may fuse (``fastmath={"contract"}``, nothing else). Work it skips, all exactly:

* **rays that see nothing of a plane**: a plane crossing behind the target camera (a ray only
  visits the planes on its side of the target centre: a contiguous range, no per-plane test),
  or outside the plane.
* **empty blocks**: the texels a block's rays sample on a plane lie in a box (the plane's map
  from m = M d / d_z to texels is affine, and the block's range of m is known); when the
  summed-area table says the box holds no occupied tile, the block skips the plane in O(1).
  On fern this removes 60 % of the ray-plane visits (from 19.5 to 8 million per render).
* **transparent samples**: a reach bit per texel says whether a bilinear sample whose top-left
  tap is that texel can have any alpha (its four taps: the texel, its right, lower and
  lower-right neighbours). Elsewhere the sample is exactly zero (premultiplied colour). The
  bake stores alpha under 1 % as 0 (:data:`cmc.serving.baking.ALPHA_FLOOR`), which clears the reach
  bits of faint fog: 22 % less time on fern.
* **opaque rays**: a ray leaves its block's live rays once its transmittance is below
  ``min_transmittance`` (default 1e-4); what is left changes a pixel by less than that.

What it cannot skip, on fern (bench/reports/history/RESULTS-until-2026-11-27.md): a render takes
about 4.5 million bilinear samples with alpha (3 MPIs x 190,000 pixels x 8), each four texel
loads and about a hundred instructions.

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
from numba.cpython.unsafe.numbers import trailing_zeros  # numba's count of trailing zero bits (tzcnt); numba is pinned

from cmc import kernel_cache
from cmc.mpi.plane_sampling import INTERPOLATIONS, check_interpolation, cubic_weights
from cmc.mpi.rendering import BICUBIC_MIN_WEIGHT

TILE_SHIFT = 3
TILE = 1 << TILE_SHIFT  # texels per occupancy tile side
ROWS = 8  # target rows per band (the unit of work a thread takes)
COLS = 8  # target columns per block (rays that skip a plane's empty region together)
assert ROWS * COLS <= 64, "a block's live rays are the bits of one 64-bit word"
kernel_cache.prepare()  # before the first kernel: numba needs a writable cache folder to define one


@dataclass(frozen=True)
class PackedTextures:
    """The textures of N MPIs in one buffer, as the kernel samples them.

    Attributes:
        texels: flat little-endian uint32, one RGBA texel a word (R in the low byte, straight
            alpha in the high byte); plane k of MPI i is an (h_i + 2) x (w_i + 2) block starting
            at ``base[i, k]``, its texels framed by a transparent border; each MPI's planes start
            at a multiple of 8 words.
        reach: flat uint8 bitmap beside ``texels`` (bit ``t & 7`` of byte ``t >> 3`` for word
            ``t``): set where a bilinear sample whose top-left tap is texel t can have alpha,
            i.e. where t, its right, lower or lower-right neighbour has some (:func:`reach`).
        base: [N, Dmax] int64 start of each plane's block.
        shapes: [N, 3] int64 (D_i, h_i, w_i) of each MPI.
        sat: flat int32 summed-area tables of the tile occupancy (:func:`occupancy`,
            :func:`occupied_tiles`), plane k of MPI i a (th + 1) x (otiles[i] + 1) block at
            ``sbase[i, k]``; sbase: [N, Dmax] int64; otiles: [N] int64 tiles per occupancy row.
    """

    texels: np.ndarray
    reach: np.ndarray
    base: np.ndarray
    shapes: np.ndarray
    sat: np.ndarray
    sbase: np.ndarray
    otiles: np.ndarray

    @staticmethod
    def allocate(shapes: Sequence[tuple[int, int, int]]) -> PackedTextures:
        """Zeroed buffers for MPIs of (D, h, w) planes; fill them with :meth:`fill`."""
        n, dmax = len(shapes), max(s[0] for s in shapes)
        base, sbase = np.zeros((n, dmax), np.int64), np.zeros((n, dmax), np.int64)
        otiles = np.zeros(n, np.int64)
        size = ssize = 0
        for i, (D, h, w) in enumerate(shapes):
            th, tw = _tiles(h, w)
            base[i, :D] = size + np.arange(D) * (h + 2) * (w + 2)
            sbase[i, :D] = ssize + np.arange(D) * (th + 1) * (tw + 1)
            otiles[i] = tw
            size += -(-D * (h + 2) * (w + 2) // 8) * 8  # the next MPI's bits start a byte of reach
            ssize += D * (th + 1) * (tw + 1)
        return PackedTextures(
            np.zeros(size, np.dtype("<u4")),
            np.zeros(size // 8, np.uint8),
            base,
            np.asarray(shapes, np.int64),
            np.zeros(ssize, np.int32),
            sbase,
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
        """Store MPI i's [D, h, w, 4] uint8 textures, their reach bits and tile occupancy."""
        D, h, w = (int(s) for s in self.shapes[i])
        assert tex.shape == (D, h, w, 4) and tex.dtype == np.uint8
        padded = self._padded(i)
        padded[:, 1:-1, 1:-1] = tex
        bits = np.packbits(reach(padded[..., 3]).reshape(-1), bitorder="little")
        start = self.base[i, 0] // 8
        self.reach[start : start + len(bits)] = bits
        th, tw = _tiles(h, w)
        sat = occupied_tiles(occupancy(tex))
        self.sat[self.sbase[i, 0] : self.sbase[i, 0] + D * (th + 1) * (tw + 1)] = sat.reshape(-1)

    def _padded(self, i: int) -> np.ndarray:
        D, h, w = (int(s) for s in self.shapes[i])
        start = self.base[i, 0]
        return self.texels[start : start + D * (h + 2) * (w + 2)].view(np.uint8).reshape(D, h + 2, w + 2, 4)

    def texture(self, i: int) -> np.ndarray:
        """[D, h, w, 4] uint8 view (no copy) of MPI i's textures."""
        return self._padded(i)[:, 1:-1, 1:-1]

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in (self.texels, self.reach, self.base, self.sat, self.sbase))


def reach(alpha: np.ndarray) -> np.ndarray:
    """[..., H, W] bool: where a bilinear sample with its top-left tap at (y, x) reads some
    alpha, i.e. where ``alpha[y : y + 2, x : x + 2]`` (zero beyond the edges) has any.

    Shape: alpha [..., H, W] (any dtype, 0 = transparent) -> [..., H, W] bool.
    """
    a = np.zeros((*alpha.shape[:-2], alpha.shape[-2] + 1, alpha.shape[-1] + 1), dtype=bool)
    a[..., :-1, :-1] = alpha > 0
    return a[..., :-1, :-1] | a[..., 1:, :-1] | a[..., :-1, 1:] | a[..., 1:, 1:]


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
    a = np.zeros((D, th * TILE, tw * TILE), dtype=bool)  # the framed planes, padded to whole tiles
    a[:, 1 : h + 1, 1 : w + 1] = rgba[..., 3] > 0
    return reach(a).reshape(D, th, TILE, tw, TILE).any(axis=(2, 4)).astype(np.uint8)


def occupied_tiles(occ: np.ndarray) -> np.ndarray:
    """Summed-area table of an occupancy map: ``sat[k, y, x]`` occupied tiles of plane k above
    row y and left of column x, so a rectangle of tiles is empty in four loads.

    Shape: occ [D, th, tw] -> [D, th + 1, tw + 1] int32.
    """
    D, th, tw = occ.shape
    sat = np.zeros((D, th + 1, tw + 1), np.int32)
    sat[:, 1:, 1:] = occ.astype(np.int32).cumsum(1).cumsum(2)
    return sat


@dataclass(frozen=True)
class MPIGeometry:
    """An MPI's reference camera and planes (:class:`cmc.mpi.rendering.MPIFrame` in float64 NumPy)."""

    K: np.ndarray  # [3, 3]
    ref_from_world: np.ndarray  # [4, 4]
    depths: np.ndarray  # [D], nearest first
    width: int
    height: int
    margin: tuple[float, float]  # (x, y)

    @staticmethod
    def from_frame(frame) -> MPIGeometry:
        f64 = lambda a: np.asarray(a.detach().cpu(), dtype=np.float64)  # noqa: E731
        return MPIGeometry(
            f64(frame.K),
            np.linalg.inv(f64(frame.world_from_ref)),
            f64(frame.depths),
            frame.width,
            frame.height,
            tuple(float(m) for m in frame.margin),
        )


def _plane_params(g: MPIGeometry, h: int, w: int, K_tgt: np.ndarray, world_from_tgt: np.ndarray):
    """Per target pixel p = (u, v, 1): ``Q p = (M d(p), d_z(p))`` with d(p) the reference-frame
    ray direction and M reference pixels -> plane grid (see :func:`cmc.mpi.rendering.render_texture_image`);
    per plane k the framed texel coordinates ``(ax_k m_x + bx_k, ay_k m_y + by_k)`` of the crossing,
    ``m = M d / d_z``, and ``e_k`` (the crossing's target depth is ``e_k / d_z``); and the number
    of planes with ``e_k <= 0`` (behind the target centre: seen by rays with ``d_z < 0`` only)."""
    mx, my = g.margin
    M = np.array([[2 / (g.width * mx), 0, -1 / mx], [0, 2 / (g.height * my), -1 / my]]) @ g.K
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
    texels, reach, base, shapes, sat, sbase, otiles, use, weights, Q, ax, bx, ay, by, e, split,
    width, height, band0, band_step, rows, cols, min_trans, cubic, cubic_min, rgb, depth, acc,
):  # pragma: no cover - compiled  # fmt: skip
    n_mpi = use.shape[0]
    inv255 = np.float32(1.0 / 255.0)
    inv255sq = np.float32(1.0 / 255.0**2)
    zero, one, t_min = np.float32(0.0), np.float32(1.0), np.float32(min_trans)
    full = np.float32(255.0)
    slack = np.float32(1.0 / 64.0)  # widens a block's texel box past any rounding of the samples'
    u1 = np.uint64(1)
    n_blocks = (width + cols - 1) // cols
    slots = rows * cols  # <= 64: a block's live rays are the set bits of one word
    # Per ray of a band, block by block (ray s = r * cols + c of block b, at row r and column
    # b * cols + c of the band, is at b * slots + s): m, d_z, this MPI's transmittance and sums,
    # the blend's sums.
    npx = n_blocks * slots
    mx, my, dz = np.zeros(npx, np.float32), np.zeros(npx, np.float32), np.zeros(npx, np.float64)
    trans, cr, cg = np.empty(npx, np.float32), np.empty(npx, np.float32), np.empty(npx, np.float32)
    cb, cd = np.empty(npx, np.float32), np.empty(npx, np.float32)
    b_tot, b_r, b_g = np.empty(npx, np.float64), np.empty(npx, np.float64), np.empty(npx, np.float64)
    b_b, b_d, b_a = np.empty(npx, np.float64), np.empty(npx, np.float64), np.empty(npx, np.float64)
    live = np.empty(n_blocks, np.uint64)  # per block, its rays still compositing this MPI
    hit_s, hit_t = np.empty(slots, np.uint64), np.empty(slots, np.uint64)
    hit_wx, hit_wy = np.empty(slots, np.float32), np.empty(slots, np.float32)
    hit_x, hit_y = np.empty(slots, np.int64), np.empty(slots, np.int64)  # framed top-left tap
    # Per block, the range of m over its live rays: the plane's texels they can sample lie in a box.
    mx_lo, mx_hi = np.empty(n_blocks, np.float32), np.empty(n_blocks, np.float32)
    my_lo, my_hi = np.empty(n_blocks, np.float32), np.empty(n_blocks, np.float32)
    for band in range(band0, (height + rows - 1) // rows, band_step):
        y_lo = band * rows
        n_rows = min(height, y_lo + rows) - y_lo
        b_tot[:], b_r[:], b_g[:], b_b[:], b_d[:], b_a[:] = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
        for j in range(n_mpi):
            i = use[j]
            D, h, w = shapes[i, 0], shapes[i, 1], shapes[i, 2]
            xmax, ymax = np.float32(w + 1), np.float32(h + 1)
            stride, tiles = w + 2, otiles[i]
            for b in range(n_blocks):
                for r in range(n_rows):
                    v = y_lo + r + 0.5
                    for c in range(min(cols, width - b * cols)):
                        g, u = b * slots + r * cols + c, b * cols + c + 0.5
                        dz[g] = Q[j, 2, 0] * u + Q[j, 2, 1] * v + Q[j, 2, 2]
                        inv = 1.0 / dz[g]
                        mx[g] = (Q[j, 0, 0] * u + Q[j, 0, 1] * v + Q[j, 0, 2]) * inv
                        my[g] = (Q[j, 1, 0] * u + Q[j, 1, 1] * v + Q[j, 1, 2]) * inv
                        trans[g], cr[g], cg[g], cb[g], cd[g] = 1.0, 0.0, 0.0, 0.0, 0.0
            # Crossings in front of the target: planes with e_k > 0 for rays with d_z > 0, planes
            # with e_k <= 0 for rays with d_z < 0 (a target inside the MPI looking back).
            for forward in (True, False):
                total = 0
                for b in range(n_blocks):
                    mask = np.uint64(0)
                    mx_lo[b], mx_hi[b] = np.inf, -np.inf
                    my_lo[b], my_hi[b] = np.inf, -np.inf
                    for r in range(n_rows):
                        for c in range(min(cols, width - b * cols)):
                            s = r * cols + c
                            g = b * slots + s
                            if (dz[g] > 0.0) if forward else (dz[g] < 0.0):
                                mask |= u1 << np.uint64(s)
                                mx_lo[b], mx_hi[b] = min(mx_lo[b], mx[g]), max(mx_hi[b], mx[g])
                                my_lo[b], my_hi[b] = min(my_lo[b], my[g]), max(my_hi[b], my[g])
                                total += 1
                    live[b] = mask
                k_lo, k_hi = (split[j], D) if forward else (0, split[j])
                for k in range(k_lo, k_hi):
                    if total == 0:
                        break
                    axk, bxk = np.float32(ax[j, k]), np.float32(bx[j, k])
                    ayk, byk = np.float32(ay[j, k]), np.float32(by[j, k])
                    ek, tex0, sat0 = np.float32(e[j, k]), base[i, k], sbase[i, k]
                    for b in range(n_blocks):
                        mask = live[b]
                        if mask == 0:
                            continue
                        # The block's rays sample this plane inside the box of fx, fy over its range
                        # of m (an affine map): skip the block when the box holds no occupied tile.
                        fx0, fx1 = axk * mx_lo[b] + bxk, axk * mx_hi[b] + bxk
                        fy0, fy1 = ayk * my_lo[b] + byk, ayk * my_hi[b] + byk
                        fx_lo, fx_hi = min(fx0, fx1) - slack, max(fx0, fx1) + slack
                        fy_lo, fy_hi = min(fy0, fy1) - slack, max(fy0, fy1) + slack
                        if fx_hi <= zero or fy_hi <= zero or fx_lo >= xmax or fy_lo >= ymax:
                            continue  # the whole box is off the plane
                        # Every ray of the block crosses the plane inside it: no per-ray test.
                        inside = fx_lo > zero and fy_lo > zero and fx_hi < xmax and fy_hi < ymax
                        if fx_lo > -1e9 and fy_lo > -1e9 and fx_hi < 1e9 and fy_hi < 1e9:  # finite
                            tx0 = np.int64(max(fx_lo, zero)) >> TILE_SHIFT
                            tx1 = (np.int64(min(fx_hi, xmax)) >> TILE_SHIFT) + 1
                            ty0 = np.int64(max(fy_lo, zero)) >> TILE_SHIFT
                            ty1 = (np.int64(min(fy_hi, ymax)) >> TILE_SHIFT) + 1
                            s0, s1 = sat0 + ty0 * (tiles + 1), sat0 + ty1 * (tiles + 1)
                            if sat[s1 + tx1] - sat[s1 + tx0] - sat[s0 + tx1] + sat[s0 + tx0] == 0:
                                continue  # only empty tiles: every sample is zero
                        g0 = b * slots
                        # First the rays whose four taps have some alpha, then their samples: the
                        # second loop has no branch that depends on the texels, so the CPU overlaps
                        # the samples of several rays.
                        n_hit = 0
                        rest = mask
                        while rest != 0:
                            s = trailing_zeros(rest)
                            rest &= rest - u1
                            g = g0 + s
                            fx = axk * mx[g] + bxk
                            fy = ayk * my[g] + byk
                            # Outside the plane (or NaN): nothing to composite.
                            if not inside and not (fx > zero and fy > zero and fx < xmax and fy < ymax):
                                continue
                            x0, y0 = np.int32(fx), np.int32(fy)  # framed top-left tap: 0 <= x0 <= w
                            t = np.uint64(tex0 + y0 * stride + x0)
                            hit_s[n_hit], hit_t[n_hit] = s, t
                            hit_wx[n_hit], hit_wy[n_hit] = fx - np.float32(x0), fy - np.float32(y0)
                            hit_x[n_hit], hit_y[n_hit] = x0, y0
                            # Kept only if its four taps have some alpha (no branch on the texels).
                            n_hit += (reach[t >> np.uint64(3)] >> (t & np.uint64(7))) & 1
                        for q in range(n_hit):
                            s, t, wx, wy = hit_s[q], hit_t[q], hit_wx[q], hit_wy[q]
                            g = g0 + s
                            p00, p01 = texels[t], texels[t + 1]
                            p10, p11 = texels[t + stride], texels[t + stride + 1]
                            w00 = (one - wy) * (one - wx) * np.float32(p00 >> 24)
                            w01 = (one - wy) * wx * np.float32(p01 >> 24)
                            w10 = wy * (one - wx) * np.float32(p10 >> 24)
                            w11 = wy * wx * np.float32(p11 >> 24)
                            sa = w00 + w01 + w10 + w11
                            T = trans[g]
                            ta = T * sa * inv255  # the sample's weight in its pixel
                            # Straight colour over 4 x 4 texels (edge texels repeated) x alpha, where
                            # the sample weighs cubic_min or more in its pixel.
                            if cubic and ta >= cubic_min:
                                cx, cy = cubic_weights(wx), cubic_weights(wy)
                                sr, sg, sb = zero, zero, zero
                                for a in range(4):
                                    row = tex0 + min(max(hit_y[q] + a - 1, 1), h) * stride
                                    rr, rg, rb = zero, zero, zero
                                    for c4 in range(4):
                                        p = texels[np.uint64(row + min(max(hit_x[q] + c4 - 1, 1), w))]
                                        rr += cx[c4] * np.float32(p & 255)
                                        rg += cx[c4] * np.float32((p >> 8) & 255)
                                        rb += cx[c4] * np.float32((p >> 16) & 255)
                                    sr, sg, sb = sr + cy[a] * rr, sg + cy[a] * rg, sb + cy[a] * rb
                                sr = sa * min(max(sr, zero), full)
                                sg = sa * min(max(sg, zero), full)
                                sb = sa * min(max(sb, zero), full)
                            else:  # premultiplied colour, bilinear
                                sr = (
                                    w00 * np.float32(p00 & 255)
                                    + w01 * np.float32(p01 & 255)
                                    + w10 * np.float32(p10 & 255)
                                    + w11 * np.float32(p11 & 255)
                                )
                                sg = (
                                    w00 * np.float32((p00 >> 8) & 255)
                                    + w01 * np.float32((p01 >> 8) & 255)
                                    + w10 * np.float32((p10 >> 8) & 255)
                                    + w11 * np.float32((p11 >> 8) & 255)
                                )
                                sb = (
                                    w00 * np.float32((p00 >> 16) & 255)
                                    + w01 * np.float32((p01 >> 16) & 255)
                                    + w10 * np.float32((p10 >> 16) & 255)
                                    + w11 * np.float32((p11 >> 16) & 255)
                                )
                            tc = T * inv255sq  # colour: texel colour x texel alpha, both 8-bit
                            cr[g] += tc * sr
                            cg[g] += tc * sg
                            cb[g] += tc * sb
                            cd[g] += ta * ek
                            T -= ta
                            trans[g] = T
                            if T < t_min:  # opaque: the ray leaves the block's live rays
                                mask &= ~(u1 << np.uint64(s))
                                total -= 1
                        live[b] = mask
            wj = weights[j]
            for g in range(npx):
                if dz[g] != 0.0:  # else no ray (or no pixel): this MPI covers nothing here
                    a = 1.0 - trans[g]
                    b_tot[g] += wj * a
                    b_r[g] += wj * cr[g]
                    b_g[g] += wj * cg[g]
                    b_b[g] += wj * cb[g]
                    b_d[g] += wj * cd[g] / dz[g]
                    b_a[g] = max(b_a[g], a)
        # cmc.mpi.rendering.blend: sum_i w_i C_i / sum_i w_i a_i, times the largest coverage.
        for b in range(n_blocks):
            for r in range(n_rows):
                y = y_lo + r
                for c in range(min(cols, width - b * cols)):
                    g, x = b * slots + r * cols + c, b * cols + c
                    norm = 1.0 / max(b_tot[g], 1e-8)
                    rgb[y, x, 0] = b_r[g] * norm * b_a[g]
                    rgb[y, x, 1] = b_g[g] * norm * b_a[g]
                    rgb[y, x, 2] = b_b[g] * norm * b_a[g]
                    depth[y, x] = b_d[g] * norm if b_a[g] > 1e-3 else 0.0
                    acc[y, x] = b_a[g]


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
    colour_interpolation: str = "bilinear",
    bicubic_min_weight: float = BICUBIC_MIN_WEIGHT,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The blend of MPIs ``use`` (blend weights ``weights[i]``) seen from a target camera.

    Args:
        packed: the MPIs' textures; mpis: their geometry, in the same order.
        weights: [N] blend weights (:func:`cmc.geometry.planes.blend_weights`); use: MPIs to render.
        K_tgt [3, 3], world_from_tgt [4, 4]: the target camera (OpenCV convention, see
            cmc.geometry.cameras); width, height in pixels.
        min_transmittance: stop compositing an MPI's ray below this transmittance (0: never).
        threads: threads for this render (default: one per core); the result does not depend on it.
        colour_interpolation: "bilinear": each sample is the bilinear blend of the four texels'
            premultiplied colour and alpha; "bicubic": alpha as before, times the straight colour
            of the 4 x 4 texels around it under Keys' cubic kernel (:func:`cmc.mpi.plane_sampling.cubic_weights`,
            texels past the plane's edge repeat the edge), clamped to [0, 1]: how
            :class:`cmc.mpi.fields.PyramidPlaneField` samples its base colours with
            ``base_interpolation="bicubic"``; a sample that weighs less than
            ``bicubic_min_weight`` in its pixel (transmittance times alpha) is taken bilinearly
            (0: every sample bicubic).
    Returns:
        as :func:`cmc.mpi.rendering.blend`: rgb [height, width, 3] (colour times coverage), depth
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
    check_interpolation(colour_interpolation, "colour_interpolation")
    cubic = colour_interpolation == "bicubic"
    w_use = np.asarray(weights, np.float64)[use_a]
    rgb = np.empty((height, width, 3), np.float32)
    depth = np.empty((height, width), np.float32)
    acc = np.empty((height, width), np.float32)
    n = max(1, min(threads or default_threads(), -(-height // ROWS)))

    def part(band0: int) -> None:
        _render_bands(
            packed.texels, packed.reach, packed.base, packed.shapes, packed.sat, packed.sbase, packed.otiles,
            use_a, w_use, Q, ax, bx, ay, by, e, split, width, height, band0, n, ROWS, COLS,
            float(min_transmittance), cubic, np.float32(bicubic_min_weight), rgb, depth, acc,
        )  # fmt: skip

    others = [_pool().submit(part, t) for t in range(1, n)]
    part(0)
    for f in others:
        f.result()
    return rgb, depth, acc


def warm_up() -> None:
    """Compile the kernel now into numba's on-disk cache (:mod:`cmc.kernel_cache`), so the first
    render of a fresh process does not pay the compile; the Dockerfiles call it."""
    K = np.array([[4.0, 0, 2], [0, 4.0, 2], [0, 0, 1]])
    packed = PackedTextures.pack([np.full((2, 4, 4, 4), 255, dtype=np.uint8)])
    g = MPIGeometry(K, np.eye(4), np.array([1.0, 2.0]), 4, 4, (1.0, 1.0))
    for mode in INTERPOLATIONS:
        render(packed, [g], np.ones(1), [0], K, np.eye(4), 4, 4, colour_interpolation=mode)
