"""The compiled CPU compositing against its torch twin, values and gradients."""

import numba
import pytest
import torch

from cmc.mpi import composite_kernel
from cmc.mpi.rendering import composite, composite_torch, strong_samples


def _rays(seed: int, R: int = 400, D: int = 9) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """rgb [R, D, 3] (a view of [D, 3, R], as a field returns it), alpha [R, D] with an opaque back
    plane, opaque planes mid-ray and rays with no alpha in front, depth [R, D]."""
    gen = torch.Generator().manual_seed(seed)
    rgb = torch.rand(D, 3, R, generator=gen).permute(2, 0, 1)
    alpha = torch.rand(R, D, generator=gen)
    alpha[:, -1] = 1
    alpha[:20, 3] = 1
    alpha[20:40, :-1] = 0
    return rgb, alpha, torch.rand(R, D, generator=gen) * 5


@pytest.mark.parametrize(("min_weight", "scale"), [(0.0, 1.0), (0.05, 1.0), (0.05, 0.1), (0.05, "per ray")])
@pytest.mark.parametrize("outputs", ["all", "colour only"])
def test_the_compiled_composite_is_its_torch_twin(outputs, min_weight, scale):
    """The same colour, depth, coverage and weights, and the same gradients of rgb and alpha
    (from all four outputs, or from the colour alone: autograd then passes no gradient for the
    others), up to float rounding; with a least weight for colour gradients, the same ones cut;
    with a factor on the colours' gradients (one, or one per ray, some 0), the same factors. The
    compiled path's gradients keep the inputs' memory layout."""
    rgb0, alpha0, depth = _rays(0)
    gen = torch.Generator().manual_seed(1)
    grads = [torch.randn(400, 3, generator=gen), torch.randn(400, generator=gen)]
    grads += [torch.randn(400, generator=gen), torch.randn(400, 9, generator=gen)]
    factor = torch.rand(400, generator=gen) * (torch.rand(400, generator=gen) > 0.3) if scale == "per ray" else scale
    results, layouts = [], []
    for fn in (composite_kernel.composite, composite_torch):
        rgb, alpha = rgb0.clone().requires_grad_(), alpha0.clone().requires_grad_()
        for t in (rgb, alpha):
            t.register_hook(lambda g, t=t: layouts.append(g.stride() == t.stride()))
        out = fn(rgb, alpha, depth, min_weight, factor)
        out = (out.rgb, out.depth, out.acc, out.weights) if fn is composite_torch else out
        used = out if outputs == "all" else out[:1]
        sum((o * g).sum() for o, g in zip(used, grads, strict=False)).backward()
        results.append([*(o.detach() for o in out), rgb.grad, alpha.grad])
    for mine, theirs in zip(*results, strict=True):
        torch.testing.assert_close(mine, theirs, rtol=0, atol=2e-6)
    assert not rgb0.is_contiguous() and layouts[:2] == [True, True]
    assert results[0][5].abs().sum() > 0 and results[0][4].abs().sum() > 0
    torch.testing.assert_close(results[0][2][20:40], torch.ones(20))  # the opaque back plane
    faint = results[0][3] < min_weight
    assert torch.equal(results[0][4][faint], torch.zeros(int(faint.sum()), 3))
    scaled = torch.as_tensor(factor).expand(400)[:, None] > 0
    assert (results[0][4][(results[0][3] >= max(min_weight, 1e-6)) & scaled] != 0).all()
    if min_weight > 0:
        assert 0.2 < faint.float().mean() < 0.8  # the cut applies to a good share, not all


def test_faint_samples_pass_no_colour_gradient_and_the_rest_the_same():
    """composite with colour_grad_min_weight: the colour gradient of a sample weighing less is 0,
    every other gradient (alpha, and the colour of the samples that weigh enough) is unchanged,
    as are the values."""
    rgb0, alpha0, depth = _rays(4)
    runs = []
    for w_min in (0.0, 0.05):
        rgb, alpha = rgb0.clone().requires_grad_(), alpha0.clone().requires_grad_()
        out = composite(rgb, alpha, depth, w_min)
        (out.rgb.square().sum() + out.depth.sum()).backward()
        runs.append((out.rgb.detach(), out.weights.detach(), rgb.grad, alpha.grad))
    (rgb_a, w, g_all, a_all), (rgb_b, _, g_cut, a_cut) = runs
    keep = w >= 0.05
    assert torch.equal(rgb_a, rgb_b) and torch.equal(a_all, a_cut)
    assert torch.equal(g_cut[keep], g_all[keep]) and not g_cut[~keep].any() and g_all[~keep].any()


def test_composite_takes_the_compiled_path_on_the_cpu_and_torch_where_it_cannot(monkeypatch):
    """rendering.composite: float32 CPU RGB to the kernel; float64, other channel counts or
    depths with a gradient to the torch ops."""
    calls = []
    kernel = composite_kernel.composite
    monkeypatch.setattr(composite_kernel, "composite", lambda *a: calls.append(a[0].dtype) or kernel(*a))
    rgb, alpha, depth = _rays(2)
    out = composite(rgb, alpha, depth)
    torch.testing.assert_close(out.rgb, composite_torch(rgb, alpha, depth).rgb, rtol=0, atol=2e-6)
    composite(rgb.double(), alpha.double(), depth.double())
    composite(rgb, alpha, depth.clone().requires_grad_())
    five = composite(torch.rand(400, 9, 5), alpha, depth)
    assert five.rgb.shape == (400, 5)
    assert calls == [torch.float32]


def test_the_compiled_composite_does_not_depend_on_the_thread_count():
    rgb, alpha, depth = _rays(3)
    threads = numba.get_num_threads()
    outs = []
    try:
        for n in (1, min(2, numba.config.NUMBA_NUM_THREADS)):
            numba.set_num_threads(n)
            a = alpha.clone().requires_grad_()
            out = composite_kernel.composite(rgb, a, depth)
            (out[0].square().sum() + out[3].sum()).backward()
            outs.append((out[0], a.grad))
    finally:
        numba.set_num_threads(threads)
    assert torch.equal(outs[0][0], outs[1][0]) and torch.equal(outs[0][1], outs[1][1])


def test_strong_samples_are_those_the_composite_passes_colour_gradients():
    """strong_samples marks exactly the samples whose weight the compiled composite computes at
    the least weight or more (the same float32 operations), and its torch twin the same samples
    up to ties within rounding."""
    _, alpha, _ = _rays(5)
    weights = composite_kernel.composite(*_rays(5))[3]
    for min_weight in (1e-3, 0.05, 0.3):
        strong = composite_kernel.strong_samples(alpha, min_weight)
        assert torch.equal(strong, weights >= min_weight)
        assert 0 < strong.float().mean() < 1
        twin = strong_samples(alpha.double(), min_weight)
        assert (twin != strong).sum() <= int(((weights - min_weight).abs() < 1e-6).sum())
