"""Compiled CPU bilinear and bicubic sampling of plane textures, with its backward pass: what
training spends most of its time on; and the fold of a texture pyramid onto its finest grid
(:func:`fold_levels`), so that a sample reads one texture instead of one per level.

:func:`sample_planes` computes ``sum_t grid_sample(textures[t], grid)`` as
:func:`torch.nn.functional.grid_sample` does (bilinear or bicubic, ``align_corners=False``,
zero outside the texture), for the per-plane textures of :class:`cmc.mpi.fields.PyramidPlaneField`. On the CPU,
torch's backward of ``grid_sample`` allocated and zeroed a gradient the size of every texture
per call and scattered into it at about half the speed of the kernel here; a training step of
fern spent about half its time there (bench/reports/history/RESULTS-until-2026-11-27.md, section "Training time").

Plane k of the samples reads texture ``plane_texture[k]`` of each tensor (the identity for the
per-plane levels, the plane's group for the shared base colours). Work is split over threads by
whole textures, so no two threads write the same gradient texel: the result does not depend on
the thread count. Sums differ from torch's in the last bits (another order of operations). One loop
over planes and rays serves both interpolations; the per-sample gathers and scatters are inlined
into it (numba's ``inline="always"``: called, they cost the loops about a fifth more time).
Where a sample's whole footprint lies inside its texture (nearly every sample), a gather or
scatter reads or writes its taps row by row without testing each against the bounds, in the
same order as the tested path: the same sums, 10-32 % less time on fern's batches
(bench/PROFILE.md, "The samplers without per-tap bounds tests").

Threads come from numba's OpenMP layer, which is not fork-safe: a process that has trained must
not fork a child that trains (numba terminates such a child). Celery's prefork parent never
trains, and nothing here forks.
"""

from __future__ import annotations

from collections.abc import Sequence

import numba
import numpy as np
import torch
import torch.nn.functional as F

from cmc import kernel_cache


