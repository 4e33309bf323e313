"""Compiled CPU kernels of the plane sweep (:mod:`cmc.method.planesweep`): the per-texel matching
cost of a view (warp, colour difference, census distance), the edge-aware window sums and the
semi-global aggregation, which took most of the model build on the CPU as torch ops (passes over
[D, h * w, 3] intermediates, one pass over the whole cost volume per window offset, one batch of
small ops per texel column of a path).

Each kernel walks the texels once and keeps the planes of a texel contiguous (arrays laid out
[h, w, D]), so a window offset costs one read of D contiguous floats instead of a pass over the
volume. The torch versions in :mod:`cmc.method.planesweep` are the slow twins (and what runs on a
GPU): the census, window and semi-global kernels do the same float32 operations in the same
order, so their results are the same to the bit; the view cost's warp and exponentials round
differently (within 1e-5, ``tests/test_planesweep.py``). Rows are split over threads: the result
does not depend on the thread count.
"""

from __future__ import annotations

import numba
import numpy as np
import torch

from cmc import kernel_cache

kernel_cache.prepare()
_JIT = dict(nogil=True, cache=True, boundscheck=False, error_model="numpy")


@numba.njit(parallel=True, **_JIT)
def _census(g_ref, g_w, radius, out):  # pragma: no cover - compiled
    h, w, D = g_w.shape
    n = np.float32((2 * radius + 1) ** 2 - 1)
    for y in numba.prange(h):
        for x in range(w):
            acc = out[y, x]
            centre = g_w[y, x]
            for d in range(D):
                acc[d] = 0
            for dy in range(-radius, radius + 1):
                sy = min(max(y + dy, 0), h - 1)
                for dx in range(-radius, radius + 1):
                    if dy == 0 and dx == 0:
                        continue
                    sx = min(max(x + dx, 0), w - 1)
                    ref_bit = g_ref[sy, sx] > g_ref[y, x]
                    src = g_w[sy, sx]
                    for d in range(D):
                        if (src[d] > centre[d]) != ref_bit:
                            acc[d] += 1
            for d in range(D):
                acc[d] /= n


def census_distance(g_ref: torch.Tensor, g_w: torch.Tensor, radius: int) -> torch.Tensor:
    """Census distance of brightness images: reference [h, w], warped [D, h, w] (CPU, float32) ->
    [D, h, w], as :func:`cmc.method.planesweep.census_distance` computes it from the colour images."""
    hwd = np.ascontiguousarray(g_w.permute(1, 2, 0).numpy())
    out = np.empty_like(hwd)
    with kernel_cache.PARALLEL_LAUNCH:
        _census(np.ascontiguousarray(g_ref.numpy()), hwd, radius, out)
    return torch.from_numpy(out).permute(2, 0, 1).contiguous()


@numba.njit(**_JIT)
def _border_bilinear(image, ix, iy, c):  # pragma: no cover - compiled
    """Channel c of image [H, W, C] at texel coordinates (ix, iy) (texel centres at 0, 1, ...),
    clamped to the image, bilinearly: ``grid_sample``'s ``padding_mode="border"``."""
    H, W = image.shape[0], image.shape[1]
    ix = min(max(ix, np.float32(0)), np.float32(W - 1))
    iy = min(max(iy, np.float32(0)), np.float32(H - 1))
    x0, y0 = int(np.floor(ix)), int(np.floor(iy))
    x1, y1 = min(x0 + 1, W - 1), min(y0 + 1, H - 1)
    ax, ay = ix - np.float32(x0), iy - np.float32(y0)
    top = (np.float32(1) - ax) * image[y0, x0, c] + ax * image[y0, x1, c]
    bottom = (np.float32(1) - ax) * image[y1, x0, c] + ax * image[y1, x1, c]
    return (np.float32(1) - ay) * top + ay * bottom


