"""Compiled CPU kernels of the plane sweep (:mod:`cmc.method.planesweep`): the census distance, the
edge-aware window sums and the semi-global aggregation, which took about half of the model build
on the CPU as torch ops (one pass over the whole [D, h, w] cost volume per window offset, one
batch of small ops per texel column of a path).

Each kernel walks the texels once and keeps the planes of a texel contiguous (arrays laid out
[h, w, D]), so a window offset costs one read of D contiguous floats instead of a pass over the
volume. The torch versions in :mod:`cmc.method.planesweep` are the slow twins (and what runs on a GPU):
each kernel does the same float32 operations in the same order, so the results are the same to
the bit (``tests/test_planesweep.py``) and a model trained with them is the one trained without.
Rows are split over threads: the result does not depend on the thread count.
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
    the same order, so the same result to the bit."""
    w = np.ascontiguousarray(weights.numpy())

    def apply(x: torch.Tensor) -> torch.Tensor:
        hwc = np.ascontiguousarray(x.permute(1, 2, 0).numpy(), dtype=np.float32)
        out = np.empty_like(hwc)
        with kernel_cache.PARALLEL_LAUNCH:
            _window_sum(hwc, w, window, out)
        return torch.from_numpy(out).permute(2, 0, 1).contiguous()

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
    window_sum(torch.rand(6, 5, 9), 3)(torch.rand(2, 6, 5))
    semi_global(torch.rand(4, 6, 5), 0.2, 2.0)
