"""Compiled CPU front-to-back compositing, with its backward pass: one walk along each ray
instead of torch's cumulative product, products and sums over [R, D] and [R, D, 3] tensors and
their backward passes (about 4x less time on a training step's rays, ``bench/PROFILE.md``).

:func:`composite` computes what :func:`cmc.mpi.rendering.composite_torch` does (paper Eq. 3.4,
3.5: the composited colour, depth, accumulated alpha and each plane's weight), in float32 in
another order of operations: the same values up to rounding (``tests/test_composite_kernel.py``).
The backward pass needs no division by ``1 - alpha`` (an opaque plane mid-ray is exact): with
``G_k`` the gradient reaching plane k's weight (directly, and through the colour, depth and
accumulated alpha), the gradient of alpha_k is ``T_k (G_k - U_{k+1})``, where ``T_k`` is the
transmittance before plane k and ``U_k = G_k alpha_k + (1 - alpha_k) U_{k+1}`` is the
back-to-front composite of the G's behind it. Rays are split over threads in tiles of 16, each
tile walked plane by plane, so that colours and gradients laid out plane first ([D, 3, R], as
the samplers return them) are read and written a cache line at a time; each ray's sums run in one
thread, so the result does not depend on the thread count.
"""

from __future__ import annotations

import numba
import numpy as np
import torch

from cmc import kernel_cache

kernel_cache.prepare()
_JIT = dict(nogil=True, cache=True, boundscheck=False, error_model="numpy")


_TILE = 16  # rays walked together, plane by plane: one cache line of a [D, 3, R] colour row


