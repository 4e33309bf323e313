"""Compiled CPU kernels of the plane sweep (:mod:`cmc.method.planesweep`): the per-texel matching
cost of a view (warp, colour difference, census distance), the edge-aware window averages
combined over the views, and the semi-global aggregation, which took most of the model build on
the CPU as torch ops (passes over [D, h * w, 3] intermediates, one pass over the whole cost volume
per window offset, one batch of small ops per texel column of a path).

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
    """out [h, w, D]: the share of the census bits (neighbour brighter than the centre, over the
    window of ``radius``) that differ between g_ref [h, w] and each plane of g_w [h, w, D]. The
    count is an integer per plane (a branch-free XOR the compiler vectorises)."""
    h, w, D = g_w.shape
    n = np.float32((2 * radius + 1) ** 2 - 1)
    for y in numba.prange(h):
        count = np.empty(D, np.int32)
        for x in range(w):
            centre = g_w[y, x]
            count[:] = 0
            for dy in range(-radius, radius + 1):
                sy = min(max(y + dy, 0), h - 1)
                for dx in range(-radius, radius + 1):
                    if dy == 0 and dx == 0:
                        continue
                    sx = min(max(x + dx, 0), w - 1)
                    ref_bit = np.int32(g_ref[sy, sx] > g_ref[y, x])
                    src = g_w[sy, sx]
                    for d in range(D):
                        count[d] += np.int32(src[d] > centre[d]) ^ ref_bit
            acc = out[y, x]
            for d in range(D):
                acc[d] = np.float32(count[d]) / n


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
def _combined_window_cost(weights, window, costs, seen, occlusion_aware, flat, out):  # pragma: no cover - compiled
    """out [h, w, D]: each view's cost (costs: a tuple of V [h, w, D] arrays, 0 where unseen)
    summed over the window with ``weights`` [h, w, window^2], divided by the window's weight of
    texels that view sees (seen: V [h, w, D] bool arrays); over the views that see any, the
    lowest (``occlusion_aware``) or their mean; ``flat`` where none does."""
    V = len(costs)
    h, w, D = costs[0].shape
    r = window // 2
    inf = np.float32(np.inf)
    for y in numba.prange(h):
        total = np.empty((V, D), np.float32)
        frac = np.empty((V, D), np.float32)
        for x in range(w):
            total[:] = 0
            frac[:] = 0
            for k in range(window * window):
                sy, sx = y + k // window - r, x + k % window - r
                if sy < 0 or sy >= h or sx < 0 or sx >= w:
                    continue
                wt = weights[y, x, k]
                for v in range(V):
                    src, src_seen = costs[v][sy, sx], seen[v][sy, sx]
                    for d in range(D):
                        total[v, d] += wt * src[d]
                        frac[v, d] += wt * np.float32(src_seen[d])
            acc = out[y, x]
            for d in range(D):
                best, n = inf, 0
                for v in range(V):
                    if frac[v, d] > 0:
                        c = total[v, d] / max(frac[v, d], np.float32(1e-6))
                        if occlusion_aware:
                            best = min(best, c)
                        else:
                            best = c if n == 0 else best + c
                        n += 1
                if n == 0:
                    acc[d] = flat
                elif occlusion_aware:
                    acc[d] = best
                else:
                    acc[d] = best / np.float32(n)


def combined_window_cost(
    weights: torch.Tensor,
    window: int,
    costs: list[torch.Tensor],
    seen: list[torch.Tensor],
    occlusion_aware: bool,
    flat: float,
) -> torch.Tensor:
    """:func:`cmc.method.planesweep._combined_window_cost` with edge-aware ``weights`` [h, w,
    window^2] (CPU float32), each view's cost and seen [D, h, w] (views of [h, w, D] arrays are
    read without a copy): the same sums and divisions in the same order, so the same result to the
    bit. Returns [D, h, w], a view of an [h, w, D] array."""
    hwd = tuple(np.ascontiguousarray(c.permute(1, 2, 0).numpy()) for c in costs)
    hwd_seen = tuple(np.ascontiguousarray(s.permute(1, 2, 0).numpy()) for s in seen)
    out = np.empty_like(hwd[0])
    with kernel_cache.PARALLEL_LAUNCH:
        _combined_window_cost(
            np.ascontiguousarray(weights.numpy()),
            window,
            hwd,
            hwd_seen,
            occlusion_aware,
            np.float32(flat),
            out,
        )
    return torch.from_numpy(out).permute(2, 0, 1)


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


@numba.njit(parallel=True, **_JIT)
def _sgm_cols_mean(cost, p1, p2, rows):  # pragma: no cover - compiled
    """rows[y, x] <- (rows[y, x] + the top-to-bottom plus the bottom-to-top path cost) / 4, the
    mean of the four paths (cost [h, w, D]; rows holds the two row paths of :func:`_sgm_rows`)."""
    h, w, D = cost.shape
    four = np.float32(4)
    for x in numba.prange(w):
        down = np.empty((h, D), np.float32)
        prev, new = cost[0, x].copy(), np.empty(D, np.float32)
        down[0] = prev
        for y in range(1, h):
            _sgm_step(prev, cost[y, x], p1, p2, new)
            down[y] = new
            prev[:] = new
        prev[:] = cost[h - 1, x]
        for d in range(D):
            rows[h - 1, x, d] = (rows[h - 1, x, d] + (down[h - 1, d] + prev[d])) / four
        for y in range(h - 2, -1, -1):
            _sgm_step(prev, cost[y, x], p1, p2, new)
            for d in range(D):
                rows[y, x, d] = (rows[y, x, d] + (down[y, d] + new[d])) / four
            prev[:] = new


def semi_global(cost: torch.Tensor, p1: float, p2: float) -> torch.Tensor:
    """:func:`cmc.method.planesweep.semi_global` of a CPU float32 cost [D, h, w] -> [D, h, w]
    (a view of an [h, w, D] cost is read without a copy)."""
    hwd = np.ascontiguousarray(cost.permute(1, 2, 0).numpy())
    total = np.empty_like(hwd)
    with kernel_cache.PARALLEL_LAUNCH:
        _sgm_rows(hwd, np.float32(p1), np.float32(p2), total)
        _sgm_cols_mean(hwd, np.float32(p1), np.float32(p2), total)
    return torch.from_numpy(total).permute(2, 0, 1).contiguous()


def warm_up() -> None:
    """Compile the kernels into numba's on-disk cache now (:mod:`cmc.kernel_cache`); the
    Dockerfiles call it."""
    guide = torch.rand(3, 6, 5)
    census_distance(guide.mean(0), torch.rand(2, 6, 5), 1)
    view_cost(torch.eye(3).expand(2, 3, 3), torch.rand(3, 6, 5), guide, torch.rand(6, 5, 2) * 5, 1, 0.05, 0.3)
    view_cost(torch.eye(3).expand(2, 3, 3), torch.rand(3, 6, 5), guide, torch.rand(6, 5, 2) * 5, None, 0.05, 0.3)
    costs = torch.rand(2, 6, 5, 4).permute(0, 3, 1, 2)
    combined_window_cost(torch.rand(6, 5, 9), 3, list(costs), list(costs > 0.5), True, 1.0)
    semi_global(torch.rand(4, 6, 5), 0.2, 2.0)
