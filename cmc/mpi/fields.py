"""Per-view MPI fields: what one multiplane image holds at a point of one of its planes.

A field answers, for rays that cross all D planes of its MPI, the colour and alpha at each
crossing. Crossings are given in *plane grid coordinates* ``g`` in [-1, 1]^2 (x right, y down),
the ``grid_sample(align_corners=False)`` convention: g = (-1, -1) is the top-left corner of the
plane's extent, which is the reference image enlarged by the MPI's margin (see
:class:`cmc.mpi.rendering.MPIFrame`). Points outside [-1, 1] are masked by the renderer.

Fields:
* :class:`MLPField` -- the paper's: an MLP over (positional encoding of (g, plane coordinate),
  raw ray direction) -> (rgb, alpha).
* :class:`PyramidPlaneField` -- the ``fast`` preset: explicit textures. Colour is a full-resolution
  base image shared by a group of adjacent planes (initialised to the reference photo) plus a
  per-plane multi-resolution residual; alpha is a per-plane multi-resolution grid. Each pyramid
  is folded onto its finest grid (every coarser level resampled bilinearly onto the next finer
  one and added, :func:`cmc.mpi.plane_sampling.fold_levels`) and that one texture is sampled:
  coarse levels learn first and act as a smoothness prior, and a sample costs one texture's
  taps, not one per level. With one base for all planes, a surface hidden behind a nearer one in the
  reference photo would have that nearer surface's fine texture wherever another view sees it;
  a base per group of planes gives it its own. While training, a :class:`ViewColour` may add to
  the colour what changes with the direction of the ray (the other photos' reflections on smooth
  surfaces); bakes hold the reference camera's colours.
* :class:`TextureField` -- fixed RGBA textures, the form a baked MPI takes.

All fields keep the farthest plane opaque (alpha = 1) so that every covered ray is fully
composited.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import nn

from cmc.config import MLPFieldConfig, PyramidFieldConfig
from cmc.errors import ConfigError
from cmc.mpi import plane_sampling


class MPIField(nn.Module):
    """Base class. ``forward(g, plane_z, dirs, colour_where=None) -> (rgb, alpha)``.

    Shape:
        g: [R, D, 2] plane grid coordinates; plane_z: [D] plane coordinate in [-1, 1]
        (normalised disparity, -1 = nearest); dirs: [R, 3] unit ray directions in the
        reference camera's frame. Returns rgb [R, D, 3] in [0, 1] and alpha [R, D] in [0, 1].

    ``colour_where``, if given, maps the alpha [R, D] to the samples whose colour the caller
    uses ([R, D] bool); elsewhere a field may return 0.5 without computing the colour (the
    pyramid field does; the others compute every colour).
    """

    num_planes: int
    # How a bake of this field is to sample its colours between texels (cmc.serving.baking records it):
    # "bilinear", or "bicubic" where the field itself samples its colours that way.
    colour_interpolation: str = "bilinear"

    def on_texel_grid(self, g: torch.Tensor, plane_z: torch.Tensor, dirs: torch.Tensor, chunk: int = 1 << 15):
        """The field at every texel of a grid, for a bake: [D, 4, h, w] straight RGBA in [0, 1].

        Shape: g [h, w, 2] texel centres (:func:`cmc.geometry.planes.texel_grid`), the same on
        every plane; plane_z [D]; dirs [h * w, 3] unit directions each texel is seen along. Here
        ``forward`` at ``chunk`` texels at a time; fields that ignore the direction do it in one go.
        """
        h, w, _ = g.shape
        flat, D = g.reshape(-1, 2), len(plane_z)
        parts = []
        for s in range(0, len(flat), chunk):
            rgb, alpha = self(flat[s : s + chunk, None].expand(-1, D, 2), plane_z, dirs[s : s + chunk])
            parts.append(torch.cat([rgb, alpha[..., None]], -1))  # [R, D, 4]
        return torch.cat(parts).reshape(h, w, D, 4).permute(2, 3, 0, 1).contiguous()


def _opaque_back(alpha: torch.Tensor) -> torch.Tensor:
    """Force the last plane (dim -1) to alpha 1 without in-place writes (autograd-safe)."""
    last = torch.zeros_like(alpha)
    last[..., -1] = 1.0
    return torch.maximum(alpha, last)


def positional_encoding(x: torch.Tensor, num_freqs: int) -> torch.Tensor:
    """Paper Eq. 4.4: [..., C] -> [..., 2 * C * num_freqs], (sin(2^k x), cos(2^k x)) per k."""
    freqs = 2.0 ** torch.arange(num_freqs, device=x.device, dtype=x.dtype)
    xf = x[..., None, :] * freqs[:, None]  # [..., L, C]
    return torch.cat([torch.sin(xf), torch.cos(xf)], dim=-1).flatten(-2)


class MLPField(MPIField):
    """F_i(gamma(x), d) -> (rgb, alpha) with x = (g_x, g_y, plane_z) and d the raw direction."""

    def __init__(self, num_planes: int, cfg: MLPFieldConfig):
        super().__init__()
        self.num_planes = num_planes
        self.cfg = cfg
        in_dim = 3 * 2 * cfg.pe_freqs + 3
        layers: list[nn.Module] = []
        for k in range(cfg.depth):
            layers += [nn.Linear(in_dim if k == 0 else cfg.width, cfg.width), nn.LeakyReLU(cfg.leaky_slope)]
        layers.append(nn.Linear(cfg.width, 4))
        self.mlp = nn.Sequential(*layers)

    def forward(self, g: torch.Tensor, plane_z: torch.Tensor, dirs: torch.Tensor, colour_where=None):
        R, D, _ = g.shape
        x = torch.cat([g, plane_z[None, :, None].expand(R, D, 1)], dim=-1)
        feats = torch.cat([positional_encoding(x, self.cfg.pe_freqs), dirs[:, None].expand(R, D, 3)], dim=-1)
        out = self.mlp(feats)
        return torch.sigmoid(out[..., :3]), _opaque_back(torch.sigmoid(out[..., 3]))


def plane_group_bounds(num_planes: int, groups: int) -> list[int]:
    """First plane of each of ``groups`` groups of adjacent planes, then ``num_planes``: group i
    holds planes [ceil(i D / G), ceil((i + 1) D / G)), so plane k is in group k * G // D."""
    return [-(-i * num_planes // groups) for i in range(groups + 1)]


def plane_groups(bounds: list[int]) -> list[int]:
    """The group of each plane, from the groups' bounds (:func:`plane_group_bounds`)."""
    return [i for i in range(len(bounds) - 1) for _ in range(bounds[i], bounds[i + 1])]


def level_size(height: int, width: int, scale: float) -> tuple[int, int]:
    """(h, w) of a texture at ``scale`` of a height x width plane extent (at least 2 x 2)."""
    return max(2, round(height * scale)), max(2, round(width * scale))


def _grid_sample_groups(texture: torch.Tensor, grid: torch.Tensor, bounds: list[int], mode: str) -> torch.Tensor:
    """Texture i of ``texture`` [G, C, h, w] sampled (``grid_sample``, ``mode``) at the points of
    planes [bounds[i], bounds[i + 1]) of ``grid`` [D, R, 2] -> [D, C, R] (any device)."""
    C = texture.shape[1]
    return torch.cat(
        [
            F.grid_sample(texture[i : i + 1], grid[k0:k1].reshape(1, 1, -1, 2), mode=mode, align_corners=False)
            .reshape(C, k1 - k0, -1)
            .transpose(0, 1)
            for i, (k0, k1) in enumerate(zip(bounds[:-1], bounds[1:], strict=True))
        ]
    )


# The texel-mean gradient (grey levels per pixel) at which :func:`flatness` falls to 1 / e: room's
# walls and glossy table lie below it, most of fern's, trex's and the synthetic set's textures far
# above (their photos' median texels 0.007 against 0.03-0.05; bench/experiments.toml).
FLAT_GRADIENT = 0.01
MASK_FLOOR = 1e-4  # ViewColour's mask below this is 0 (a texel gradient above about 3 FLAT_GRADIENT)


def flatness(photo: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """How untextured ``photo`` [3, H, W] (values in [0, 1]) is around each texel of an [h, w] =
    ``size`` grid, in (0, 1]: exp(-(m / FLAT_GRADIENT)^2), m the mean over the texel of the grey
    image's central-difference gradient magnitude (per pixel); 1 where the photo is flat. Returns [h, w]."""
    grey = photo.mean(0)
    grad = torch.zeros_like(grey)
    gx = (grey[1:-1, 2:] - grey[1:-1, :-2]) / 2
    gy = (grey[2:, 1:-1] - grey[:-2, 1:-1]) / 2
    grad[1:-1, 1:-1] = (gx**2 + gy**2).sqrt()
    m = F.adaptive_avg_pool2d(grad[None, None], size)[0, 0]
    return torch.exp(-((m / FLAT_GRADIENT) ** 2))


class ViewColour(nn.Module):
    """A training-time term of a :class:`PyramidPlaneField`'s colour: how much a group's colour
    logits change with the direction a ray crosses a plane.

    At a plane sample, ``delta`` [2] is the target ray's slope (x / z, y / z in the reference
    camera's frame) minus the slope of the reference camera's ray through the same point, in
    units of ``slope_scale`` (a typical parallax: the inputs' mean baseline over a typical scene
    depth), clamped to [-2, 2]; it is 0 for every ray of the reference photo (below
    :data:`cmc.mpi.plane_sampling.DELTA_FLOOR` on both axes: rounding), and for a direction that
    does not point into the planes (z <= 0: e.g. the zero vector, for no direction). The colour
    logits gain ``A(g) @ delta`` per channel, A a [G, 3 x 2, h, w] texture per group of planes
    (bilinear, starting at 0) times :func:`flatness` of the reference photo (0 below
    :data:`MASK_FLOOR`, where the compiled sampler skips the samples), so that the
    other photos' reflections and highlights on smooth surfaces need not be explained by
    geometry, while a textured surface's change with the view, which is what a wrong depth looks
    like, still moves the geometry. Bakes hold the reference camera's colours (delta = 0), and so does every render
    the service makes from them: the term is a nuisance the training explains away, not
    view-dependent appearance to show (``CMCModel.render`` of the trained model still adds it).

    Args:
        groups: G; size: (h, w) of the texture; grid_from_camera: [2, 3] the frame's
        :meth:`cmc.mpi.rendering.MPIFrame.grid_from_camera` (no skew); slope_scale: as above;
        photo: [3, H, W] the reference photo on the plane extent's grid.
    """

    def __init__(
        self,
        groups: int,
        size: tuple[int, int],
        grid_from_camera: torch.Tensor,
        slope_scale: float,
        photo: torch.Tensor,
    ):
        super().__init__()
        self.texture = nn.Parameter(torch.zeros(groups, 6, *size, device=photo.device))
        mask = flatness(photo, size)
        self.register_buffer("mask", torch.where(mask < MASK_FLOOR, 0.0, mask))
        M = grid_from_camera.to(photo.dtype)
        self.register_buffer("focal", torch.stack([M[0, 0], M[1, 1]]))  # grid units per unit slope
        self.register_buffer("centre", M[:, 2].clone())  # grid coordinates of the optical axis
        self.slope_scale = float(slope_scale)

    def logits(self, grid: torch.Tensor, dirs: torch.Tensor, bounds: list[int], where: torch.Tensor | None):
        """Colour logits [D, 3, R] at grid [D, R, 2] for rays along dirs [R, 3] (the groups'
        planes by ``bounds``); with ``where`` ([D, R] bool) only at the samples it marks, 0
        elsewhere."""
        texture = self.texture * self.mask
        if plane_sampling.supported(grid, [texture, dirs]):  # the compiled CPU pass
            groups = plane_groups(bounds)
            args = (self.mask, self.centre, self.focal, self.slope_scale, where)
            return plane_sampling.sample_view_colour(grid, dirs, groups, texture, *args)
        ref_slope = (grid - self.centre) / self.focal  # [D, R, 2]
        ahead = dirs[:, 2:3] > 0  # a ray that meets the planes; not so the zero direction "any view"
        slope = torch.where(ahead, dirs[:, :2] / torch.where(ahead, dirs[:, 2:3], 1.0), ref_slope)
        delta = (slope - ref_slope) / self.slope_scale
        tiny = (delta.abs() < plane_sampling.DELTA_FLOOR).all(-1, keepdim=True)
        delta = torch.where(tiny, 0.0, delta.clamp(-2, 2))
        a = _grid_sample_groups(texture, grid, bounds, "bilinear")
        if where is not None:
            a = torch.where(where[:, None], a, torch.zeros_like(a))
        return a[:, 0::2] * delta[:, None, :, 0] + a[:, 1::2] * delta[:, None, :, 1]


class PyramidPlaneField(MPIField):
    """Explicit per-plane textures; see the module docstring.

    Colour logits of plane k = base[k * G // D](g) + fold(colour)[k](g); alpha logit =
    fold(alpha)[k](g), where base is [G, 3, h, w] (G = ``cfg.base_groups``, one base per
    group of about D / G adjacent planes, sampled as ``cfg.base_interpolation``), colour level l
    is [D, 3, h * s_l, w * s_l] and alpha level l [D, 1, h * s_l, w * s_l], and fold(levels)
    (:func:`cmc.mpi.plane_sampling.fold_levels`) the levels summed on the finest one's grid,
    sampled bilinearly.
    Alpha and colour are apart so that a query reads alpha first and colour only where the
    caller needs it (``forward``'s ``colour_where``).

    Args:
        num_planes: D.
        height, width: plane extent in reference-image pixels (image size times margin).
        cfg: level scales and base groups.
        init_rgb: [3, height, width] initial base colour in [0, 1] (the reference photo, padded),
            or [G, 3, height, width], one per base group.
        init_alpha: optional [D, h0, w0] initial alpha of each plane (any size; resampled to the
            finest level). Without it alpha starts at 1 / (D - k): equal composite weights.
        view_colour: optional :class:`ViewColour` (with ``cfg.base_groups`` groups), added to
            the colour logits of training rays; the texel grid (bakes) leaves it out.
    """

    def __init__(
        self,
        num_planes: int,
        height: int,
        width: int,
        cfg: PyramidFieldConfig,
        init_rgb: torch.Tensor,
        init_alpha: torch.Tensor | None = None,
        view_colour: ViewColour | None = None,
    ):
        super().__init__()
        self.num_planes = num_planes
        self.view_colour = view_colour
        self.cfg = cfg
        self.colour_interpolation = cfg.base_interpolation

        def size(s: float) -> tuple[int, int]:
            return level_size(height, width, s)

        if not 1 <= cfg.base_groups <= num_planes:
            raise ConfigError(f"base_groups must be 1 to num_planes ({num_planes}), got {cfg.base_groups}")
        rgb = init_rgb.float().reshape(-1, *init_rgb.shape[-3:])  # [1 or G, 3, h, w]
        if rgb.shape[-2:] != (height, width):
            raise ValueError(
                f"init_rgb must be on the plane extent's grid {height} x {width}, got {tuple(rgb.shape[-2:])}"
            )
        base = torch.logit(rgb.clamp(0.02, 0.98)).expand(cfg.base_groups, -1, -1, -1)
        self.base = nn.Parameter(base.contiguous())  # [G, 3, h, w]
        # Initial alpha 1 / (D - k), held by the coarsest level: every plane contributes equally.
        k = torch.arange(num_planes, dtype=torch.float32, device=rgb.device)
        alpha0 = torch.logit((1.0 / (num_planes - k)).clamp(max=0.99))
        self.colour_levels = nn.ParameterList()
        self.alpha_levels = nn.ParameterList()
        for n, s in enumerate(cfg.scales):
            alpha = torch.zeros(num_planes, 1, *size(s), device=rgb.device)
            if init_alpha is not None and n == 0:
                a = F.interpolate(init_alpha[:, None].float(), size=size(s), mode="bilinear", align_corners=False)
                alpha[:, 0] = torch.logit(a[:, 0].clamp(0.01, 0.99))
            elif init_alpha is None and n == len(cfg.scales) - 1:
                alpha[:, 0] = alpha0[:, None, None]
            self.alpha_levels.append(nn.Parameter(alpha))
        for s in cfg.colour_scales:
            self.colour_levels.append(nn.Parameter(torch.zeros(num_planes, 3, *size(s), device=rgb.device)))

    def forward(
        self,
        g: torch.Tensor,
        plane_z: torch.Tensor,
        dirs: torch.Tensor,
        colour_where: Callable[[torch.Tensor], torch.Tensor] | None = None,
    ):
        grid = g.transpose(0, 1)  # [D, R, 2], the samplers' layout
        alpha = _opaque_back(torch.sigmoid(self._alpha_logits(grid).T))
        where = None if colour_where is None else colour_where(alpha).T.contiguous()  # once for every sampler
        logits = self._colour_logits(grid, where)
        if self.view_colour is not None:
            logits = logits + self.view_colour.logits(grid, dirs, plane_group_bounds(len(grid), len(self.base)), where)
        return torch.sigmoid(logits.permute(2, 0, 1)), alpha

    @torch.no_grad()
    def on_texel_grid(self, g: torch.Tensor, plane_z: torch.Tensor, dirs: torch.Tensor, chunk: int = 0):
        """:meth:`MPIField.on_texel_grid` without the directions (the reference camera's colours:
        no :class:`ViewColour`): every texel at once, in the layout the samplers return (no
        reordering of the D x h x w samples)."""
        h, w, _ = g.shape
        grid = g.reshape(1, -1, 2).expand(len(plane_z), -1, 2).contiguous()
        alpha = self._alpha_logits(grid).sigmoid_()
        alpha[-1] = 1.0  # the back plane opaque
        colour = self._colour_logits(grid, None, same_points=True)
        return torch.cat([colour.sigmoid_(), alpha[:, None]], 1).reshape(-1, 4, h, w)

    def _alpha_logits(self, grid: torch.Tensor) -> torch.Tensor:
        """Alpha logits [D, R] at grid [D, R, 2]."""
        alpha = plane_sampling.fold_levels(list(self.alpha_levels))
        if plane_sampling.supported(grid, [alpha]):  # the compiled CPU sampler
            return plane_sampling.sample_planes(grid, range(len(grid)), [alpha])[:, 0]
        return F.grid_sample(alpha, grid[:, None], align_corners=False)[:, 0, 0]

    def _colour_logits(self, grid: torch.Tensor, where: torch.Tensor | None, same_points: bool = False) -> torch.Tensor:
        """Colour logits [D, 3, R] (base plus levels) at grid [D, R, 2]; with ``where`` ([D, R]
        bool) only at the samples it marks, 0 elsewhere (those not sampled, without gradient).
        ``same_points``: every plane's row of ``grid`` is the same (a texel grid), so on the CPU
        each group's base colour is sampled once for all its planes (the same values)."""
        D, G = grid.shape[0], len(self.base)
        bounds = plane_group_bounds(D, G)  # plane k takes base k * G // D
        residual = plane_sampling.fold_levels(list(self.colour_levels)) if self.colour_levels else None
        if plane_sampling.supported(grid, self.parameters()):  # the compiled CPU sampler
            groups = plane_groups(bounds)
            if same_points and where is None:
                base = plane_sampling.sample_planes(grid[:G], range(G), [self.base], self.cfg.base_interpolation)
                base = base[groups]
            else:
                base = plane_sampling.sample_planes(grid, groups, [self.base], self.cfg.base_interpolation, where=where)
            if residual is None:
                return base
            return base + plane_sampling.sample_planes(grid, range(D), [residual], where=where)
        logits = self._colour_torch(grid, bounds, residual)
        return logits if where is None else torch.where(where[:, None], logits, torch.zeros_like(logits))

    def _colour_torch(self, grid: torch.Tensor, bounds: list[int], residual: torch.Tensor | None) -> torch.Tensor:
        """:meth:`_colour_logits` at every sample with ``grid_sample`` (any device;
        :mod:`cmc.mpi.plane_sampling` computes the same on the CPU); ``residual`` the folded
        colour levels [D, 3, h, w], or None."""
        base = _grid_sample_groups(self.base, grid, bounds, self.cfg.base_interpolation)
        if residual is None:
            return base
        return base + F.grid_sample(residual, grid[:, None], align_corners=False).squeeze(2)


class TextureField(MPIField):
    """Fixed RGBA plane textures [D, 4, h, w] (straight alpha), e.g. a baked MPI.

    Alpha is sampled bilinearly; colour bilinearly too (zero outside), or with
    ``colour_interpolation="bicubic"`` by Keys' cubic kernel with the edge texels repeated,
    clamped to [0, 1] (as :func:`cmc.serving.texture_kernel.render` does).
    """

    def __init__(self, rgba: torch.Tensor, colour_interpolation: str = "bilinear"):
        super().__init__()
        plane_sampling.check_interpolation(colour_interpolation, "colour_interpolation")
        self.num_planes = rgba.shape[0]
        self.colour_interpolation = colour_interpolation
        self.register_buffer("rgba", rgba)
        # Premultiplied copy, back plane opaque, for whole-image rendering (render_texture_image).
        alpha = _opaque_back(rgba[:, 3].transpose(0, -1)).transpose(0, -1)[:, None]
        self.register_buffer("premultiplied", torch.cat([rgba[:, :3] * alpha, alpha], 1))

    def forward(self, g: torch.Tensor, plane_z: torch.Tensor, dirs: torch.Tensor, colour_where=None):
        grid = g.permute(1, 0, 2)[:, None]
        if self.colour_interpolation == "bicubic":  # colour bicubic, alpha alone bilinear
            rgb = sample_colour_bicubic(self.rgba[:, :3], grid)[:, :, 0].permute(2, 0, 1)
            alpha = F.grid_sample(self.rgba[:, 3:], grid, align_corners=False)[:, 0, 0].T  # [R, D]
            return rgb, _opaque_back(alpha)
        s = F.grid_sample(self.rgba, grid, align_corners=False)[:, :, 0].permute(2, 0, 1)  # [R, D, 4]
        return s[..., :3], _opaque_back(s[..., 3])


def sample_colour_bicubic(rgb: torch.Tensor, grid: torch.Tensor) -> torch.Tensor:
    """Straight colours [N, 3, h, w] in [0, 1] sampled at ``grid_sample`` grid [N, H, W, 2] with
    Keys' cubic kernel, edge texels repeated, clamped to [0, 1] -> [N, 3, H, W]."""
    return F.grid_sample(rgb, grid, mode="bicubic", padding_mode="border", align_corners=False).clamp(0, 1)