@numba.njit(parallel=True, **_JIT)
def _warp_and_compare(H_j_from_ref, image, ref_rgb, uv, ad, grey, inside):  # pragma: no cover - compiled
    """For every texel (uv [h, w, 2] its reference pixel) and plane d: the other view's colour
    where plane d's homography ``H_j_from_ref[d]`` takes the texel (bilinear, border-clamped, from
    image [H, W, 3]); out: the mean absolute difference to ``ref_rgb`` [h, w, 3] (``ad``), its
    brightness (``grey``) and whether the view sees it (``inside``), all [h, w, D]."""
    h, w, D = ad.shape
    H, W = image.shape[0], image.shape[1]
    third = np.float32(1) / np.float32(3)
    for y in numba.prange(h):
        for x in range(w):
            u, v = uv[y, x, 0], uv[y, x, 1]
            for d in range(D):
                m = H_j_from_ref[d]
                qx = m[0, 0] * u + m[0, 1] * v + m[0, 2]
                qy = m[1, 0] * u + m[1, 1] * v + m[1, 2]
                qz = m[2, 0] * u + m[2, 1] * v + m[2, 2]
                z = max(qz, np.float32(1e-6))
                gx = qx / z / np.float32(W) * np.float32(2) - np.float32(1)
                gy = qy / z / np.float32(H) * np.float32(2) - np.float32(1)
                inside[y, x, d] = abs(gx) <= 1 and abs(gy) <= 1 and qz > 0
                ix = ((gx + np.float32(1)) * np.float32(W) - np.float32(1)) * np.float32(0.5)
                iy = ((gy + np.float32(1)) * np.float32(H) - np.float32(1)) * np.float32(0.5)
                diff, bright = np.float32(0), np.float32(0)
                for c in range(3):
                    col = _border_bilinear(image, ix, iy, c)
                    diff += abs(col - ref_rgb[y, x, c])
                    bright += col
                ad[y, x, d] = diff * third
                grey[y, x, d] = bright * third


@numba.njit(parallel=True, **_JIT)
def _ad_census(ad, census, inside, ad_scale, census_scale):  # pragma: no cover - compiled
    """ad [h, w, D] <- ((1 - exp(-ad / ad_scale)) + (1 - exp(-census / census_scale))) where
    ``inside``, else 0."""
    h, w, D = ad.shape
    for y in numba.prange(h):
        for x in range(w):
            for d in range(D):
                if inside[y, x, d]:
                    a = np.float32(1) - np.exp(-ad[y, x, d] / ad_scale)
                    ad[y, x, d] = a + (np.float32(1) - np.exp(-census[y, x, d] / census_scale))
                else:
                    ad[y, x, d] = 0