def _chunks(plane_texture: np.ndarray, parts: int) -> np.ndarray:
    """Bounds of at most ``parts`` contiguous plane ranges, each holding whole textures (the
    planes of one texture are contiguous): range i is [cuts[i], cuts[i + 1])."""
    D = len(plane_texture)
    starts = [0] + [k for k in range(1, D) if plane_texture[k] != plane_texture[k - 1]]
    n = min(parts, len(starts))
    return np.array([starts[i * len(starts) // n] for i in range(n)] + [D], np.int64)


kernel_cache.prepare()  # before the first kernel: numba needs a writable cache folder to define one
_JIT = dict(nogil=True, cache=True, boundscheck=False, error_model="numpy", fastmath={"contract"})


@numba.njit(**_JIT)
def _texel_coord(g, n):
    """Texel coordinate (texel centres at 0, 1, ...) of grid coordinate g on n texels, as
    ``grid_sample(align_corners=False)``: g = -1 and 1 are the outer edges of the texture."""
    return ((g + np.float32(1)) * np.float32(n) - np.float32(1)) * np.float32(0.5)


@numba.njit(**_JIT)
def _taps(gx, gy, H, W):
    """Bilinear taps of grid point (gx, gy) on an H x W texture (``align_corners=False``):
    top-left texel (x0, y0), the four weights, and which of the two columns / rows lie inside."""
    ix, iy = _texel_coord(gx, W), _texel_coord(gy, H)
    fx, fy = np.floor(ix), np.floor(iy)
    x0, y0 = np.int64(fx), np.int64(fy)
    ax, ay = ix - fx, iy - fy
    bx, by = np.float32(1) - ax, np.float32(1) - ay
    return (
        x0, y0, bx * by, ax * by, bx * ay, ax * ay,
        0 <= x0 < W, 0 <= x0 + 1 < W, 0 <= y0 < H, 0 <= y0 + 1 < H,
    )  # fmt: skip


# The bilinear taps of one channel, for the view-colour pass. _gather_bilinear and
# _scatter_bilinear keep their own copies of these loops: written through these helpers (the taps
# as one tuple or as arguments) they ran 10-20 % slower, and with the untested interior paths the
# gathers 1.7-1.8 times slower (bench/PROFILE.md, the view-colour pass and the untested path).
@numba.njit(inline="always", **_JIT)
def _tap_sum(tex, t, c, taps):
    """The bilinear sample of tex[t, c] at :func:`_taps`' footprint ``taps`` (zero outside)."""
    x0, y0, w00, w01, w10, w11, vx0, vx1, vy0, vy1 = taps
    s = np.float32(0)
    if vx0 and vx1 and vy0 and vy1:  # all four taps inside: no test per tap
        top, bottom = tex[t, c, y0], tex[t, c, y0 + 1]
        s += w00 * top[x0]
        s += w01 * top[x0 + 1]
        s += w10 * bottom[x0]
        s += w11 * bottom[x0 + 1]
        return s
    if vy0:
        if vx0:
            s += w00 * tex[t, c, y0, x0]
        if vx1:
            s += w01 * tex[t, c, y0, x0 + 1]
    if vy1:
        if vx0:
            s += w10 * tex[t, c, y0 + 1, x0]
        if vx1:
            s += w11 * tex[t, c, y0 + 1, x0 + 1]
    return s


@numba.njit(inline="always", **_JIT)
def _tap_add(grad_tex, t, c, taps, g):
    """The transpose of :func:`_tap_sum`: grad_tex[t, c] += each tap's weight times g."""
    x0, y0, w00, w01, w10, w11, vx0, vx1, vy0, vy1 = taps
    if vx0 and vx1 and vy0 and vy1:  # all four taps inside: no test per tap
        top, bottom = grad_tex[t, c, y0], grad_tex[t, c, y0 + 1]
        top[x0] += w00 * g
        top[x0 + 1] += w01 * g
        bottom[x0] += w10 * g
        bottom[x0 + 1] += w11 * g
        return
    if vy0:
        if vx0:
            grad_tex[t, c, y0, x0] += w00 * g
        if vx1:
            grad_tex[t, c, y0, x0 + 1] += w01 * g
    if vy1:
        if vx0:
            grad_tex[t, c, y0 + 1, x0] += w10 * g
        if vx1:
            grad_tex[t, c, y0 + 1, x0 + 1] += w11 * g


@numba.njit(inline="always", **_JIT)
def _gather_bilinear(tex, t, gx, gy, out, k, r):
    """out[k, c, r] += bilinear sample of tex[t, c] at grid point (gx, gy), for every channel c."""
    C, H, W = tex.shape[1], tex.shape[2], tex.shape[3]
    x0, y0, w00, w01, w10, w11, vx0, vx1, vy0, vy1 = _taps(gx, gy, H, W)
    if vx0 and vx1 and vy0 and vy1:  # all four taps inside (nearly every sample): no test per tap
        for c in range(C):
            top, bottom = tex[t, c, y0], tex[t, c, y0 + 1]
            s = np.float32(0)
            s += w00 * top[x0]
            s += w01 * top[x0 + 1]
            s += w10 * bottom[x0]
            s += w11 * bottom[x0 + 1]
            out[k, c, r] += s
        return
    for c in range(C):
        s = np.float32(0)
        if vy0:
            if vx0:
                s += w00 * tex[t, c, y0, x0]
            if vx1:
                s += w01 * tex[t, c, y0, x0 + 1]
        if vy1:
            if vx0:
                s += w10 * tex[t, c, y0 + 1, x0]
            if vx1:
                s += w11 * tex[t, c, y0 + 1, x0 + 1]
        out[k, c, r] += s


@numba.njit(inline="always", **_JIT)
def _scatter_bilinear(grad_out, t, gx, gy, grad_tex, k, r):
    """The transpose of :func:`_gather_bilinear`: grad_tex[t] += its taps times grad_out[k, :, r]."""
    C, H, W = grad_tex.shape[1], grad_tex.shape[2], grad_tex.shape[3]
    x0, y0, w00, w01, w10, w11, vx0, vx1, vy0, vy1 = _taps(gx, gy, H, W)
    if vx0 and vx1 and vy0 and vy1:  # all four taps inside: no test per tap
        for c in range(C):
            g = grad_out[k, c, r]
            if g == 0:
                continue
            top, bottom = grad_tex[t, c, y0], grad_tex[t, c, y0 + 1]
            top[x0] += w00 * g
            top[x0 + 1] += w01 * g
            bottom[x0] += w10 * g
            bottom[x0 + 1] += w11 * g
        return
    for c in range(C):
        g = grad_out[k, c, r]
        if g == 0:
            continue
        if vy0:
            if vx0:
                grad_tex[t, c, y0, x0] += w00 * g
            if vx1:
                grad_tex[t, c, y0, x0 + 1] += w01 * g
        if vy1:
            if vx0:
                grad_tex[t, c, y0 + 1, x0] += w10 * g
            if vx1:
                grad_tex[t, c, y0 + 1, x0 + 1] += w11 * g


INTERPOLATIONS = ("bilinear", "bicubic")  # the sampling kernels here, by grid_sample's names
CUBIC_A = -0.75  # the cubic convolution kernel's free parameter, as torch's bicubic grid_sample


def check_interpolation(value: str, name: str) -> None:
    """Raise ValueError unless ``value`` is one of :data:`INTERPOLATIONS` (``name``: the setting's
    name, for the message)."""
    if value not in INTERPOLATIONS:
        raise ValueError(f"{name} must be one of {', '.join(map(repr, INTERPOLATIONS))}, got {value!r}")


@numba.njit(**_JIT)
def cubic_weights(t):
    """The four weights of Keys' cubic convolution (A = CUBIC_A) for texels at offsets -1, 0, 1, 2
    from a sample at fraction t in [0, 1) past texel 0; they sum to 1 (float32 in, float32 out)."""
    a = np.float32(CUBIC_A)
    u, v = t + np.float32(1), np.float32(1) - t  # distances to the outer taps are u and 2 - t
    w0 = ((a * u - np.float32(5) * a) * u + np.float32(8) * a) * u - np.float32(4) * a
    w1 = ((a + np.float32(2)) * t - (a + np.float32(3))) * t * t + np.float32(1)
    w2 = ((a + np.float32(2)) * v - (a + np.float32(3))) * v * v + np.float32(1)
    w3 = np.float32(1) - w0 - w1 - w2
    return (w0, w1, w2, w3)


@numba.njit(**_JIT)
def _cubic_axis(g, n):
    """Bicubic taps along one axis of grid coordinate g on n texels (``align_corners=False``):
    the first of the four texels and their weights."""
    i = _texel_coord(g, n)
    f = np.floor(i)
    return np.int64(f) - 1, cubic_weights(i - f)


@numba.njit(inline="always", **_JIT)
def _gather_cubic(tex, t, gx, gy, out, k, r):
    """As :func:`_gather_bilinear`, with bicubic taps (4 x 4 texels, zero outside)."""
    C, H, W = tex.shape[1], tex.shape[2], tex.shape[3]
    x0, wx = _cubic_axis(gx, W)
    y0, wy = _cubic_axis(gy, H)
    if 0 <= x0 and x0 + 3 < W and 0 <= y0 and y0 + 3 < H:  # all 16 taps inside: no test per tap
        for c in range(C):
            s = np.float32(0)
            for a in range(4):
                line = tex[t, c, y0 + a]
                row = np.float32(0)
                row += wx[0] * line[x0]
                row += wx[1] * line[x0 + 1]
                row += wx[2] * line[x0 + 2]
                row += wx[3] * line[x0 + 3]
                s += wy[a] * row
            out[k, c, r] += s
        return
    for c in range(C):
        s = np.float32(0)
        for a in range(4):
            y = y0 + a
            if 0 <= y < H:
                row = np.float32(0)
                for b in range(4):
                    x = x0 + b
                    if 0 <= x < W:
                        row += wx[b] * tex[t, c, y, x]
                s += wy[a] * row
        out[k, c, r] += s


@numba.njit(inline="always", **_JIT)
def _scatter_cubic(grad_out, t, gx, gy, grad_tex, k, r):
    """The transpose of :func:`_gather_cubic`."""
    C, H, W = grad_tex.shape[1], grad_tex.shape[2], grad_tex.shape[3]
    x0, wx = _cubic_axis(gx, W)
    y0, wy = _cubic_axis(gy, H)
    if 0 <= x0 and x0 + 3 < W and 0 <= y0 and y0 + 3 < H:  # all 16 taps inside: no test per tap
        for c in range(C):
            g = grad_out[k, c, r]
            if g == 0:
                continue
            for a in range(4):
                ga = wy[a] * g
                line = grad_tex[t, c, y0 + a]
                line[x0] += wx[0] * ga
                line[x0 + 1] += wx[1] * ga
                line[x0 + 2] += wx[2] * ga
                line[x0 + 3] += wx[3] * ga
        return
    for c in range(C):
        g = grad_out[k, c, r]
        if g == 0:
            continue
        for a in range(4):
            y = y0 + a
            if 0 <= y < H:
                ga = wy[a] * g
                for b in range(4):
                    x = x0 + b
                    if 0 <= x < W:
                        grad_tex[t, c, y, x] += wx[b] * ga


@numba.njit(**_JIT)
def _forward(tex, grid, plane_texture, out, p0, p1, cubic, where):
    """out[k, c, r] += sample of tex[plane_texture[k], c] at grid[k, r] (bilinear, or bicubic
    where ``cubic``), for k in [p0, p1) and, unless ``where`` is empty, only where ``where[k, r]``."""
    masked = where.shape[0] > 0
    for k in range(p0, p1):
        t = plane_texture[k]
        for r in range(grid.shape[1]):
            if masked and not where[k, r]:
                continue
            if cubic:
                _gather_cubic(tex, t, grid[k, r, 0], grid[k, r, 1], out, k, r)
            else:
                _gather_bilinear(tex, t, grid[k, r, 0], grid[k, r, 1], out, k, r)


@numba.njit(**_JIT)
def _backward(grad_out, grid, plane_texture, grad_tex, p0, p1, cubic, where):
    """grad_tex[t] = the transpose of :func:`_forward` applied to grad_out[k], summed over the
    planes k of texture t, for the textures of planes [p0, p1), which no other range holds."""
    grad_tex[plane_texture[p0] : plane_texture[p1 - 1] + 1] = 0  # zeroed here: fresh pages in parallel
    C = grad_out.shape[1]
    masked = where.shape[0] > 0
    for k in range(p0, p1):
        t = plane_texture[k]
        for r in range(grid.shape[1]):
            if masked and not where[k, r]:
                continue
            nonzero = False
            for c in range(C):
                nonzero = nonzero or grad_out[k, c, r] != 0
            if not nonzero:  # e.g. the colours of a sample too faint to fit (cmc.mpi.rendering.composite)
                continue
            if cubic:
                _scatter_cubic(grad_out, t, grid[k, r, 0], grid[k, r, 1], grad_tex, k, r)
            else:
                _scatter_bilinear(grad_out, t, grid[k, r, 0], grid[k, r, 1], grad_tex, k, r)


@numba.njit(parallel=True, **_JIT)
def _forward_parallel(tex, grid, plane_texture, out, cuts, cubic, where):
    for i in numba.prange(len(cuts) - 1):
        _forward(tex, grid, plane_texture, out, cuts[i], cuts[i + 1], cubic, where)


@numba.njit(parallel=True, **_JIT)
def _backward_parallel(grad_out, grid, plane_texture, grad_tex, cuts, cubic, where):
    for i in numba.prange(len(cuts) - 1):
        _backward(grad_out, grid, plane_texture, grad_tex, cuts[i], cuts[i + 1], cubic, where)


class _SamplePlanes(torch.autograd.Function):
    @staticmethod
    def forward(
        ctx, grid: torch.Tensor, where: np.ndarray, plane_texture: np.ndarray, cubic: bool, *textures: torch.Tensor
    ) -> torch.Tensor:
        D, R = grid.shape[:2]
        out = torch.zeros(D, textures[0].shape[1], R)
        numba.set_num_threads(min(numba.config.NUMBA_NUM_THREADS, torch.get_num_threads()))
        chunks = _chunks(plane_texture, numba.get_num_threads())
        g = grid.numpy()
        with kernel_cache.PARALLEL_LAUNCH:
            for tex in textures:
                _forward_parallel(tex.detach().numpy(), g, plane_texture, out.numpy(), chunks, cubic, where)
        ctx.save_for_backward(grid)
        ctx.where, ctx.plane_texture, ctx.chunks, ctx.cubic = where, plane_texture, chunks, cubic
        ctx.shapes = [t.shape for t in textures]
        return out

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        (grid,) = ctx.saved_tensors
        go, g = grad_out.contiguous().numpy(), grid.numpy()
        grads = []
        for shape, needed in zip(ctx.shapes, ctx.needs_input_grad[4:], strict=True):
            gt = None
            if needed:
                gt = torch.empty(shape)
                with kernel_cache.PARALLEL_LAUNCH:  # zeroes and fills the textures planes read
                    _backward_parallel(go, g, ctx.plane_texture, gt.numpy(), ctx.chunks, ctx.cubic, ctx.where)
                gt[np.setdiff1d(np.arange(shape[0]), ctx.plane_texture)] = 0  # and those none reads
            grads.append(gt)
        return (None, None, None, None, *grads)


_NO_MASK = np.zeros((0, 0), np.bool_)  # sample_planes without ``where``: every sample


def supported(grid: torch.Tensor, textures: Sequence[torch.Tensor]) -> bool:
    """Whether :func:`sample_planes` can take these: float32 on the CPU, no gradient to the grid."""
    tensors = (grid, *textures)
    return not grid.requires_grad and all(t.device.type == "cpu" and t.dtype == torch.float32 for t in tensors)


def sample_planes(
    grid: torch.Tensor,
    plane_texture: Sequence[int],
    textures: Sequence[torch.Tensor],
    mode: str = "bilinear",
    where: torch.Tensor | None = None,
) -> torch.Tensor:
    """Sum over ``textures`` of their samples (``mode`` "bilinear" or "bicubic", as
    ``grid_sample``'s): ``out[k, :, r]`` = sum_t of texture
    ``plane_texture[k]`` of ``textures[t]`` at grid point ``grid[k, r]`` (``grid_sample``
    coordinates, ``align_corners=False``, zero outside); with ``where`` ([D, R] bool), only the
    samples it marks, 0 at the others (which then pass no gradient).

    Shape: grid [D, R, 2]; textures [T_i, C, H_i, W_i] (same C, any sizes), the planes of one
    texture contiguous -> [D, C, R]. Differentiable in the textures, not in the grid; only where
    :func:`supported` (the GPU keeps ``grid_sample``).
    """
    if not supported(grid, textures):
        raise ValueError("sample_planes takes float32 CPU tensors and a grid without gradient")
    check_interpolation(mode, "mode")
    pt = np.asarray(plane_texture, np.int64)
    mask = _NO_MASK if where is None else where.contiguous().numpy()
    return _SamplePlanes.apply(grid.contiguous(), mask, pt, mode == "bicubic", *textures)


# A ray's view-colour delta (cmc.mpi.fields.ViewColour) below this on both axes counts as 0: the
# reference photo's own rays, whose delta is 0 up to rounding (about 1e-6).
DELTA_FLOOR = 1e-4


@numba.njit(inline="always", **_JIT)
def _view_delta(gx, gy, dirs, r, frame):
    """ViewColour's delta (x, y) of the sample at grid point (gx, gy) on ray r of ``dirs`` [R, 3]
    (the ray's slope minus the reference ray's through the point, times frame[4], clamped to
    [-2, 2]), with frame = (centre x, centre y, focal x, focal y, 1 / slope_scale); (0, 0) for a
    ray that does not point into the planes or a delta below DELTA_FLOOR."""
    z = dirs[r, 2]
    if not z > 0:
        return np.float32(0), np.float32(0)
    dx = (dirs[r, 0] / z - (gx - frame[0]) / frame[2]) * frame[4]
    dy = (dirs[r, 1] / z - (gy - frame[1]) / frame[3]) * frame[4]
    if abs(dx) < DELTA_FLOOR and abs(dy) < DELTA_FLOOR:
        return np.float32(0), np.float32(0)
    two = np.float32(2)
    return min(max(dx, -two), two), min(max(dy, -two), two)


@numba.njit(inline="always", **_JIT)
def _any_tap(mask, taps):
    """Whether any in-bounds texel of :func:`_taps`' footprint ``taps`` is nonzero in ``mask`` [h, w]."""
    x0, y0, _, _, _, _, vx0, vx1, vy0, vy1 = taps
    return (
        (vy0 and vx0 and mask[y0, x0] != 0)
        or (vy0 and vx1 and mask[y0, x0 + 1] != 0)
        or (vy1 and vx0 and mask[y0 + 1, x0] != 0)
        or (vy1 and vx1 and mask[y0 + 1, x0 + 1] != 0)
    )


@numba.njit(**_JIT)
def _view_forward(tex, mask, grid, dirs, frame, plane_texture, out, p0, p1, where):
    """out[k, c, r] = tex[t, 2c] * dx + tex[t, 2c + 1] * dy, each sampled bilinearly at grid[k, r]
    (t = plane_texture[k], (dx, dy) = :func:`_view_delta`), for k in [p0, p1); 0 where ``where``
    (unless empty) is False, the delta is 0 or ``mask`` is 0 at every tap."""
    H, W = tex.shape[2], tex.shape[3]
    masked = where.shape[0] > 0
    for k in range(p0, p1):
        t = plane_texture[k]
        for r in range(grid.shape[1]):
            for c in range(3):
                out[k, c, r] = 0
            if masked and not where[k, r]:
                continue
            gx, gy = grid[k, r, 0], grid[k, r, 1]
            dx, dy = _view_delta(gx, gy, dirs, r, frame)
            if dx == 0 and dy == 0:
                continue
            taps = _taps(gx, gy, H, W)
            if not _any_tap(mask, taps):
                continue
            for c in range(3):
                out[k, c, r] = _tap_sum(tex, t, 2 * c, taps) * dx + _tap_sum(tex, t, 2 * c + 1, taps) * dy


@numba.njit(**_JIT)
def _view_backward(grad_out, mask, grid, dirs, frame, plane_texture, grad_tex, p0, p1, where):
    """grad_tex[t] = the transpose of :func:`_view_forward` applied to grad_out, summed over the
    planes k of texture t, for the textures of planes [p0, p1), which no other range holds."""
    grad_tex[plane_texture[p0] : plane_texture[p1 - 1] + 1] = 0
    H, W = grad_tex.shape[2], grad_tex.shape[3]
    masked = where.shape[0] > 0
    for k in range(p0, p1):
        t = plane_texture[k]
        for r in range(grid.shape[1]):
            if masked and not where[k, r]:
                continue
            gx, gy = grid[k, r, 0], grid[k, r, 1]
            dx, dy = _view_delta(gx, gy, dirs, r, frame)
            if dx == 0 and dy == 0:
                continue
            taps = _taps(gx, gy, H, W)
            if not _any_tap(mask, taps):
                continue
            for c in range(3):
                g = grad_out[k, c, r]
                if g != 0:
                    _tap_add(grad_tex, t, 2 * c, taps, g * dx)
                    _tap_add(grad_tex, t, 2 * c + 1, taps, g * dy)


@numba.njit(parallel=True, **_JIT)
def _view_forward_parallel(tex, mask, grid, dirs, frame, plane_texture, out, cuts, where):
    for i in numba.prange(len(cuts) - 1):
        _view_forward(tex, mask, grid, dirs, frame, plane_texture, out, cuts[i], cuts[i + 1], where)


@numba.njit(parallel=True, **_JIT)
def _view_backward_parallel(grad_out, mask, grid, dirs, frame, plane_texture, grad_tex, cuts, where):
    for i in numba.prange(len(cuts) - 1):
        _view_backward(grad_out, mask, grid, dirs, frame, plane_texture, grad_tex, cuts[i], cuts[i + 1], where)


class _SampleViewColour(torch.autograd.Function):
    @staticmethod
    def forward(ctx, grid, dirs, frame, mask, where, plane_texture, texture):  # type: ignore[override]
        D, R = grid.shape[:2]
        out = torch.empty(D, 3, R)
        numba.set_num_threads(min(numba.config.NUMBA_NUM_THREADS, torch.get_num_threads()))
        chunks = _chunks(plane_texture, numba.get_num_threads())
        args = (mask.numpy(), grid.numpy(), dirs.numpy(), frame, plane_texture)
        with kernel_cache.PARALLEL_LAUNCH:
            _view_forward_parallel(texture.detach().numpy(), *args, out.numpy(), chunks, where)
        ctx.save_for_backward(grid, dirs, mask)
        ctx.frame, ctx.where, ctx.plane_texture = frame, where, plane_texture
        ctx.chunks, ctx.shape = chunks, texture.shape
        return out

    @staticmethod
    def backward(ctx, grad_out):  # type: ignore[override]
        grid, dirs, mask = ctx.saved_tensors
        grad = torch.empty(ctx.shape)
        args = (mask.numpy(), grid.numpy(), dirs.numpy(), ctx.frame, ctx.plane_texture)
        with kernel_cache.PARALLEL_LAUNCH:
            _view_backward_parallel(grad_out.contiguous().numpy(), *args, grad.numpy(), ctx.chunks, ctx.where)
        grad[np.setdiff1d(np.arange(ctx.shape[0]), ctx.plane_texture)] = 0
        return None, None, None, None, None, None, grad


def sample_view_colour(
    grid: torch.Tensor,
    dirs: torch.Tensor,
    plane_texture: Sequence[int],
    texture: torch.Tensor,
    mask: torch.Tensor,
    centre: torch.Tensor,
    focal: torch.Tensor,
    slope_scale: float,
    where: torch.Tensor | None = None,
) -> torch.Tensor:
    """The colour logits of :class:`cmc.mpi.fields.ViewColour` in one compiled pass (the CPU,
    float32): ``out[k, c, r]`` = texture[t, 2c] * dx + texture[t, 2c + 1] * dy, both sampled
    bilinearly at grid[k, r] (``grid_sample``'s coordinates), t = ``plane_texture[k]``, (dx, dy)
    the ray's delta (ViewColour's; 0 below :data:`DELTA_FLOOR`, as ViewColour's torch twin);
    samples whose four taps all lie where ``mask`` is 0 (the texture is 0 there) are skipped.

    Shape: grid [D, R, 2], dirs [R, 3] (the reference camera's frame), texture [G, 6, h, w], mask
    [h, w], centre and focal [2] (the frame's grid coordinates of the optical axis and grid units
    per unit slope), where [D, R] bool or None -> [D, 3, R]. Differentiable in the texture only.
    """
    if not supported(grid, [texture, dirs, mask]):
        raise ValueError("sample_view_colour takes float32 CPU tensors and a grid without gradient")
    frame = np.array([*centre.tolist(), *focal.tolist(), 1 / slope_scale], np.float32)
    keep = _NO_MASK if where is None else where.contiguous().numpy()
    pt = np.asarray(plane_texture, np.int64)
    return _SampleViewColour.apply(
        grid.contiguous(), dirs.contiguous(), frame, mask.contiguous(), keep, pt, texture.contiguous()
    )


def _linear_taps(n_in: int, n_out: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Taps of linear resampling from n_in to n_out texels along one axis, as ``F.interpolate``'s
    "bilinear" with ``size`` and ``align_corners=False``: output texel i reads texels i0[i] and
    i1[i] with weights 1 - f[i] and f[i]."""
    src = np.maximum((np.arange(n_out, dtype=np.float32) + np.float32(0.5)) * np.float32(n_in / n_out) - 0.5, 0)
    i0 = np.minimum(src.astype(np.int64), n_in - 1)
    return i0, np.minimum(i0 + 1, n_in - 1), (src - i0).astype(np.float32)


@numba.njit(parallel=True, **_JIT)
def _add_upsampled(fine, coarse, out, y0, y1, fy, x0, x1, fx):  # pragma: no cover - compiled
    """out[n] = fine[n] + coarse[n] resampled bilinearly onto fine's grid (taps per axis from
    :func:`_linear_taps`); [N, H, W] and [N, h, w]. Each output row: the two coarse rows it
    reads blended first, then resampled along x."""
    N, H, W = fine.shape
    w = coarse.shape[2]
    for n in numba.prange(N):
        row = np.empty(w, np.float32)
        for i in range(H):
            a, b, v = y0[i], y1[i], fy[i]
            for c in range(w):
                row[c] = coarse[n, a, c] + v * (coarse[n, b, c] - coarse[n, a, c])
            for j in range(W):
                left = row[x0[j]]
                out[n, i, j] = fine[n, i, j] + left + fx[j] * (row[x1[j]] - left)


@numba.njit(parallel=True, **_JIT)
def _upsampled_transpose(grad, grad_coarse, y0, y1, fy, x0, x1, fx):  # pragma: no cover - compiled
    """grad_coarse[n] = the transpose of :func:`_add_upsampled`'s resampling applied to grad[n]."""
    N, H, W = grad.shape
    w = grad_coarse.shape[2]
    for n in numba.prange(N):
        grad_coarse[n] = 0
        row = np.empty(w, np.float32)
        for i in range(H):
            row[:] = 0
            for j in range(W):
                g = grad[n, i, j]
                right = g * fx[j]
                row[x0[j]] += g - right
                row[x1[j]] += right
            a, b, v = y0[i], y1[i], fy[i]
            for c in range(w):
                lower = row[c] * v
                grad_coarse[n, a, c] += row[c] - lower
                grad_coarse[n, b, c] += lower


class _FoldLevels(torch.autograd.Function):
    @staticmethod
    def forward(ctx, *levels: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        taps, folded = [], levels[-1].detach().contiguous()
        for fine in reversed(levels[:-1]):
            (h, w), (H, W) = folded.shape[-2:], fine.shape[-2:]
            t = (*_linear_taps(h, H), *_linear_taps(w, W))
            out = torch.empty(fine.shape)
            with kernel_cache.PARALLEL_LAUNCH:
                _add_upsampled(
                    fine.detach().contiguous().numpy().reshape(-1, H, W),
                    folded.numpy().reshape(-1, h, w),
                    out.numpy().reshape(-1, H, W),
                    *t,
                )
            taps.append(t)
            folded = out
        ctx.taps, ctx.shapes = taps[::-1], [lvl.shape for lvl in levels]
        return folded

    @staticmethod
    def backward(ctx, grad: torch.Tensor):  # type: ignore[override]
        grads = [grad]
        for t, shape in zip(ctx.taps, ctx.shapes[1:], strict=True):
            g = grads[-1].contiguous()
            gc = torch.empty(shape)
            with kernel_cache.PARALLEL_LAUNCH:
                _upsampled_transpose(g.numpy().reshape(-1, *g.shape[-2:]), gc.numpy().reshape(-1, *shape[-2:]), *t)
            grads.append(gc)
        return tuple(grads)


def fold_levels_reference(levels: Sequence[torch.Tensor]) -> torch.Tensor:
    """:func:`fold_levels` with ``F.interpolate`` (any device; the slow twin of the kernels)."""
    folded = levels[-1]
    for fine in reversed(levels[:-1]):
        folded = fine + F.interpolate(folded, size=fine.shape[-2:], mode="bilinear", align_corners=False)
    return folded


def fold_levels(levels: Sequence[torch.Tensor]) -> torch.Tensor:
    """A pyramid of textures folded onto its finest grid: F_{L-1} = levels[L-1], F_l = levels[l] +
    F_{l+1} resampled bilinearly onto levels[l]'s grid (``F.interpolate``, ``align_corners=False``);
    returns F_0. A sampler then reads one texture where it read one per level; each coarse level
    reaches a sample through successive linear resamplings (a smooth basis, wider than its texel).

    Shape: levels [P, C, H_l, W_l], finest first -> [P, C, H_0, W_0]; differentiable in every
    level. Compiled on the CPU (float32), :func:`fold_levels_reference` elsewhere.
    """
    if len(levels) == 1:
        return levels[0]
    if all(t.device.type == "cpu" and t.dtype == torch.float32 for t in levels):
        return _FoldLevels.apply(*levels)
    return fold_levels_reference(levels)


def warm_up() -> None:
    """Compile the kernels now into numba's on-disk cache (:mod:`cmc.kernel_cache`), so the first
    training step of a fresh process does not pay the compile; the Dockerfiles call it."""
    tex = torch.zeros(2, 4, 3, 3, requires_grad=True)
    for mode in INTERPOLATIONS:
        for where in (None, torch.ones(2, 5, dtype=torch.bool)):
            sample_planes(torch.zeros(2, 5, 2), [0, 1], [tex], mode, where).sum().backward()
    fold_levels([tex, torch.zeros(2, 4, 2, 2, requires_grad=True)]).sum().backward()
    view = torch.zeros(2, 6, 3, 3, requires_grad=True)
    dirs = torch.tensor([[0.0, 0.0, 1.0]]).expand(5, 3)
    for where in (None, torch.ones(2, 5, dtype=torch.bool)):
        args = (torch.ones(3, 3), torch.zeros(2), torch.ones(2), 1.0, where)
        sample_view_colour(torch.full((2, 5, 2), 0.5), dirs, [0, 1], view, *args).sum().backward()