@numba.njit(parallel=True, **_JIT)
def _forward(rgb, alpha, depth, out_rgb, out_depth, out_acc, weights, scratch):  # pragma: no cover - compiled
    R, D = alpha.shape
    for tile in numba.prange((R + _TILE - 1) // _TILE):
        r0 = tile * _TILE
        n = min(_TILE, R - r0)
        trans, sums = scratch[tile, 0], scratch[tile, 1:]  # sums: colour, then depth
        trans[:] = 1
        sums[:] = 0
        for k in range(D):
            for j in range(n):
                r = r0 + j
                w = alpha[r, k] * trans[j]
                weights[r, k] = w
                sums[0, j] += w * rgb[r, k, 0]
                sums[1, j] += w * rgb[r, k, 1]
                sums[2, j] += w * rgb[r, k, 2]
                sums[3, j] += w * depth[r, k]
                trans[j] *= np.float32(1) - alpha[r, k]
        for j in range(n):
            r = r0 + j
            out_rgb[r, 0], out_rgb[r, 1], out_rgb[r, 2] = sums[0, j], sums[1, j], sums[2, j]
            out_depth[r] = sums[3, j]
            out_acc[r] = np.float32(1) - trans[j]


@numba.njit(parallel=True, **_JIT)
def _backward(
    rgb, alpha, depth, weights, g_rgb, g_depth, g_acc, g_w, min_w, scale, d_rgb, d_alpha, scratch
):  # pragma: no cover - compiled
    R, D = alpha.shape
    min_w = np.float32(min_w)
    for tile in numba.prange((R + _TILE - 1) // _TILE):
        r0 = tile * _TILE
        n = min(_TILE, R - r0)
        u, trans = scratch[tile, 0], scratch[tile, 1]  # U_{k+1}; the transmittance
        u[:] = 0
        for k in range(D - 1, -1, -1):
            for j in range(n):
                r = r0 + j
                a0, a1, a2, gz, ga = g_rgb[r, 0], g_rgb[r, 1], g_rgb[r, 2], g_depth[r], g_acc[r]
                g = g_w[r, k] + a0 * rgb[r, k, 0] + a1 * rgb[r, k, 1] + a2 * rgb[r, k, 2] + gz * depth[r, k] + ga
                w = weights[r, k]
                if w >= min_w:  # the colours' share of the gradient
                    s = scale[r]
                    d_rgb[r, k, 0], d_rgb[r, k, 1], d_rgb[r, k, 2] = w * (s * a0), w * (s * a1), w * (s * a2)
                else:
                    d_rgb[r, k, 0] = d_rgb[r, k, 1] = d_rgb[r, k, 2] = np.float32(0)
                d_alpha[r, k] = g - u[j]
                u[j] = g * alpha[r, k] + (np.float32(1) - alpha[r, k]) * u[j]
        trans[:] = 1
        for k in range(D):
            for j in range(n):
                r = r0 + j
                d_alpha[r, k] *= trans[j]
                trans[j] *= np.float32(1) - alpha[r, k]


@numba.njit(parallel=True, **_JIT)
def _strong(alpha, min_w, out):  # pragma: no cover - compiled
    R, D = alpha.shape
    min_w = np.float32(min_w)
    for r in numba.prange(R):
        trans = np.float32(1)
        for k in range(D):
            out[r, k] = alpha[r, k] * trans >= min_w  # the weight exactly as _forward computes it
            trans *= np.float32(1) - alpha[r, k]


def strong_samples(alpha: torch.Tensor, min_w: float) -> torch.Tensor:
    """[R, D] bool: the samples whose weight :func:`composite` computes at ``min_w`` or more (the
    same float32 operations, so the same samples its backward pass gives colour gradients).
    Shape: alpha [R, D], float32 on the CPU."""
    out = torch.empty(alpha.shape, dtype=torch.bool)
    with kernel_cache.PARALLEL_LAUNCH:
        _strong(alpha.detach().contiguous().numpy(), min_w, out.numpy())
    return out


def _scratch(R: int) -> np.ndarray:
    """Per-ray working values of the kernels, five rows per tile of rays."""
    return np.empty(((R + _TILE - 1) // _TILE, 5, _TILE), np.float32)


def _array(t: torch.Tensor | None, shape: tuple[int, ...]) -> np.ndarray:
    """The gradient ``t`` as an array, zeros where autograd passed none."""
    return np.zeros(shape, np.float32) if t is None else t.detach().numpy()


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, rgb: torch.Tensor, alpha: torch.Tensor, depth: torch.Tensor, min_w: float, scale: np.ndarray):  # type: ignore[override]
        R, D = alpha.shape
        out_rgb, out_depth, out_acc, weights = torch.empty(R, 3), torch.empty(R), torch.empty(R), torch.empty(R, D)
        with kernel_cache.PARALLEL_LAUNCH:
            _forward(
                rgb.detach().numpy(),
                alpha.detach().numpy(),
                depth.numpy(),
                out_rgb.numpy(),
                out_depth.numpy(),
                out_acc.numpy(),
                weights.numpy(),
                _scratch(R),
            )
        ctx.save_for_backward(rgb, alpha, depth, weights)
        ctx.min_w, ctx.scale = min_w, scale
        ctx.set_materialize_grads(False)
        return out_rgb, out_depth, out_acc, weights

    @staticmethod
    def backward(ctx, g_rgb, g_depth, g_acc, g_w):  # type: ignore[override]
        rgb, alpha, depth, weights = ctx.saved_tensors
        R, D = alpha.shape
        # In the inputs' own memory layout (a field's colours are a view of its samplers' [D, 3,
        # R]): the gradient then reaches the samplers without a copy.
        d_rgb, d_alpha = torch.empty_like(rgb), torch.empty_like(alpha)
        with kernel_cache.PARALLEL_LAUNCH:
            _backward(
                rgb.detach().numpy(),
                alpha.detach().numpy(),
                depth.numpy(),
                weights.numpy(),
                _array(g_rgb, (R, 3)),
                _array(g_depth, (R,)),
                _array(g_acc, (R,)),
                _array(g_w, (R, D)),
                ctx.min_w,
                ctx.scale,
                d_rgb.numpy(),
                d_alpha.numpy(),
                _scratch(R),
            )
        return d_rgb, d_alpha, None, None, None


def supported(rgb: torch.Tensor, alpha: torch.Tensor, depth: torch.Tensor) -> bool:
    """Whether :func:`composite` can take these: float32 CPU tensors, three colour channels, no
    gradient to the depths."""
    tensors = (rgb, alpha, depth)
    cpu = all(t.device.type == "cpu" and t.dtype == torch.float32 for t in tensors)
    return cpu and rgb.shape[-1] == 3 and not depth.requires_grad


def composite(
    rgb: torch.Tensor,
    alpha: torch.Tensor,
    depth: torch.Tensor,
    colour_grad_min_weight: float = 0.0,
    colour_grad_scale: float | torch.Tensor = 1.0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Front-to-back compositing of rgb [R, D, 3], alpha [R, D] and per-sample depth [R, D],
    nearest plane first -> colour [R, 3], depth [R], accumulated alpha [R] and the planes'
    weights [R, D]; differentiable in rgb and alpha, the gradient of a sample's colour times
    ``colour_grad_scale`` (one factor, or one per ray: [R]), and exactly 0 where its weight is
    below ``colour_grad_min_weight``. The gradients of rgb and alpha have their memory layout.
    Only where :func:`supported`."""
    if not supported(rgb, alpha, depth):
        raise ValueError("the compiled composite takes float32 CPU tensors, RGB, and depths without gradient")
    scale = np.broadcast_to(np.asarray(colour_grad_scale, np.float32), (len(alpha),))
    return _Composite.apply(rgb, alpha, depth, colour_grad_min_weight, np.ascontiguousarray(scale))


def warm_up() -> None:
    """Compile the kernels now into numba's on-disk cache (:mod:`cmc.kernel_cache`), so the first
    training step of a fresh process does not pay the compile; the Dockerfiles call it."""
    alpha = torch.rand(2, 3, requires_grad=True)
    # rgb contiguous and as a field returns it (a permuted view); gradients dense and broadcast.
    for rgb in (torch.rand(2, 3, 3), torch.rand(3, 2, 3).permute(1, 2, 0)):
        out = composite(rgb.requires_grad_(), alpha, torch.rand(2, 3), 0.5)
        sum(o.sum() + (o * torch.rand_like(o)).sum() for o in out).backward()
    strong_samples(alpha, 0.5)
