"""The compiled CPU sampler of plane textures against torch's grid_sample, values and gradients."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from cmc.config import PyramidFieldConfig
from cmc.mpi import plane_sampling
from cmc.mpi.fields import PyramidPlaneField


def _grid_sample_sum(grid, plane_texture, textures, mode):
    """The definition, with torch: sum over textures of grid_sample of each plane's texture."""
    index = torch.as_tensor(plane_texture)
    return sum(F.grid_sample(t[index], grid[:, None], mode=mode, align_corners=False)[:, :, 0] for t in textures)


def _footprint_inside(grid: torch.Tensor, h: int, w: int, mode: str) -> torch.Tensor:
    """Whether every tap of each sample (2 x 2 bilinear, 4 x 4 bicubic) lies inside an h x w
    texture (``align_corners=False``)."""
    lo, hi = (0, 1) if mode == "bilinear" else (-1, 2)
    first = [torch.floor(((grid[..., i] + 1) * n - 1) / 2) for i, n in ((0, w), (1, h))]
    return (first[0] + lo >= 0) & (first[0] + hi < w) & (first[1] + lo >= 0) & (first[1] + hi < h)


def _assert_same_values_and_gradients(fast, slow, textures, weights):
    """``fast(leaves)`` and ``slow(leaves)`` (functions of copies of ``textures`` with gradients)
    agree in value and in the gradients of ``sum(out * weights)``; returns the fast one's output
    and gradients."""
    outs, grads = [], []
    for fn in (fast, slow):
        leaves = [t.clone().requires_grad_() for t in textures]
        out = fn(leaves)
        (out * weights).sum().backward()
        outs.append(out.detach())
        grads.append([t.grad for t in leaves])
    torch.testing.assert_close(outs[0], outs[1], rtol=0, atol=1e-5)
    for mine, theirs in zip(*grads, strict=True):
        torch.testing.assert_close(mine, theirs, rtol=0, atol=1e-4)
    return outs[0], grads[0]


@pytest.mark.parametrize("zeros", [False, True])
@pytest.mark.parametrize("mode", ["bilinear", "bicubic"])
@pytest.mark.parametrize("plane_texture", [[0, 1, 2, 3, 4], [0, 0, 0, 1, 1]])
def test_sample_planes_matches_grid_sample_and_its_gradient(plane_texture, mode, zeros):
    """With ``zeros``, the gradient reaching the samples is exactly 0 at most samples and
    channels (as for faint samples' colours, which the backward pass skips). The samples cover
    both paths of the kernels: footprints wholly inside the larger texture (no test per tap)
    and footprints reaching past its edge."""
    gen = torch.Generator().manual_seed(0)
    textures = [torch.randn(max(plane_texture) + 1, 4, h, w, generator=gen) for h, w in ((9, 13), (4, 6))]
    # Points beyond the texture (|g| > 1) sample zero padding, as grid_sample's do.
    grid = torch.rand(len(plane_texture), 300, 2, generator=gen) * 3 - 1.5
    inside = _footprint_inside(grid, 9, 13, mode)
    assert 0 < inside.sum() < inside.numel(), inside.sum()
    weights = torch.randn(len(plane_texture), 4, 300, generator=gen)
    if zeros:
        weights[torch.rand(weights.shape, generator=gen) < 0.7] = 0
        weights[:, :, :100] = 0  # whole samples
    out, grads = _assert_same_values_and_gradients(
        lambda leaves: plane_sampling.sample_planes(grid, plane_texture, leaves, mode),
        lambda leaves: _grid_sample_sum(grid, plane_texture, leaves, mode),
        textures,
        weights,
    )
    assert out.abs().sum() > 0 and grads[0].abs().sum() > 0


def test_sample_planes_does_not_depend_on_the_thread_count():
    """Also: textures that no plane reads (3 to 5 here) get a zero gradient."""
    gen = torch.Generator().manual_seed(1)
    tex = torch.randn(6, 3, 20, 30, generator=gen)
    grid = torch.rand(6, 500, 2, generator=gen) * 2 - 1
    results = []
    threads = torch.get_num_threads()
    try:
        for n in (1, 2):
            torch.set_num_threads(n)
            leaf = tex.clone().requires_grad_()
            out = plane_sampling.sample_planes(grid, [0, 0, 1, 1, 2, 2], [leaf])
            out.square().sum().backward()
            results.append((out.detach(), leaf.grad))
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(results[0][0], results[1][0]) and torch.equal(results[0][1], results[1][1])
    grad = results[1][1]
    assert (grad[3:] == 0).all() and (grad[:3] != 0).any(dim=(1, 2, 3)).all()


def test_sample_planes_refuses_what_it_cannot_differentiate():
    tex = torch.zeros(1, 4, 2, 2)
    with pytest.raises(ValueError):
        plane_sampling.sample_planes(torch.zeros(1, 3, 2, requires_grad=True), [0], [tex])
    with pytest.raises(ValueError):
        plane_sampling.sample_planes(torch.zeros(1, 3, 2, dtype=torch.float64), [0], [tex.double()])
    with pytest.raises(ValueError, match="mode"):
        plane_sampling.sample_planes(torch.zeros(1, 3, 2), [0], [tex], "nearest")


