"""The CMC model: one MPI (frame + field) per input view, and novel-view rendering by blending."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from cmc.config import ModelConfig
from cmc.data.datasets import Scene
from cmc.errors import ConfigError
from cmc.geometry.planes import content_plane_depths, mean_baseline, occupied_depth_range, texel_grid
from cmc.method.planesweep import alpha_from_weights, plane_sweep_weights
from cmc.mpi.fields import MLPField, MPIField, PyramidPlaneField, ViewColour, level_size, plane_group_bounds
from cmc.mpi.rendering import ImageOutput, MPIFrame, render_image


def push_pull_fill(color: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """Fill where ``weight`` is 0 with a smooth extrapolation of the known colours.

    Shape: color [C, h, w], weight [1, h, w] in [0, 1] (how much of a texel is known). Known
    texels keep their colour; the rest blend in the next coarser level of a 2x pyramid of
    weighted averages (a coarse texel counts as known once it covers one known texel), so the
    fill is the nearby colour, blurrier the farther it lies from what is known.
    """
    h, w = color.shape[-2:]
    if min(h, w) <= 2:
        mean = (color * weight).sum((1, 2), keepdim=True) / weight.sum().clamp_min(1e-8)
        return weight * color + (1 - weight) * mean
    pooled_w = F.avg_pool2d(weight[None], 2, ceil_mode=True)[0]
    pooled_c = F.avg_pool2d((color * weight)[None], 2, ceil_mode=True)[0] / pooled_w.clamp_min(1e-8)
    coarse = push_pull_fill(pooled_c, (4 * pooled_w).clamp(max=1))
    coarse = F.interpolate(coarse[None], size=(h, w), mode="bilinear", align_corners=False)[0]
    return weight * color + (1 - weight) * coarse


def hidden_layer_colours(rgb: torch.Tensor, front: torch.Tensor, num_planes: int, groups: int) -> torch.Tensor:
    """Initial base colour of each group of planes: the reference colour ``rgb`` [3, h, w] where
    the visible surface (plane index ``front`` [h0, w0], 0 = nearest, any size; ``num_planes``
    where the photo's colour should stay on every plane) lies in or behind the group, and a
    push-pull fill from those texels where a nearer surface hides the group (the background
    continued behind an occluder, not the occluder's colour). Returns [G, 3, h, w], the groups of
    :func:`cmc.mpi.fields.plane_group_bounds`."""
    front = F.interpolate(front[None, None].float(), size=rgb.shape[-2:], mode="nearest")[0]
    starts = plane_group_bounds(num_planes, groups)[:-1]
    return torch.stack([push_pull_fill(rgb, (front >= k0).float()) for k0 in starts])


def padded_reference(image: np.ndarray, frame: MPIFrame) -> torch.Tensor:
    """[3, h, w] the reference photo resampled onto the plane extent, edge-extended into the
    margin (the initial colour of a pyramid field), on the frame's device."""
    dev = frame.K.device
    img = torch.as_tensor(image, dtype=torch.float32, device=dev).permute(2, 0, 1)[None]
    h, w = frame.extent
    grid = texel_grid(h, w, dev)[None] * torch.tensor(frame.margin, device=dev)  # plane grid -> image grid coordinates
    return F.grid_sample(img, grid, align_corners=False, padding_mode="border")[0]


def sweep_probabilities(
    frames: list[MPIFrame], images: torch.Tensor, ref: int, cfg: ModelConfig, supersample: bool = True
) -> torch.Tensor:
    """[D, h, w] the plane sweep of MPI ``ref`` (:func:`plane_sweep_weights`) with ``cfg.sweep``,
    on the grid of the pyramid field's finest alpha level; on the finer grid ``cfg.sweep`` asks
    for (where affordable) unless ``supersample`` is False. images: [N, 3, H, W]."""
    sweep = cfg.sweep if supersample else replace(cfg.sweep, supersample=1)
    h, w = (max(2, round(e * cfg.pyramid.scales[0])) for e in frames[ref].extent)
    return plane_sweep_weights(frames, images, ref, h, w, sweep)


def sweep_statistics(frames: list[MPIFrame], images: torch.Tensor, cfg: ModelConfig) -> tuple[np.ndarray, np.ndarray]:
    """Where the plane sweep finds the scene, on the planes of ``frames`` (the same planes in
    every frame), over the texels inside each reference photo: ``(density, surfaces)``, each [D],
    the mean over views of each view's shares.

    ``density``: the plane-sweep probabilities (:func:`sweep_probabilities`, not supersampled)
    summed per plane: how much of the scene lies at each plane. ``surfaces``: the texels counted
    at their most likely plane, each weighted by how far its peak stands above a flat answer
    (``max p - 1 / D``: a texel the sweep cannot place counts for nothing). images: [N, 3, H, W].
    """
    density, surfaces = [], []
    for i, fr in enumerate(frames):
        probs = sweep_probabilities(frames, images, i, cfg, supersample=False)
        h, w = probs.shape[-2:]
        inside = (texel_grid(h, w, probs.device).abs() <= 1 / torch.tensor(fr.margin, device=probs.device)).all(-1)
        p = probs[:, inside].double()  # [D, T]
        per_plane = p.sum(1)
        peak, best = p.max(0)
        placed = torch.zeros_like(per_plane).index_add_(0, best, (peak - 1.0 / len(p)).clamp_min(0))
        density.append((per_plane / per_plane.sum()).cpu().numpy())
        surfaces.append((placed / placed.sum().clamp_min(1e-12)).cpu().numpy())
    return np.mean(density, 0), np.mean(surfaces, 0)


class ExposureResponse(nn.Module):
    """How each of N input photos renders colour, relative to one shared response: photo v shows
    a colour c (RGB in [0, 1], per channel) as ``exp(log_gain[v]) * c + offset[v]``. Phones set
    exposure and white balance per shot; MPI i holds colours in photo i's response, and
    :meth:`convert` takes them into photo j's before they are compared with photo j, so that the
    difference of the two photos' responses is not explained by geometry. Starts as the identity;
    only differences between views matter (a change shared by all views converts to nothing)."""

    def __init__(self, num_views: int):
        super().__init__()
        self.log_gain = nn.Parameter(torch.zeros(num_views, 3))
        self.offset = nn.Parameter(torch.zeros(num_views, 3))

    def convert(self, rgb: torch.Tensor, src: int, dst: int | None) -> torch.Tensor:
        """Colours [..., 3] in photo ``src``'s response -> photo ``dst``'s (unchanged when equal),
        or with ``dst`` None into the mean of the photos' responses (what renders show)."""
        if src == dst:
            return rgb
        scale, shift = self.affine(src, dst)
        return rgb * scale + shift

    def affine(self, src: int, dst: int | None) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`convert` as ``rgb * scale + shift``: the two [3] per-channel factors."""
        log_gain, offset = (
            (self.log_gain.mean(0), self.offset.mean(0)) if dst is None else (self.log_gain[dst], self.offset[dst])
        )
        scale = torch.exp(log_gain - self.log_gain[src])
        return scale, offset - self.offset[src] * scale


class MeanResponseField(MPIField):
    """MPI ``view``'s field with its colours taken from its photo's response into the mean of
    the input photos' (:meth:`ExposureResponse.convert` with ``dst=None``), clipped to [0, 1]:
    every MPI of a render or a bake then shows one exposure and white balance."""

    def __init__(self, field: MPIField, exposure: ExposureResponse, view: int):
        super().__init__()
        self.field, self.exposure, self.view = field, exposure, view
        self.num_planes, self.colour_interpolation = field.num_planes, field.colour_interpolation

    def forward(self, g: torch.Tensor, plane_z: torch.Tensor, dirs: torch.Tensor, colour_where=None):
        rgb, alpha = self.field(g, plane_z, dirs, colour_where)
        return self.exposure.convert(rgb, self.view, None).clamp(0, 1), alpha

    @torch.no_grad()
    def on_texel_grid(self, g: torch.Tensor, plane_z: torch.Tensor, dirs: torch.Tensor, chunk: int = 1 << 15):
        rgba = self.field.on_texel_grid(g, plane_z, dirs, chunk)
        scale, shift = self.exposure.affine(self.view, None)
        rgb = rgba[:, :3]  # [D, 3, h, w], converted in place
        rgb.mul_(scale[:, None, None]).add_(shift[:, None, None]).clamp_(0, 1)
        return rgba


# A fitted depth range replaces the scene's bounds when its disparity span is below this share of
# theirs (one more plane sweep; the planes would otherwise move by under a tenth of a spacing).
FIT_WORTH = 0.9
# The share of a model build that CMCModel's on_progress gives the sweeps placing the planes (fern:
# 3.1 of 14.4 s, bench/PROFILE.md); each MPI's alpha sweep takes an equal part of the rest.
PLACING_SHARE = 0.25


class CMCModel(nn.Module):
    """Per-view MPIs for the N views of a scene.

    Attributes:
        frames: N :class:`MPIFrame` (reference camera and plane depths of each MPI).
        fields: N fields (``nn.ModuleList``).
        exposure: the input photos' colour responses (:class:`ExposureResponse`), or None;
            renders and bakes show every MPI in their mean (:meth:`display_fields`).
        near, far: the plane range (scene units) shared by all MPIs: the scene's bounds, or with
            ``fit_depth_range`` the part of them where the plane sweep finds the scene.

    ``on_progress(share)`` is called as the build goes (plane sweeps: seconds to minutes) with the
    share of it done, 0 to 1: a quarter for the sweeps that place the planes, the rest MPI by MPI
    (about the shares of their time on fern, bench/PROFILE.md).
    """

    def __init__(
        self,
        scene: Scene,
        cfg: ModelConfig,
        device: torch.device | str = "cpu",
        on_progress: Callable[[float], None] | None = None,
    ):
        super().__init__()
        # A preset's base colour groups may outnumber the planes of a model set smaller by hand
        # (``model.num_planes=4`` under ``fast``'s 8 groups): then one base per plane.
        groups = min(cfg.pyramid.base_groups, cfg.num_planes)
        cfg = replace(cfg, pyramid=replace(cfg.pyramid, base_groups=groups))
        self.cfg = cfg
        self.near, self.far = scene.near, scene.far
        cams = scene.cameras
        self.width, self.height = cams.width, cams.height
        images = torch.as_tensor(scene.images, device=device).permute(0, 3, 1, 2)

        def frames(depths: np.ndarray | None = None) -> list[MPIFrame]:
            return [
                MPIFrame.create(
                    cams.K[i],
                    cams.world_from_cam[i],
                    self.near,
                    self.far,
                    cfg.num_planes,
                    cams.width,
                    cams.height,
                    cfg.margin,
                    device,
                    depths,
                )
                for i in range(len(scene))
            ]

        self.frames = frames()
        if not 0 < cfg.plane_density_floor <= 1:
            raise ConfigError(f"model.plane_density_floor must be in (0, 1], got {cfg.plane_density_floor}")
        if cfg.plane_density_floor < 1:
            density, surfaces = sweep_statistics(self.frames, images, cfg)
            if cfg.fit_depth_range:
                near, far = occupied_depth_range(self.near, self.far, surfaces)
                if 1 / near - 1 / far < FIT_WORTH * (1 / self.near - 1 / self.far):  # else the planes barely move
                    self.near, self.far = near, far
                    self.frames = frames()
                    density, _ = sweep_statistics(self.frames, images, cfg)
            self.frames = frames(content_plane_depths(self.near, self.far, density, cfg.plane_density_floor))
        report = on_progress or (lambda share: None)
        report(PLACING_SHARE)
        fields: list[MPIField] = []
        # A typical parallax between the inputs (ViewColour's unit of ray slope).
        slope_scale = mean_baseline(cams.world_from_cam[:, :3, 3]) * (1 / self.near + 1 / self.far) / 2
        for i, fr in enumerate(self.frames):
            if cfg.field_type == "mlp":
                fields.append(MLPField(cfg.num_planes, cfg.mlp))
            elif cfg.field_type == "pyramid":
                photo = padded_reference(scene.images[i], fr)
                init_alpha, rgb = None, photo
                if cfg.pyramid.init_from_sweep:
                    probs = sweep_probabilities(self.frames, images, i, cfg)
                    init_alpha = alpha_from_weights(probs)
                    if cfg.pyramid.hidden_colour_everywhere:
                        rgb = hidden_layer_colours(rgb, probs.argmax(0), cfg.num_planes, cfg.pyramid.base_groups)
                view_colour = None
                if cfg.pyramid.view_colour_scale > 0:
                    size = level_size(*fr.extent, cfg.pyramid.view_colour_scale)
                    view_colour = ViewColour(cfg.pyramid.base_groups, size, fr.grid_from_camera(), slope_scale, photo)
                fields.append(PyramidPlaneField(cfg.num_planes, *fr.extent, cfg.pyramid, rgb, init_alpha, view_colour))
            else:
                raise ValueError(f"unknown field type {cfg.field_type!r}")
            report(PLACING_SHARE + (1 - PLACING_SHARE) * (i + 1) / len(self.frames))
        self.fields = nn.ModuleList(fields).to(device)
        self.exposure = ExposureResponse(len(scene)).to(device) if cfg.exposure_compensation else None

    def render(
        self,
        K: np.ndarray,
        world_from_cam: np.ndarray,
        width: int,
        height: int,
        mpi_index: int | None = None,
        min_weight: float = 0.0,
    ) -> ImageOutput:
        """Render colour and depth for any camera (see :func:`cmc.mpi.rendering.render_image`), every
        MPI in the mean of the photos' colour responses (:meth:`display_fields`)."""
        return render_image(
            self.display_fields(), self.frames, K, world_from_cam, width, height, mpi_index, min_weight=min_weight
        )  # type: ignore[arg-type]

    def display_fields(self) -> list[MPIField]:
        """The fields as renders and bakes show them: as trained, or, with exposure compensation,
        each in the mean of the photos' colour responses (:class:`MeanResponseField`)."""
        fields: list[MPIField] = list(self.fields)  # type: ignore[arg-type]
        if self.exposure is None:
            return fields
        return [MeanResponseField(f, self.exposure, i) for i, f in enumerate(fields)]
