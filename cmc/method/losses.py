"""The CMC losses (paper Eq. 4.5-4.8) over renders of the same rays by every MPI.

Every function takes ``outs``: one :class:`cmc.mpi.rendering.RayOutput` per MPI, all for the same
R target rays. A ray counts for an MPI only where that MPI's planes cover it (accumulated alpha
> 0.5, treated as a constant mask): outside its extent an MPI renders nothing, and asking it to
match a colour there would only add a constant to the loss.

Squared norms are summed over RGB channels and averaged over rays, as written in the paper.
Depths are divided by ``depth_scale`` (far - near of the planes) before squaring, which equals
the paper's depth loss with lambda_dc rescaled by 1 / (far - near)^2 and makes the weights
independent of the scene's units.
"""

from __future__ import annotations

from collections.abc import Sequence
from itertools import combinations

import torch

from cmc.method import prior_kernel
from cmc.mpi.rendering import RayOutput


def _mask(o: RayOutput) -> torch.Tensor:
    return (o.acc.detach() > 0.5).float()


def reconstruction_loss(outs: Sequence[RayOutput], target_rgb: torch.Tensor) -> torch.Tensor:
    """Eq. 4.5 for one input view: mean over MPIs and rays of ||C_i(r) - C_gt(r)||^2.

    Shape: target_rgb [R, 3].
    """
    terms = [(_mask(o) * ((o.rgb - target_rgb) ** 2).sum(-1)).mean() for o in outs]
    return torch.stack(terms).mean()


def _pairwise(outs: Sequence[RayOutput], value) -> torch.Tensor:
    terms = [(_mask(a) * _mask(b) * value(a, b)).mean() for a, b in combinations(outs, 2)]
    return torch.stack(terms).mean() if terms else outs[0].rgb.new_zeros(())


def appearance_consistency(outs: Sequence[RayOutput]) -> torch.Tensor:
    """Eq. 4.6: mean over MPI pairs i < j and rays of ||C_i(r) - C_j(r)||^2."""
    return _pairwise(outs, lambda a, b: ((a.rgb - b.rgb) ** 2).sum(-1))


def depth_consistency(outs: Sequence[RayOutput], depth_scale: float) -> torch.Tensor:
    """Eq. 4.7: mean over MPI pairs i < j and rays of ((Z_i(r) - Z_j(r)) / depth_scale)^2."""
    return _pairwise(outs, lambda a, b: ((a.depth - b.depth) / depth_scale) ** 2)


def robust_depth_consistency(outs: Sequence[RayOutput], near: float, far: float, scale: float) -> torch.Tensor:
    """Eq. 4.7 in an occlusion-tolerant form: mean over MPI pairs and rays of
    ``log(1 + ((s_i - s_j) / scale)^2)`` on normalised disparity
    ``s = (1/z - 1/far) / (1/near - 1/far)`` (0 at far, 1 at near; the planes are uniform in s).

    Two MPIs may rightly disagree about a ray's depth where one of them sees an occluder and the
    other the surface behind it; the squared loss then pulls both towards an average depth (a
    halo of wrong depth at every occlusion edge). The Cauchy penalty corrects disagreements of a
    few ``scale`` (use one plane spacing, 1 / (D - 1)) and lets large ones go: its gradient falls
    off as 1 / difference.
    """
    inv_near, inv_far = 1.0 / near, 1.0 / far

    def s(o: RayOutput) -> torch.Tensor:
        return (1.0 / o.depth.clamp_min(0.5 * near) - inv_far) / (inv_near - inv_far)

    return _pairwise(outs, lambda a, b: torch.log1p(((s(a) - s(b)) / scale) ** 2))


def distortion(outs: Sequence[RayOutput], num_planes: int) -> torch.Tensor:
    """Concentration prior on each ray's compositing weights (the distortion loss of
    Mip-NeRF 360, over plane position in normalised disparity s_k = k / (D - 1)).

    Per ray: ``sum_{k,l} w_k w_l |s_k - s_l| + 1/3 sum_k w_k^2 delta`` with plane spacing
    ``delta = 1 / (D - 1)``. It is small when the weight sits on one plane or a few adjacent ones,
    and grows when it is spread over distant planes (a ray meeting fog, or two surfaces
    half-transparent). Mean over MPIs and covered rays; every output needs ``weights``. On the
    CPU each ray's sum comes from a compiled kernel (:func:`cmc.method.prior_kernel.distortion_per_ray`).
    """
    delta = 1.0 / (num_planes - 1)
    terms = []
    for o in outs:
        w = o.weights
        if prior_kernel.supported(w):
            per_ray = prior_kernel.distortion_per_ray(w, delta)
        else:
            s = torch.arange(w.shape[1], device=w.device, dtype=w.dtype) * delta
            # sum_{k,l} w_k w_l |s_k - s_l| = 2 sum_k w_k (s_k W_<k - S_<k), exclusive prefix sums.
            W = torch.cumsum(w, 1) - w
            S = torch.cumsum(w * s, 1) - w * s
            per_ray = 2 * (w * (s * W - S)).sum(1) + (w**2).sum(1) * delta / 3
        terms.append((_mask(o) * per_ray).mean())
    return torch.stack(terms).mean()


def alpha_and_transmittance(weights: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-plane alpha and transmittance recovered from compositing weights ``[R, D]`` (front to
    back): ``T_k = 1 - sum_{l<k} w_l`` (clamped to [0, 1]) and ``a_k = w_k / T_k`` (``T_k`` at
    least 1e-4). Both ``[R, D]``; alpha is not clamped."""
    trans = (1 - (torch.cumsum(weights, 1) - weights)).clamp(0, 1)
    return weights / trans.clamp_min(1e-4), trans


def alpha_entropy(outs: Sequence[RayOutput]) -> torch.Tensor:
    """Binary entropy of the alpha a ray meets, weighted by its transmittance there.

    Per ray: ``sum_k T_k H(a_k)`` with ``H(a) = -a log a - (1 - a) log(1 - a)``, alpha and
    transmittance recovered from the compositing weights (``T_k = 1 - sum_{l<k} w_l``,
    ``a_k = w_k / T_k``). Faint alpha in front of a surface (fog: a ghost of a surface at another
    depth once the view moves) costs, clear space (a = 0) and an opaque surface (a = 1) do not,
    nor anything behind an opaque surface. The back plane (k = D - 1) is not counted: it is
    opaque by construction, and its alpha recovered in float32 lands a few 1e-6 from 1 either
    way, where H' is large and the clamp decides by rounding whether it passes. Mean over MPIs
    and covered rays; on the CPU each ray's sum comes from a compiled kernel
    (:func:`cmc.method.prior_kernel.alpha_entropy_per_ray`).
    """
    terms = []
    for o in outs:
        if prior_kernel.supported(o.weights):
            per_ray = prior_kernel.alpha_entropy_per_ray(o.weights)
        else:
            a, trans = (x[:, :-1] for x in alpha_and_transmittance(o.weights))  # the back plane left out
            a = a.clamp(1e-6, 1 - 1e-6)
            per_ray = (trans * -(a * torch.log(a) + (1 - a) * torch.log1p(-a))).sum(1)
        terms.append((_mask(o) * per_ray).mean())
    return torch.stack(terms).mean()
