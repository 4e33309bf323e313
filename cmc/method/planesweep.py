"""Plane-sweep stereo over an MPI's planes: a photo-consistency prior to initialise alpha.

For MPI i and plane k, every texel of the plane extent is a 3D point; it is projected into the
other input views with the plane-induced homography, and the colour found there is compared
with the reference photo. Planes on which the views agree are likely surfaces. The ``fast``
preset starts its alpha from this (``PyramidFieldConfig.init_from_sweep``), so training refines a
plausible geometry instead of discovering one from uniform fog; :class:`SweepConfig` holds the
sweep's settings.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import torch
import torch.nn.functional as F

from cmc.config import SweepConfig
from cmc.geometry.planes import homographies_ref_from_tgt, texel_grid


def texel_pixels(frame, height: int, width: int) -> torch.Tensor:
    """[height * width, 2] reference pixel coordinates of a texel grid over the plane extent."""
    return frame.pixels_from_grid(texel_grid(height, width, frame.K.device).reshape(-1, 2))


def sample_image(image: torch.Tensor, uv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Bilinear colours of image [3, H, W] at pixel coordinates uv [..., 2] -> ([..., 3], inside [...])."""
    H, W = image.shape[-2:]
    g = uv / uv.new_tensor([W, H]) * 2 - 1
    inside = (g.abs() <= 1).all(-1)
    flat = g.reshape(1, 1, -1, 2)
    c = F.grid_sample(image[None], flat, align_corners=False, padding_mode="border")[0, :, 0]
    return c.T.reshape(*uv.shape[:-1], 3), inside