def test_bicubic_keeps_detail_that_bilinear_blurs_between_texels():
    """What bicubic sampling is for: a texture of fine detail (a sinusoid of period 3.2 texels)
    sampled half-way between its texels. Bilinear averages neighbours and keeps under 60 % of
    the amplitude (56 %); the cubic kernel keeps over 80 % (84 %) and errs less than half as much."""
    n, period = 64, 3.2
    x = torch.arange(n, dtype=torch.float32) + 0.5  # texel centres, in texels
    tex = torch.sin(2 * torch.pi * x / period).reshape(1, 1, 1, n).expand(1, 1, 4, n).contiguous()
    at = x[8:-8] + 0.5  # half-way between texel centres, away from the edges
    grid = torch.stack([at / n * 2 - 1, torch.zeros_like(at)], -1)[None]  # [1, R, 2]
    truth = torch.sin(2 * torch.pi * at / period)
    err, amp = {}, {}
    for mode in ("bilinear", "bicubic"):
        s = plane_sampling.sample_planes(grid, [0], [tex], mode)[0, 0]
        err[mode] = float((s - truth).abs().mean())
        amp[mode] = float((s * truth).sum() / (truth * truth).sum())
    assert amp["bilinear"] < 0.6 and amp["bicubic"] > 0.8
    assert err["bicubic"] < 0.5 * err["bilinear"]


@pytest.mark.parametrize("channels", [1, 3])
def test_fold_levels_matches_interpolate_and_its_gradient(channels):
    """The compiled fold against its definition with ``F.interpolate`` (sizes not all halves of
    each other, as fern's 227 x 302 over 114 x 151 over 57 x 76), values and gradients; a
    constant coarsest level folds to that constant everywhere (the resampling weights sum to 1)."""
    gen = torch.Generator().manual_seed(3)
    sizes = [(23, 30), (12, 15), (6, 8), (3, 4)]
    levels = [torch.randn(5, channels, h, w, generator=gen) for h, w in sizes]
    weights = torch.randn(5, channels, *sizes[0], generator=gen)
    _, grads = _assert_same_values_and_gradients(
        plane_sampling.fold_levels, plane_sampling.fold_levels_reference, levels, weights
    )
    assert all(g.abs().sum() > 0 for g in grads)
    flat = [torch.zeros(5, channels, h, w) for h, w in sizes[:-1]] + [torch.full((5, channels, *sizes[-1]), 0.7)]
    torch.testing.assert_close(plane_sampling.fold_levels(flat), torch.full((5, channels, *sizes[0]), 0.7))


@pytest.mark.parametrize("interpolation", ["bilinear", "bicubic"])
@pytest.mark.parametrize(("num_planes", "groups"), [(12, 4), (10, 4)])
@pytest.mark.parametrize("masked", [False, True])
def test_pyramid_field_is_the_same_with_either_sampler(monkeypatch, num_planes, groups, interpolation, masked):
    """The field on the CPU (compiled sampler) and on torch's grid_sample (the GPU's path): same
    colours and alpha, same gradients; 10 planes in 4 groups makes groups of unequal size. With
    ``colour_where`` (here: alpha above 0.3) both give 0.5 and no colour gradient at the other
    samples, and the same as without it at the marked ones."""
    gen = torch.Generator().manual_seed(2)
    cfg = PyramidFieldConfig(base_groups=groups, base_interpolation=interpolation)
    field = PyramidPlaneField(num_planes, 30, 40, cfg, torch.rand(3, 30, 40, generator=gen))
    with torch.no_grad():
        for p in field.parameters():
            p.add_(0.3 * torch.randn(p.shape, generator=gen))
    g = torch.rand(200, num_planes, 2, generator=gen) * 3 - 1.5
    where = (lambda alpha: alpha.detach() > 0.3) if masked else None
    results = []
    for compiled in (True, False):
        if not compiled:
            monkeypatch.setattr(plane_sampling, "supported", lambda *a: False)
        field.zero_grad()
        rgb, alpha = field(g, None, None, where)
        (rgb.square().sum() + alpha.sum()).backward()
        results.append((rgb.detach(), alpha.detach(), [p.grad.clone() for p in field.parameters()]))
    (rgb1, a1, g1), (rgb2, a2, g2) = results
    torch.testing.assert_close(rgb1, rgb2, rtol=0, atol=1e-6)
    torch.testing.assert_close(a1, a2, rtol=0, atol=1e-6)
    for x, y in zip(g1, g2, strict=True):
        torch.testing.assert_close(x, y, rtol=1e-4, atol=1e-5)
    assert all(np.isfinite(x.numpy()).all() and x.abs().sum() > 0 for x in g1)
    if masked:
        marked = a1 > 0.3
        assert 0.1 < float(marked.float().mean()) < 0.9
        assert bool((rgb1[~marked] == 0.5).all())
        full, _ = field(g, None, None)
        torch.testing.assert_close(rgb1[marked], full.detach()[marked], rtol=0, atol=1e-6)