def view_cost(
    H_j_from_ref: torch.Tensor,
    image: torch.Tensor,
    ref_grid: torch.Tensor,
    uv: torch.Tensor,
    census_radius: int | None,
    ad_scale: float,
    census_scale: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The per-texel matching cost of a reference MPI's planes against one other view, as
    :func:`cmc.method.planesweep.view_cost_torch` computes it before its window average, in one
    pass over the texels (CPU, float32; the same up to float rounding, ``tests/test_planesweep.py``).

    Args:
        H_j_from_ref: [D, 3, 3] homographies taking reference pixels to the other view's pixels.
        image: the other view's photo [3, H, W]; ref_grid: the reference colour at the texels [3, h, w];
        uv: the texels' reference pixels [h, w, 2].
        census_radius: None for the colour difference alone ("ad"); else the AD-Census cost
            with census windows of this radius, its terms scaled by ``ad_scale`` and ``census_scale``.
    Returns:
        cost and seen, [D, h, w] (float32, bool) views of [h, w, D] arrays.
    """
    h, w = ref_grid.shape[1:]
    D = H_j_from_ref.shape[0]
    ad, grey = np.empty((h, w, D), np.float32), np.empty((h, w, D), np.float32)
    inside = np.empty((h, w, D), np.bool_)
    ref_hwc = np.ascontiguousarray(ref_grid.permute(1, 2, 0).numpy())
    with kernel_cache.PARALLEL_LAUNCH:
        _warp_and_compare(
            np.ascontiguousarray(H_j_from_ref.numpy()),
            np.ascontiguousarray(image.permute(1, 2, 0).numpy()),
            ref_hwc,
            np.ascontiguousarray(uv.numpy()),
            ad,
            grey,
            inside,
        )
        if census_radius is not None:
            census = np.empty_like(grey)
            _census(np.ascontiguousarray(ref_grid.mean(0).numpy()), grey, census_radius, census)
            _ad_census(ad, census, inside, np.float32(ad_scale), np.float32(census_scale))
        else:
            ad *= inside
    return torch.from_numpy(ad).permute(2, 0, 1), torch.from_numpy(inside).permute(2, 0, 1)


@numba.njit(parallel=True, **_JIT)
def _window_sum(x_hwc, weights, window, out):  # pragma: no cover - compiled
    h, w, C = x_hwc.shape
    r = window // 2
    for y in numba.prange(h):
        for x in range(w):
            acc = out[y, x]
            for c in range(C):
                acc[c] = 0
            for k in range(window * window):
                sy, sx = y + k // window - r, x + k % window - r
                if sy < 0 or sy >= h or sx < 0 or sx >= w:
                    continue
                wt = weights[y, x, k]
                src = x_hwc[sy, sx]
                for c in range(C):
                    acc[c] += wt * src[c]


def window_sum(weights: torch.Tensor, window: int):
    """The function [C, h, w] -> [C, h, w] of :func:`cmc.method.planesweep._window_mean` with the
    window's weights given (CPU float32 [h, w, window^2], offsets row by row): the same sums in
    the same order, so the same result to the bit. It reads and returns [C, h, w] views of
    [h, w, C] arrays without a copy (any other layout is copied)."""
    w = np.ascontiguousarray(weights.numpy())

    def apply(x: torch.Tensor) -> torch.Tensor:
        hwc = np.ascontiguousarray(x.permute(1, 2, 0).numpy(), dtype=np.float32)
        out = np.empty_like(hwc)
        with kernel_cache.PARALLEL_LAUNCH:
            _window_sum(hwc, w, window, out)
        return torch.from_numpy(out).permute(2, 0, 1)

    return apply


@numba.njit(**_JIT)
def _sgm_step(prev, cost, p1, p2, new):  # pragma: no cover - compiled
    """One texel along a path: ``new[d] = cost[d] + min(prev[d], prev[d +- 1] + p1, min(prev) +
    p2) - min(prev)``, in the order of operations of :func:`cmc.method.planesweep.semi_global_torch`."""
    D = prev.shape[0]
    low = prev[0]
    for d in range(1, D):
        low = min(low, prev[d])
    inf = np.float32(np.inf)
    for d in range(D):
        up = prev[d + 1] if d + 1 < D else inf
        down = prev[d - 1] if d > 0 else inf
        m = min(min(prev[d], min(up, down) + p1), low + p2)
        new[d] = (cost[d] + m) - low


@numba.njit(parallel=True, **_JIT)
def _sgm_rows(cost, p1, p2, out):  # pragma: no cover - compiled
    """out[y, x] = the left-to-right plus the right-to-left path cost (cost [h, w, D])."""
    h, w, D = cost.shape
    for y in numba.prange(h):
        prev, new = cost[y, 0].copy(), np.empty(D, np.float32)
        out[y, 0] = prev
        for x in range(1, w):
            _sgm_step(prev, cost[y, x], p1, p2, new)
            out[y, x] = new
            prev[:] = new
        prev[:] = cost[y, w - 1]
        out[y, w - 1] += prev
        for x in range(w - 2, -1, -1):
            _sgm_step(prev, cost[y, x], p1, p2, new)
            out[y, x] += new
            prev[:] = new


def semi_global(cost: torch.Tensor, p1: float, p2: float) -> torch.Tensor:
    """:func:`cmc.method.planesweep.semi_global` of a CPU float32 cost [D, h, w] -> [D, h, w]."""
    hwd = np.ascontiguousarray(cost.permute(1, 2, 0).numpy())
    whd = np.ascontiguousarray(cost.permute(2, 1, 0).numpy())
    rows, cols = np.empty_like(hwd), np.empty_like(whd)
    with kernel_cache.PARALLEL_LAUNCH:
        _sgm_rows(hwd, np.float32(p1), np.float32(p2), rows)
        _sgm_rows(whd, np.float32(p1), np.float32(p2), cols)
    total = torch.from_numpy(rows) + torch.from_numpy(cols).transpose(0, 1)
    return (total / 4).permute(2, 0, 1).contiguous()


def warm_up() -> None:
    """Compile the kernels into numba's on-disk cache now (:mod:`cmc.kernel_cache`); the
    Dockerfiles call it."""
    guide = torch.rand(3, 6, 5)
    census_distance(guide.mean(0), torch.rand(2, 6, 5), 1)
    view_cost(torch.eye(3).expand(2, 3, 3), torch.rand(3, 6, 5), guide, torch.rand(6, 5, 2) * 5, 1, 0.05, 0.3)
    view_cost(torch.eye(3).expand(2, 3, 3), torch.rand(3, 6, 5), guide, torch.rand(6, 5, 2) * 5, None, 0.05, 0.3)
    window_sum(torch.rand(6, 5, 9), 3)(torch.rand(2, 6, 5))
    semi_global(torch.rand(4, 6, 5), 0.2, 2.0)