@torch.no_grad()
def _texel_cost(
    fr: Any,
    other: Any,
    image: torch.Tensor,
    ref_grid: torch.Tensor,
    uv_ref: torch.Tensor,
    cost: str,
    compiled: bool = True,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The per-texel matching cost [D, h, w] of the reference MPI ``fr``'s planes against one
    other view (``other``'s frame, its photo ``image`` [3, H, W]), 0 where that view does not see
    the texel, and where it sees them ([D, h, w] bool). ``ref_grid`` [3, h, w]: the reference
    colour at the texels, whose reference pixels are ``uv_ref`` [h * w, 2]. On the CPU a compiled
    kernel computes it (:func:`cmc.method.sweep_kernel.view_cost`) unless ``compiled`` is False;
    elsewhere :func:`view_cost_torch`, its twin."""
    # Homographies taking view-j pixels to reference pixels for the reference planes; invert.
    H_ref_from_j = homographies_ref_from_tgt(fr.K, fr.ref_from_world, other.K, other.world_from_ref, fr.depths)
    H_j_from_ref = torch.linalg.inv(H_ref_from_j)
    census_radius = CENSUS_RADIUS if cost == "ad_census" else None
    if compiled and image.device.type == "cpu" and image.dtype == torch.float32:
        from cmc.method import sweep_kernel

        uv = uv_ref.reshape(*ref_grid.shape[1:], 2)
        return sweep_kernel.view_cost(H_j_from_ref, image, ref_grid, uv, census_radius, AD_SCALE, CENSUS_SCALE)
    return view_cost_torch(H_j_from_ref, image, ref_grid, uv_ref, census_radius)


def view_cost_torch(
    H_j_from_ref: torch.Tensor,
    image: torch.Tensor,
    ref_grid: torch.Tensor,
    uv_ref: torch.Tensor,
    census_radius: int | None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The per-texel cost [D, h, w] of the planes whose homographies ``H_j_from_ref`` [D, 3, 3]
    take reference pixels to pixels of the photo ``image`` [3, H, W], and whether that view sees
    them ([D, h, w] bool): the mean absolute colour difference to ``ref_grid`` [3, h, w] at the
    texels' reference pixels ``uv_ref`` [h * w, 2]; with ``census_radius`` the AD-Census cost
    (:func:`plane_sweep_weights`); 0 where the view does not see the texel. Any device."""
    D, (height, width) = H_j_from_ref.shape[0], ref_grid.shape[1:]
    p = torch.cat([uv_ref, torch.ones_like(uv_ref[:, :1])], -1)
    q = torch.einsum("dij,tj->dti", H_j_from_ref, p)
    uv_j = q[..., :2] / q[..., 2:3].clamp_min(1e-6)
    rgb_j, inside = sample_image(image, uv_j)  # [D, T, 3]
    inside = (inside & (q[..., 2] > 0)).reshape(D, height, width)
    ref_rgb = ref_grid.reshape(3, -1).T
    diff = (rgb_j - ref_rgb).abs().mean(-1).reshape(D, height, width)
    if census_radius is not None:
        warped = rgb_j.reshape(D, height, width, 3).permute(0, 3, 1, 2)
        census = census_distance(ref_grid, warped, census_radius)
        diff = (1 - torch.exp(-diff / AD_SCALE)) + (1 - torch.exp(-census / CENSUS_SCALE))
    return diff * inside, inside


def _combined_window_cost(
    weights: torch.Tensor | None,
    window: int,
    costs: list[torch.Tensor],
    seen: list[torch.Tensor],
    occlusion_aware: bool,
    kind: str,
    compiled: bool = True,
) -> torch.Tensor:
    """The other views' per-texel costs (each [D, h, w], 0 where unseen; ``seen`` each [D, h, w]
    bool) as one window-averaged cost [D, h, w]. Each view's cost is averaged over the window
    (:func:`_window_weights`; ``weights`` None: uniform) over the texels it sees (sum of costs /
    weight seen); the views that see a texel through the window are then averaged, or with
    ``occlusion_aware`` the lowest is taken. A plane no other view sees costs what a random match
    would: colour difference 0.5, and half the census bits (``kind``: "ad" or "ad_census"). On
    the CPU with edge-aware weights a compiled kernel does it all in one pass
    (:func:`cmc.method.sweep_kernel.combined_window_cost`, the same result to the bit) unless
    ``compiled`` is False."""
    flat = 0.5 if kind == "ad" else 2 - math.exp(-0.5 / AD_SCALE) - math.exp(-0.5 / CENSUS_SCALE)
    if compiled and weights is not None and weights.device.type == "cpu" and costs[0].dtype == torch.float32:
        from cmc.method import sweep_kernel

        return sweep_kernel.combined_window_cost(weights, window, costs, seen, occlusion_aware, flat)
    aggregate = _window_sum(weights, window)
    averaged, seen_through = [], []
    for c, s in zip(costs, seen, strict=True):
        frac = aggregate(s.float())
        averaged.append(aggregate(c) / frac.clamp_min(1e-6))
        seen_through.append(frac > 0)
    cost, seen_any = torch.stack(averaged), torch.stack(seen_through)
    if occlusion_aware:
        c = torch.where(seen_any, cost, torch.full_like(cost, float("inf"))).amin(0)
    else:
        c = (cost * seen_any).sum(0) / seen_any.sum(0).clamp_min(1)
    return torch.where(seen_any.any(0), c, torch.full_like(c, flat))


def plane_sweep_weights(
    frames: list,
    images: torch.Tensor,
    ref: int,
    height: int,
    width: int,
    cfg: SweepConfig,
) -> torch.Tensor:
    """Per-texel probability that each plane of MPI ``ref`` holds the visible surface.

    The cost of a plane at a texel compares the reference photo with another view warped onto
    the plane: with ``cfg.cost="ad"`` the mean absolute colour difference; with ``"ad_census"``
    that difference and the census distance (:func:`census_distance`), each mapped to [0, 1) by
    ``1 - exp(-c / scale)`` and summed (AD-Census, Mei et al. 2011: the census term ranks
    brightness within a patch, so it holds under the exposure and vignetting differences of real
    photos; the colour term separates patches of the same texture but different colour). It is
    averaged over a ``cfg.window`` x ``cfg.window`` neighbourhood: uniformly, or with
    ``cfg.edge_sigma`` > 0 weighted by ``exp(-|I(x) - I(y)| / edge_sigma)`` (mean absolute colour
    difference of the reference photo between the texel and its neighbour), so that the costs of
    a background do not leak across an object's outline (foreground fattening). The views' costs
    are averaged, or with ``cfg.occlusion_aware`` the lowest is taken (a surface hidden from one
    view by an occluder still matches in another). Texels no other view sees get a flat cost,
    that of a random match. ``cfg.smoothness`` (P1, P2) aggregates the window-averaged cost
    semi-globally (:func:`semi_global`) before the softmin at ``cfg.temperature``.

    Texels of the margin (outside the reference image) hold no reference colour, only the
    edge-extended photo, so their costs match streaks by chance (near-plane smears wherever a
    target looks past an input's border). With ``cfg.extend_border`` they take the
    probabilities of the nearest texel inside the image instead: the border's geometry
    continues outwards, as its colour does.

    Args:
        frames: the MPIFrames of all views; images: [N, 3, H, W] in [0, 1].
        height, width: texel grid over the plane extent.
        cfg: the sweep's settings. ``cfg.supersample`` runs it on a grid that many times finer
            in each direction (as far as :func:`affordable_supersample` allows under
            ``cfg.max_texels``; the window scaled with it) and averages the probabilities back
            over each texel: a texel straddling a depth edge then holds both surfaces in
            proportion, and thin structures (fern's leaflets, 1-2 pixels wide) are matched at
            the photo's resolution.
    Returns:
        [D, height, width] probabilities summing to 1 over planes.
    """
    if cfg.supersample < 1:
        raise ValueError(f"plane-sweep supersample must be a whole number >= 1, got {cfg.supersample}")
    factor = affordable_supersample(height, width, cfg.supersample, cfg.max_texels)
    if factor > 1:
        # The sweep on a grid ``factor`` times finer, with the same window footprint (rounded
        # down to an odd size); the probabilities are averaged back over each texel.
        fine_window = cfg.window * factor - (cfg.window * factor + 1) % 2
        fine_cfg = replace(cfg, window=fine_window, supersample=1)
        fine = plane_sweep_weights(frames, images, ref, height * factor, width * factor, fine_cfg)
        return F.avg_pool2d(fine[None], factor)[0]
    fr = frames[ref]
    uv_ref = texel_pixels(fr, height, width)  # [T, 2]
    ref_rgb, _ = sample_image(images[ref], uv_ref)
    if cfg.cost not in ("ad", "ad_census"):
        raise ValueError(f"unknown plane-sweep cost {cfg.cost!r}; choose 'ad' or 'ad_census'")
    ref_grid = ref_rgb.T.reshape(3, height, width)
    costs, seen = [], []
    for j, other in enumerate(frames):
        if j != ref:
            view_cost, view_seen = _texel_cost(fr, other, images[j], ref_grid, uv_ref, cfg.cost)
            costs.append(view_cost)
            seen.append(view_seen)
    weights = _window_weights(ref_grid, cfg.window, cfg.edge_sigma or None)
    c = _combined_window_cost(weights, cfg.window, costs, seen, cfg.occlusion_aware, cfg.cost)
    if cfg.smoothness[1] > 0:
        c = semi_global(c, *cfg.smoothness)
    probs = torch.softmax(-c / cfg.temperature, dim=0)
    if cfg.extend_border:
        uv = uv_ref.reshape(height, width, 2)
        rows = _nearest_inside(uv[:, 0, 1], fr.height)  # texel rows whose v lies in [0, H]
        cols = _nearest_inside(uv[0, :, 0], fr.width)
        probs = probs[:, rows][:, :, cols]
    return probs


# Scales of the two terms of the "ad_census" cost (mean absolute colour difference in [0, 1]; share
# of census bits that differ). Chosen on the plane sweep alone (share of texels whose best plane
# lies within one plane of the known depth, bench/DIAGNOSIS.md), on the synthetic scenes and
# fern's SfM points together.
AD_SCALE = 0.05
CENSUS_SCALE = 0.3
CENSUS_RADIUS = 3


def affordable_supersample(height: int, width: int, supersample: int, max_texels: int) -> int:
    """The largest factor <= ``supersample`` (at least 1) whose sweep grid of ``height *
    factor`` x ``width * factor`` texels holds at most ``max_texels``. The sweep's time and memory
    grow with its texels times planes (fern at 504x378: 14 s and 1.6 GB per MPI on the 2x grid,
    0.7 s and 0.7 GB on alpha's own grid), so larger photos sweep on a coarser grid relative to
    alpha, which is itself already finer in pixels."""
    factor = max(1, supersample)
    while factor > 1 and height * factor * width * factor > max_texels:
        factor -= 1
    return factor


def census_distance(ref: torch.Tensor, warped: torch.Tensor, radius: int = CENSUS_RADIUS) -> torch.Tensor:
    """Census distance between a reference image [3, h, w] and warped images [D, 3, h, w]: the
    share of the (2 * radius + 1)^2 - 1 neighbours whose brightness (mean of the channels)
    relative to the centre texel differs in sign between the two -> [D, h, w] in [0, 1].
    Borders are replicated. On the CPU a compiled kernel (:mod:`cmc.method.sweep_kernel`) computes it;
    elsewhere :func:`census_distance_torch`, its twin."""
    if ref.device.type == "cpu" and ref.dtype == torch.float32:
        from cmc.method import sweep_kernel

        return sweep_kernel.census_distance(ref.mean(0), warped.mean(1), radius)
    return census_distance_torch(ref, warped, radius)


def census_distance_torch(ref: torch.Tensor, warped: torch.Tensor, radius: int = CENSUS_RADIUS) -> torch.Tensor:
    """:func:`census_distance` as torch ops (any device)."""
    h, w = ref.shape[-2:]
    g_ref, g_w = ref.mean(0, keepdim=True)[None], warped.mean(1, keepdim=True)
    p_ref = F.pad(g_ref, (radius,) * 4, mode="replicate")
    p_w = F.pad(g_w, (radius,) * 4, mode="replicate")
    total = torch.zeros(warped.shape[0], h, w, dtype=warped.dtype, device=warped.device)
    n = 0
    for dy in range(2 * radius + 1):
        for dx in range(2 * radius + 1):
            if dy == radius and dx == radius:
                continue
            bit_ref = p_ref[..., dy : dy + h, dx : dx + w] > g_ref
            bit_w = p_w[..., dy : dy + h, dx : dx + w] > g_w
            total += (bit_ref != bit_w)[:, 0]
            n += 1
    return total / n


def _nearest_inside(coords: torch.Tensor, size: int) -> torch.Tensor:
    """For texel centre coordinates [n] (pixels, increasing), the index of the nearest texel whose
    centre lies inside [0, size] (itself when inside)."""
    inside = ((coords >= 0) & (coords <= size)).nonzero()[:, 0]
    if len(inside) == 0:
        return torch.arange(len(coords), device=coords.device)
    return torch.arange(len(coords), device=coords.device).clamp(int(inside[0]), int(inside[-1]))


def _window_weights(guide: torch.Tensor, window: int, edge_sigma: float | None) -> torch.Tensor | None:
    """The weights [h, w, window^2] (offsets row by row) of the edge-aware window at each texel of
    ``guide`` [3, h, w]: ``exp(-mean_c |guide(x) - guide(y)| / edge_sigma)``, 0 for texels outside
    the grid, normalised over the window. None without ``edge_sigma`` (a uniform window)."""
    if edge_sigma is None:
        return None
    r = window // 2
    h, w = guide.shape[-2:]
    padded = F.pad(guide, (r, r, r, r))
    inside = F.pad(torch.ones(1, h, w, device=guide.device), (r, r, r, r))
    weights = []
    for dy in range(window):
        for dx in range(window):
            diff = (padded[:, dy : dy + h, dx : dx + w] - guide).abs().mean(0)
            weights.append(torch.exp(-diff / edge_sigma) * inside[0, dy : dy + h, dx : dx + w])
    total = sum(weights)
    return torch.stack([wt / total for wt in weights], -1)


def _window_sum(weights: torch.Tensor | None, window: int):
    """A function [C, h, w] -> [C, h, w]: a weighted sum over each texel's window, texels outside
    the grid counting as zero, with the weights of :func:`_window_weights` (None: uniform, 1 /
    window^2). Callers divide two such sums (costs by coverage), so only the relative weights
    matter."""
    r = window // 2
    if weights is None:
        return lambda x: F.avg_pool2d(x[:, None], window, stride=1, padding=r)[:, 0]
    h, w = weights.shape[:2]
    offsets = [(dy, dx) for dy in range(window) for dx in range(window)]

    def apply(x: torch.Tensor) -> torch.Tensor:
        xp = F.pad(x, (r, r, r, r))
        return sum(weights[..., k] * xp[:, dy : dy + h, dx : dx + w] for k, (dy, dx) in enumerate(offsets))

    return apply


def alpha_from_weights(weights: torch.Tensor, lo: float = 0.01, hi: float = 0.99) -> torch.Tensor:
    """Alphas whose front-to-back composite has the given per-plane weights ([D, ...])."""
    remaining = 1 - torch.cumsum(weights, 0) + weights  # transmittance before each plane
    return (weights / remaining.clamp_min(1e-6)).clamp(lo, hi)


def semi_global(cost: torch.Tensor, p1: float, p2: float) -> torch.Tensor:
    """:func:`semi_global_torch`; on the CPU a compiled kernel (:mod:`cmc.method.sweep_kernel`)."""
    if cost.device.type == "cpu" and cost.dtype == torch.float32:
        from cmc.method import sweep_kernel

        return sweep_kernel.semi_global(cost, p1, p2)
    return semi_global_torch(cost, p1, p2)


def semi_global_torch(cost: torch.Tensor, p1: float, p2: float) -> torch.Tensor:
    """Semi-global aggregation (Hirschmüller 2008) of a plane-sweep cost [D, h, w] along the four
    axis directions -> [D, h, w], the mean of the four path costs.

    Along each path a texel's cost of plane d adds the cheapest way to reach it from the previous
    texel: the same plane, a neighbouring plane (+ ``p1``) or any plane (+ ``p2``), less the
    previous texel's minimum (so the sums stay bounded). Surfaces are piecewise smooth in depth,
    so a texel whose own cost is ambiguous (untextured, or seen by one view) takes the plane its
    neighbours along the four lines agree on, while a clear jump still pays only ``p2``."""

    def path(c: torch.Tensor) -> torch.Tensor:  # left to right along the last axis
        out = [c[:, :, 0]]
        wall = torch.full_like(c[:1, :, 0], float("inf"))
        for x in range(1, c.shape[2]):
            prev = out[-1]
            low = prev.amin(0)
            step = torch.minimum(torch.cat([prev[1:], wall]), torch.cat([wall, prev[:-1]])) + p1
            out.append(c[:, :, x] + torch.minimum(torch.minimum(prev, step), (low + p2)[None]) - low)
        return torch.stack(out, 2)

    ct = cost.transpose(1, 2)
    total = path(cost) + path(cost.flip(2)).flip(2)
    total = total + (path(ct) + path(ct.flip(2)).flip(2)).transpose(1, 2)
    return total / 4
