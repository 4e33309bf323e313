"""The compiled per-ray priors (cmc.method.prior_kernel) against their torch forms in
cmc.method.losses: values and gradients, on weights with nearly opaque planes mid-ray and rays
that meet nothing; the entropy leaves the back plane out."""

from __future__ import annotations

import pytest
import torch

from cmc.method import prior_kernel
from cmc.method.losses import alpha_entropy, distortion
from cmc.mpi.rendering import RayOutput

R, D = 600, 14


def weights_of_rays(seed: int) -> torch.Tensor:
    """[R, D] compositing weights: faint alpha, some opaque planes (also mid-ray), empty rays."""
    g = torch.Generator().manual_seed(seed)
    alpha = torch.rand(R, D, generator=g) ** 6
    # Nearly opaque planes, also mid-ray (alpha recovered from weights is ill-conditioned where
    # the transmittance reaches float32's resolution, in either implementation: not tested here).
    alpha[torch.rand(R, D, generator=g) < 0.05] = 0.9
    alpha[: R // 10] = 0.0  # rays that meet nothing
    alpha[R // 10 :, -1] = 1.0
    trans = torch.cumprod(torch.cat([torch.ones(R, 1), 1 - alpha[:, :-1]], 1), 1)
    return alpha * trans


@pytest.mark.parametrize("prior", ["distortion", "alpha_entropy"])
def test_the_kernels_match_the_torch_priors_in_value_and_gradient(prior):
    """float32 weights take the kernel, float64 weights the torch form (the reference)."""
    loss = (lambda outs: distortion(outs, D)) if prior == "distortion" else alpha_entropy
    w = weights_of_rays(3)
    covered = (torch.rand(R, generator=torch.Generator().manual_seed(4)) > 0.2).float()  # the loss's ray mask

    def value(weights: torch.Tensor) -> torch.Tensor:
        return loss([RayOutput(weights.new_zeros(R, 3), weights.new_zeros(R), covered.to(weights), weights)])

    assert prior_kernel.supported(w) and not prior_kernel.supported(w.double())
    fast_w, slow_w = w.clone().requires_grad_(), w.double().requires_grad_()
    fast, slow = value(fast_w), value(slow_w)
    assert slow.item() > 1e-3  # the rays carry the prior
    torch.testing.assert_close(fast.double(), slow, rtol=1e-5, atol=1e-8)
    (fast_g,) = torch.autograd.grad(fast, fast_w)
    (slow_g,) = torch.autograd.grad(slow, slow_w)
    assert float((slow_g[covered == 0]).abs().max()) == 0 and float(slow_g.abs().max()) > 0
    torch.testing.assert_close(fast_g.double(), slow_g, rtol=1e-4, atol=1e-6 * float(slow_g.abs().max()))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_entropy_leaves_the_opaque_back_plane_out(dtype):
    """The back plane is opaque by construction (its alpha 1, whatever weight reaches it): its
    weight changes neither the entropy nor any gradient, in the kernel (float32) and in torch."""
    w = weights_of_rays(5).to(dtype)
    out = lambda x: [RayOutput(x.new_zeros(R, 3), x.new_zeros(R), x.new_ones(R), x)]  # noqa: E731
    x = w.clone().requires_grad_()
    (g,) = torch.autograd.grad(alpha_entropy(out(x)), x)
    moved = w.clone()
    moved[:, -1] *= 0.5
    torch.testing.assert_close(alpha_entropy(out(moved)), alpha_entropy(out(w)), rtol=0, atol=0)
    assert not g[:, -1].any() and g[:, :-1].any()
