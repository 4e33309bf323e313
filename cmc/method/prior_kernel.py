"""Compiled CPU per-ray priors on compositing weights, with their backward passes: one walk
along each ray instead of torch's prefix sums, logarithms and products over [R, D] tensors and
their backward passes.

:func:`distortion_per_ray` and :func:`alpha_entropy_per_ray` compute what the torch forms in
:func:`cmc.method.losses.distortion` and :func:`cmc.method.losses.alpha_entropy` compute per ray
(the same clamps, and gradients where torch's clamps pass them) in another order of operations,
the entropy's prefix sums in float64 (alpha recovered as ``w_k / T_k`` is ill-conditioned where
``T_k`` is small): the same values up to rounding (``tests/test_prior_kernel.py``). Rays are
split over threads; each ray's sums run in one thread, so the result does not depend on the
thread count. The entropy's forward pass runs in three passes (alpha and the transmittance
compiled, their logarithms in torch, the sums compiled) and keeps each plane's H and H' for the
backward pass.

Distortion, per ray: ``L = sum_{k,l} w_k w_l |s_k - s_l| + delta / 3 sum_k w_k^2`` with
``s_k = k delta``; ``dL/dw_j = 2 sum_l w_l |s_j - s_l| + 2 delta / 3 w_j``, the sum split at j
into prefix and suffix sums of w and w s.

Alpha entropy, per ray: ``L = sum_{k<D-1} T_k H(a_k)`` (the back plane not counted),
``T_k = clamp(1 - P_k, 0, 1)`` with ``P_k = sum_{l<k} w_l``, ``a_k = w_k / max(T_k, 1e-4)``, H
the binary entropy of ``clamp(a_k, 1e-6, 1 - 1e-6)``. ``dL/dw_j = T_j H'(a_j) / max(T_j, 1e-4)
- sum_{k>j} dL_k/dT_k`` (where the clamps pass gradients), ``dL_k/dT_k = H(a_k) - T_k H'(a_k)
w_k / T_k^2``.
"""

from __future__ import annotations

import numba
import numpy as np
import torch

from cmc import kernel_cache

kernel_cache.prepare()
_JIT = dict(nogil=True, cache=True, boundscheck=False, error_model="numpy")
_T_MIN = 1e-4  # the transmittance alpha is recovered with at least (cmc.method.losses.alpha_and_transmittance)
_A_MIN = 1e-6  # alpha clamped to [_A_MIN, 1 - _A_MIN] inside the entropy


@numba.njit(parallel=True, **_JIT)
def _distortion_forward(w, delta, out):  # pragma: no cover - compiled
    R, D = w.shape
    delta = np.float32(delta)
    for r in numba.prange(R):
        before = before_s = acc = sq = np.float32(0)
        for k in range(D):
            s = k * delta
            wk = w[r, k]
            acc += wk * (s * before - before_s)
            sq += wk * wk
            before += wk
            before_s += wk * s
        out[r] = np.float32(2) * acc + sq * delta / np.float32(3)


@numba.njit(parallel=True, **_JIT)
def _distortion_backward(w, delta, g, d_w):  # pragma: no cover - compiled
    R, D = w.shape
    delta = np.float32(delta)
    for r in numba.prange(R):
        total = total_s = np.float32(0)
        for k in range(D):
            total += w[r, k]
            total_s += w[r, k] * k * delta
        before = before_s = np.float32(0)
        for k in range(D):
            s = k * delta
            wk = w[r, k]
            after = total - before - wk
            after_s = total_s - before_s - wk * s
            spread = s * before - before_s + after_s - s * after  # sum_l w_l |s_k - s_l|
            d_w[r, k] = g[r] * (np.float32(2) * spread + np.float32(2) * delta / np.float32(3) * wk)
            before += wk
            before_s += wk * s


@numba.njit(inline="always", **_JIT)
def _transmittance(prefix):  # pragma: no cover - compiled
    """(T, whether its clamp passes a gradient, max(T, _T_MIN)) from the float64 prefix sum."""
    t_raw = 1.0 - prefix
    t = min(max(t_raw, 0.0), 1.0)
    return t, t_raw >= 0 and t_raw <= 1, max(t, _T_MIN)


@numba.njit(parallel=True, **_JIT)
def _entropy_alpha(w, a, t, passes):  # pragma: no cover - compiled
    """Per plane but the back one, the clamped alpha a, the transmittance t (float32) and whether
    alpha's clamp passes a gradient, from the float64 prefix sums of each ray's weights."""
    R, D = w.shape
    lo, hi = np.float32(_A_MIN), np.float32(1 - _A_MIN)
    for r in numba.prange(R):
        prefix = 0.0
        for k in range(D - 1):
            tk, _, t_c = _transmittance(prefix)
            ak = np.float32(w[r, k] / t_c)
            a[r, k] = min(max(ak, lo), hi)
            t[r, k] = tk
            passes[r, k] = ak >= lo and ak <= hi
            prefix += w[r, k]


@numba.njit(parallel=True, **_JIT)
def _entropy_sum(a, t, passes, log_a, log_1ma, out, h, dh):  # pragma: no cover - compiled
    """Per ray the prior (summed in float64), and per plane the entropy h and its derivative dh
    (kept for the backward pass; 0 where alpha's clamp passes no gradient), from the logarithms
    of a and 1 - a."""
    R, D1 = a.shape
    for r in numba.prange(R):
        total = 0.0
        for k in range(D1):
            hk = -(a[r, k] * log_a[r, k] + (np.float32(1) - a[r, k]) * log_1ma[r, k])
            h[r, k] = hk
            dh[r, k] = log_1ma[r, k] - log_a[r, k] if passes[r, k] else np.float32(0)
            total += t[r, k] * hk
        out[r] = total


@numba.njit(parallel=True, **_JIT)
def _entropy_backward(w, g, h, dh, d_w):  # pragma: no cover - compiled
    R, D = w.shape
    for r in numba.prange(R):
        prefix = 0.0
        for k in range(D - 1):
            prefix += w[r, k]
        d_w[r, D - 1] = np.float32(0)
        suffix = 0.0  # sum over k > j of dL_k / dP_k
        for k in range(D - 2, -1, -1):
            prefix -= w[r, k]
            t, in_t, t_c = _transmittance(prefix)
            d_w[r, k] = g[r] * (t * dh[r, k] / t_c + suffix)
            d_t = h[r, k]
            if t >= _T_MIN:
                d_t -= t * dh[r, k] * w[r, k] / (t_c * t_c)
            if in_t:
                suffix -= d_t


class _Distortion(torch.autograd.Function):
    @staticmethod
    def forward(ctx, w: torch.Tensor, delta: float):  # type: ignore[override]
        out = torch.empty(w.shape[0])
        with kernel_cache.PARALLEL_LAUNCH:
            _distortion_forward(w.detach().numpy(), delta, out.numpy())
        ctx.save_for_backward(w)
        ctx.delta = delta
        return out

    @staticmethod
    def backward(ctx, g):  # type: ignore[override]
        (w,) = ctx.saved_tensors
        d_w = torch.empty_like(w)
        with kernel_cache.PARALLEL_LAUNCH:
            _distortion_backward(w.detach().numpy(), ctx.delta, g.contiguous().numpy(), d_w.numpy())
        return d_w, None


class _AlphaEntropy(torch.autograd.Function):
    @staticmethod
    def forward(ctx, w: torch.Tensor):  # type: ignore[override]
        R, D = w.shape
        a, t, passes = torch.empty(R, D - 1), torch.empty(R, D - 1), torch.empty(R, D - 1, dtype=torch.bool)
        out, h, dh = torch.empty(R), torch.empty(R, D - 1), torch.empty(R, D - 1)
        with kernel_cache.PARALLEL_LAUNCH:
            _entropy_alpha(w.detach().numpy(), a.numpy(), t.numpy(), passes.numpy())
        # log a and log(1 - a) in torch, vectorised (numba's are scalar without Intel's SVML)
        log_a, log_1ma = torch.log(a), torch.log1p(-a)
        with kernel_cache.PARALLEL_LAUNCH:
            _entropy_sum(
                a.numpy(), t.numpy(), passes.numpy(), log_a.numpy(), log_1ma.numpy(), out.numpy(), h.numpy(), dh.numpy()
            )
        ctx.save_for_backward(w, h, dh)
        return out

    @staticmethod
    def backward(ctx, g):  # type: ignore[override]
        w, h, dh = ctx.saved_tensors
        d_w = torch.empty_like(w)
        with kernel_cache.PARALLEL_LAUNCH:
            _entropy_backward(
                w.detach().numpy(),
                g.contiguous().numpy(),
                h.numpy(),
                dh.numpy(),
                d_w.numpy(),
            )
        return d_w


def supported(weights: torch.Tensor) -> bool:
    """Whether the kernels take these weights: a float32 CPU tensor [R, D]."""
    return weights.device.type == "cpu" and weights.dtype == torch.float32 and weights.dim() == 2


def distortion_per_ray(weights: torch.Tensor, delta: float) -> torch.Tensor:
    """[R] the distortion prior of each ray of compositing weights [R, D] (plane spacing
    ``delta`` in normalised disparity); differentiable in the weights."""
    return _Distortion.apply(weights.contiguous(), delta)


def alpha_entropy_per_ray(weights: torch.Tensor) -> torch.Tensor:
    """[R] the transmittance-weighted binary entropy of the alpha each ray of compositing
    weights [R, D] meets; differentiable in the weights."""
    return _AlphaEntropy.apply(weights.contiguous())


def warm_up() -> None:
    """Compile the kernels now into numba's on-disk cache (:mod:`cmc.kernel_cache`); the Docker images call it."""
    w = torch.full((2, 3), 0.2)
    for fn in (lambda x: distortion_per_ray(x, 0.5), alpha_entropy_per_ray):
        x = w.clone().requires_grad_()
        fn(x).sum().backward()
