"""Rendering rays and images from per-view MPIs: homography warps and alpha compositing.

Conventions: :mod:`cmc.geometry.cameras`. A target ray is identified by its target camera and a
continuous pixel coordinate ``uv``. Its crossing with plane k of MPI i is found with the
plane-induced homography (paper Eq. 4.1-4.2), the field is queried there, and the D samples
are composited front to back (Eq. 3.4 colour, Eq. 3.5 depth).

Depth: Eq. 3.5 composites the reference camera's plane depths z_k. Those are only comparable
between MPIs whose cameras are parallel, so we composite the *target camera's* depth of each
plane crossing instead (identical to z_k when the target is the reference camera). Depth is
therefore always target-camera z in scene units, for every MPI.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from cmc.geometry.cameras import pixel_rays
from cmc.geometry.planes import (
    ArrayT,
    blend_weights,
    mean_baseline,
    pixel_centers,
    plane_depths,
)
from cmc.mpi import composite_kernel
from cmc.mpi.fields import MPIField, TextureField, sample_colour_bicubic

# Where a render samples colour bicubically (``straight_rgb`` below, the CPU kernel of
# cmc.serving.texture_kernel), a sample weighing less than this in its pixel (transmittance times
# alpha) takes the bilinear premultiplied colour of its four texels instead: that moves the pixel
# by at most the sample's weight times the two colours' difference, and a render of fern takes
# 30 % less time (most samples with any alpha weigh under 1 %, and every sample bicubic made the
# render 2.4 times as long as none; bench/PROFILE.md).
BICUBIC_MIN_WEIGHT = 0.01


@dataclass(frozen=True)
class MPIFrame:
    """Where one MPI lives: its reference camera and planes.

    Attributes:
        K: [3, 3] reference intrinsics (pixels); world_from_ref: [4, 4] (OpenCV axes).
        depths: [D] plane depths in the reference camera, nearest first (uniform in disparity,
            or crowded where the scene's surfaces are: :func:`cmc.geometry.planes.content_plane_depths`).
        width, height: reference image size in pixels.
        margin: (x, y) the planes extend ``margin`` times the image's width and height about
            its centre, so that target views looking past the reference image's border still see
            plane content. :meth:`create` makes each a whole number of pixels on both sides, so
            the full-resolution texel grid has its texel centres on the photo's pixel centres.
    """

    K: torch.Tensor
    world_from_ref: torch.Tensor
    depths: torch.Tensor
    width: int
    height: int
    margin: tuple[float, float]

    @staticmethod
    def create(
        K: np.ndarray,
        world_from_ref: np.ndarray,
        near: float,
        far: float,
        num_planes: int,
        width: int,
        height: int,
        margin: float,
        device: torch.device | str = "cpu",
        depths: np.ndarray | None = None,
    ) -> MPIFrame:
        """``depths`` [num_planes], nearest first, from ``near`` to ``far``: the planes (default
        uniform in disparity, :func:`cmc.geometry.planes.plane_depths`); ``margin``: the plane
        extent about ``margin`` times the image's size (:func:`pixel_aligned_margin`)."""
        d = plane_depths(near, far, num_planes) if depths is None else np.asarray(depths)
        if len(d) != num_planes:
            raise ValueError(f"{len(d)} plane depths given for {num_planes} planes")
        t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32, device=device)  # noqa: E731
        return MPIFrame(t(K), t(world_from_ref), t(d), width, height, pixel_aligned_margin(width, height, margin))

    @property
    def ref_from_world(self) -> torch.Tensor:
        return torch.linalg.inv(self.world_from_ref)

    @property
    def plane_z(self) -> torch.Tensor:
        """[D] plane coordinate for fields: disparity mapped linearly to [-1 (near), 1 (far)]."""
        disp = 1.0 / self.depths
        return (disp[0] - disp) / (disp[0] - disp[-1]) * 2 - 1

    @property
    def extent(self) -> tuple[int, int]:
        """(height, width) of the plane extent in reference pixels (image size times margin)."""
        return round(self.height * self.margin[1]), round(self.width * self.margin[0])

    def grid_from_pixels(self, uv: torch.Tensor) -> torch.Tensor:
        """Reference pixel coordinates [..., 2] -> plane grid coordinates in [-1, 1] inside."""
        size = uv.new_tensor([self.width, self.height])
        return (uv / size * 2 - 1) / uv.new_tensor(self.margin)

    def pixels_from_grid(self, g: torch.Tensor) -> torch.Tensor:
        """Inverse of :meth:`grid_from_pixels`."""
        size = g.new_tensor([self.width, self.height])
        return (g * g.new_tensor(self.margin) + 1) / 2 * size

    def grid_from_camera(self, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """[2, 3] M: a point X in reference camera coordinates (or a ray) -> ``M X / X_z``, the
        plane grid coordinates of its projection (:meth:`grid_from_pixels` of ``K X / X_z``)."""
        mx, my = self.margin
        G = [[2 / (self.width * mx), 0, -1 / mx], [0, 2 / (self.height * my), -1 / my]]
        return torch.tensor(G, dtype=dtype, device=self.K.device) @ self.K.to(dtype)


def pixel_aligned_margin(width: int, height: int, margin: float) -> tuple[float, float]:
    """(x, y) margins closest to ``margin`` that add a whole number of pixels on each side of a
    ``width`` x ``height`` image: the plane extent is then (width + 2 px) x (height + 2 py)
    texels at full resolution, and texel c sits on pixel centre c - px + 0.5 exactly (sampling
    the reference view between texels would low-pass its finest detail)."""
    px, py = round(width * (margin - 1) / 2), round(height * (margin - 1) / 2)
    return (width + 2 * px) / width, (height + 2 * py) / height


@dataclass
class RayOutput:
    """Composited result for R rays.

    Attributes:
        rgb: [R, 3] colour in [0, 1]; depth: [R] target-camera depth (scene units, 0 where
        nothing is hit); acc: [R] accumulated alpha, 0 outside the MPI's planes;
        weights: [R, D] the compositing weights of the planes, nearest first (only from
        :func:`composite`, for losses on how a ray's opacity is spread).
    """

    rgb: torch.Tensor
    depth: torch.Tensor
    acc: torch.Tensor
    weights: torch.Tensor | None = None

    def select(self, rays: torch.Tensor) -> RayOutput:
        """The rays of index ``rays`` (any index tensor over R)."""
        weights = None if self.weights is None else self.weights[rays]
        return RayOutput(self.rgb[rays], self.depth[rays], self.acc[rays], weights)


def composite(
    rgb: torch.Tensor,
    alpha: torch.Tensor,
    depth: torch.Tensor,
    colour_grad_min_weight: float = 0.0,
    colour_grad_scale: float | torch.Tensor = 1.0,
) -> RayOutput:
    """Front-to-back alpha compositing (paper Eq. 3.4, 3.5).

    Shape: rgb [R, D, 3] (any number of channels), alpha [R, D], depth [R, D] (per-sample depth),
    nearest plane first. The gradients that reach the colours are multiplied by
    ``colour_grad_scale``, one factor or one per ray ([R]; the rendered values do not depend on
    it); a sample whose weight is below ``colour_grad_min_weight`` passes none to its colour (its
    share of the ray's colour is too small to fit, and the compiled sampler skips the colour
    texels of such samples in the backward pass). On the CPU a compiled kernel
    (:mod:`cmc.mpi.composite_kernel`) computes it; elsewhere (and for depths with a gradient, or
    other than 3 channels) :func:`composite_torch`, its twin.
    """
    if composite_kernel.supported(rgb, alpha, depth):
        return RayOutput(*composite_kernel.composite(rgb, alpha, depth, colour_grad_min_weight, colour_grad_scale))
    return composite_torch(rgb, alpha, depth, colour_grad_min_weight, colour_grad_scale)


def composite_torch(
    rgb: torch.Tensor,
    alpha: torch.Tensor,
    depth: torch.Tensor,
    colour_grad_min_weight: float = 0.0,
    colour_grad_scale: float | torch.Tensor = 1.0,
) -> RayOutput:
    """:func:`composite` as torch ops (any device)."""
    w = _weights_torch(alpha)
    if rgb.requires_grad and (torch.is_tensor(colour_grad_scale) or colour_grad_scale != 1.0):
        scale = torch.as_tensor(colour_grad_scale, dtype=rgb.dtype, device=rgb.device)
        scale = scale[:, None, None] if scale.ndim else scale
        rgb = rgb.detach() + scale * (rgb - rgb.detach())
    if colour_grad_min_weight > 0 and rgb.requires_grad:
        rgb = torch.where((w.detach() >= colour_grad_min_weight)[..., None], rgb, rgb.detach())
    return RayOutput((w[..., None] * rgb).sum(1), (w * depth).sum(1), w.sum(1), w)


def _weights_torch(alpha: torch.Tensor) -> torch.Tensor:
    """Each plane's weight [R, D] in its ray: alpha [R, D] times the transmittance before it."""
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1]], dim=1), dim=1)
    return alpha * trans


def strong_samples(alpha: torch.Tensor, min_weight: float) -> torch.Tensor:
    """[R, D] bool: the samples whose weight in their ray (alpha [R, D], nearest plane first)
    is at least ``min_weight``, computed as :func:`composite` computes it."""
    if alpha.device.type == "cpu" and alpha.dtype == torch.float32:
        return composite_kernel.strong_samples(alpha, min_weight)
    return _weights_torch(alpha) >= min_weight


def render_rays(
    field: MPIField, frame: MPIFrame, K_tgt: torch.Tensor, world_from_tgt: torch.Tensor, uv: torch.Tensor
) -> RayOutput:
    """Render target rays from one MPI.

    Shape: K_tgt [3, 3], world_from_tgt [4, 4], uv [R, 2] target pixel coordinates.
    """
    return render_ray_groups(field, frame, [(K_tgt, world_from_tgt, uv)])[0]


def render_ray_groups(
    field: MPIField,
    frame: MPIFrame,
    groups: Sequence[tuple[torch.Tensor, torch.Tensor, torch.Tensor]],
    color_grad: Sequence[bool | float] | None = None,
    colour_grad_min_weight: float = 0.0,
) -> list[RayOutput]:
    """Render rays of several target cameras from one MPI with a single field query.

    One query instead of one per camera matters for explicit fields, whose backward pass
    touches every texture once per query.

    Args:
        groups: (K_tgt [3, 3], world_from_tgt [4, 4], uv [R_g, 2]) per target camera.
        color_grad: per group, the factor on the gradients that flow to the field's colours
            (default 1 for all; True is 1, False is 0: only alpha, the geometry, receives the
            group's gradients). The rendered values do not depend on it.
        colour_grad_min_weight: samples weighing less in their ray pass no gradient to their
            colour (:func:`composite`), and the field need not compute their colour
            (``MPIField``'s ``colour_where``: such a sample's colour may read 0.5, which moves
            its ray's colour by at most half the faint samples' summed weight). With it, a
            group whose factor is 0 gets no colour computed at all (its colour reads 0.5
            wherever a field honours ``colour_where``).
    Returns:
        one RayOutput per group.
    """
    gs, lams, insides, dirss = [], [], [], []
    z = frame.depths
    M = frame.grid_from_camera(z.dtype)  # [2, 3]
    for K_tgt, world_from_tgt, uv in groups:
        # The ray t + lam * d_ref (reference frame, d_ref with target z = 1) meets plane k at the
        # target depth lam_k = e_k / d_z (e_k = z_k - t_z), at plane grid coordinates
        # g_k = (e_k / z_k) m + M t / z_k with m = M d_ref / d_z: one multiply-add per plane
        # (the plane-induced homography of paper Eq. 4.1-4.2, in affine form).
        ref_from_tgt = frame.ref_from_world @ world_from_tgt
        t = ref_from_tgt[:3, 3]
        d_ref = pixel_rays(K_tgt, uv) @ ref_from_tgt[:3, :3].T  # [R, 3]
        d_z = d_ref[:, 2:3]
        d_z = torch.where(d_z == 0, torch.full_like(d_z, 1e-12), d_z)  # a ray parallel to the planes
        e = z - t[2]  # [D]
        lam = e[None] / d_z  # [R, D]
        m = (d_ref @ M.T) / d_z  # [R, 2]
        g = torch.addcmul((M @ t / z[:, None])[:, None, :], (e / z)[:, None, None], m[None])  # [D, R, 2]
        insides.append((lam > 0) & (g.abs() <= 1).all(-1).T)
        gs.append(g.clamp(-1.5, 1.5))
        lams.append(lam)
        dirss.append(d_ref / d_ref.norm(dim=-1, keepdim=True))
    sizes = [len(lam) for lam in lams]
    inside = torch.cat(insides)
    scales = [1.0] * len(groups) if color_grad is None else [float(s) for s in color_grad]
    scale = torch.cat([torch.full((n,), s, device=z.device) for n, s in zip(sizes, scales, strict=True)])
    colour_where = None
    if colour_grad_min_weight > 0:

        def colour_where(alpha: torch.Tensor) -> torch.Tensor:
            strong = strong_samples(alpha.detach() * inside, colour_grad_min_weight)
            return strong if min(scales) > 0 else strong & (scale > 0)[:, None]

    # [R, D, 2] as a view of the [D, R, 2] grid the explicit fields sample plane by plane.
    rgb, alpha = field(torch.cat(gs, 1).transpose(0, 1), frame.plane_z, torch.cat(dirss), colour_where)
    if max(scales) == 0:  # no colour gradients: no backward pass through the colours at all
        rgb = rgb.detach()
    lam = torch.cat(lams)
    # All groups in one composite (its gradients keep the field's layout; split, not slices: the
    # backward of a slice fills a zero gradient of the whole batch per group).
    out = composite(rgb, alpha * inside, torch.where(inside, lam, torch.zeros_like(lam)), colour_grad_min_weight, scale)
    parts = [out.rgb.split(sizes), out.depth.split(sizes), out.acc.split(sizes), out.weights.split(sizes)]
    return [RayOutput(*p) for p in zip(*parts, strict=True)]


@dataclass
class ImageOutput:
    """A rendered image. rgb [H, W, 3] in [0, 1]; depth [H, W] target-camera z (scene units);
    acc [H, W] coverage in [0, 1]."""

    rgb: torch.Tensor
    depth: torch.Tensor
    acc: torch.Tensor


def blend(outputs: Sequence[RayOutput], weights: torch.Tensor) -> RayOutput:
    """Blend per-MPI renders of the same rays: per-camera weights [N] times each MPI's coverage,
    renormalised per ray, so an MPI whose planes do not reach a ray does not darken it.

    With coverage a_i and premultiplied colour C_i, the blended colour is
    ``sum_i w_i C_i / sum_i w_i a_i`` (times the largest coverage), depth likewise; depth is 0
    where no MPI covers the ray (coverage < 1e-3).
    """
    acc_all = torch.stack([o.acc for o in outputs], 0)  # [N, R]
    total = (acc_all * weights[:, None]).sum(0).clamp_min(1e-8)
    rgb = sum(weights[i] * o.rgb for i, o in enumerate(outputs)) / total[:, None]
    depth = sum(weights[i] * o.depth for i, o in enumerate(outputs)) / total
    acc = acc_all.max(0).values
    depth = torch.where(acc > 1e-3, depth, torch.zeros_like(depth))  # type: ignore[arg-type]
    return RayOutput(rgb * acc[:, None], depth, acc)  # type: ignore[operator]


@dataclass
class _TextureWarp:
    """The terms of :func:`render_texture_image`'s warp (its docstring has the algebra) for
    ``B`` batches of ``Pb`` pixels: plane k's grid coordinates are
    ``offsets[k] + scales[k] * (m_front if e[k] > 0 else m_behind)``.

    Shape: offsets [D, 2]; m_front, m_behind [B, 1, Pb, 2] (m(p), or far outside the plane where
    the crossing would lie behind the target); dz [B, 1, 1, Pb] d_z(p); e, scales [D] and
    depth_steps [D + 1] (e_k - e_{k-1}) as floats.
    """

    offsets: torch.Tensor
    m_front: torch.Tensor
    m_behind: torch.Tensor
    dz: torch.Tensor
    e: list[float]
    scales: list[float]
    depth_steps: list[float]

    @staticmethod
    def of(
        frame: MPIFrame,
        K_tgt: torch.Tensor,
        world_from_tgt: torch.Tensor,
        width: int,
        height: int,
        B: int,
        dev: torch.device,
        dt: torch.dtype,
    ) -> _TextureWarp:
        """The warp of ``frame``'s planes into the target camera's width x height pixels."""
        M = frame.grid_from_camera(dt).to(dev)  # [2, 3]
        ref_from_tgt = frame.ref_from_world @ world_from_tgt
        R, t = ref_from_tgt[:3, :3], ref_from_tgt[:3, 3]
        d_from_pixel = R @ torch.linalg.inv(K_tgt)  # [3, 3]: homogeneous target pixel -> d(p)
        z = frame.depths
        e = z - t[2]  # [D]
        offsets = (M @ t)[None] / z[:, None]  # [D, 2]
        offsets[e == 0] = 1e12  # a plane through the target centre is seen edge-on: transparent
        # Pixels, row-major, padded to `blocks` equal batches: [B, 1, Pb, ...].
        P = width * height
        Pb = -(-P // B)
        u = torch.arange(width, device=dev, dtype=dt) + 0.5
        v = torch.arange(height, device=dev, dtype=dt) + 0.5
        Q = torch.cat([M @ d_from_pixel, d_from_pixel[2:]])  # [3, 3]: pixel (u, v, 1) -> (M d(p), d_z(p))
        md = ((v[:, None, None] * Q[:, 1] + Q[:, 2]) + u[None, :, None] * Q[:, 0]).reshape(P, 3)
        md = torch.cat([md, md[-1:].expand(B * Pb - P, 3)])  # padded with copies of the last pixel
        dz = md[:, 2].reshape(B, 1, 1, Pb)
        m = (md[:, :2] / md[:, 2:]).reshape(B, 1, Pb, 2)
        # lam_k > 0 needs d_z(p) and e_k of the same sign: m where it holds, far outside elsewhere.
        dz_m = dz.reshape(B, 1, Pb, 1)
        m_e_pos = torch.where(dz_m > 0, m, 1e12)  # for the planes with e_k > 0 (in front of the target centre)
        m_e_neg = torch.where(dz_m < 0, m, 1e12)  # for those with e_k <= 0 (the target is inside the MPI)
        scales, e_list = (e / z).tolist(), e.tolist()
        depth_steps = torch.cat([e[:1], e[1:] - e[:-1], -e[-1:]]).tolist()  # [D + 1]
        return _TextureWarp(offsets, m_e_pos, m_e_neg, dz, e_list, scales, depth_steps)


def render_texture_image(
    rgba_premult: torch.Tensor,
    frame: MPIFrame,
    K_tgt: torch.Tensor,
    world_from_tgt: torch.Tensor,
    width: int,
    height: int,
    blocks: int | None = None,
    straight_rgb: torch.Tensor | None = None,
    bicubic_min_weight: float = BICUBIC_MIN_WEIGHT,
) -> RayOutput:
    """Whole-image render of fixed textures: every plane warped by its homography, then composited.

    The fast path for baked MPIs (slow twin: :func:`cmc.mpi._reference.render_texture_image_reference`). Textures
    are premultiplied, so sampling outside a plane (zero padding) is simply transparent. With
    ``straight_rgb`` [D, 3, h, w] (the straight colours of the same planes), a sample's colour is
    those colours sampled bicubically (:func:`cmc.mpi.fields.sample_colour_bicubic`) times its
    bilinear alpha, as :class:`cmc.mpi.fields.TextureField` does with ``colour_interpolation="bicubic"``,
    where the sample weighs ``bicubic_min_weight`` or more in its pixel (:data:`BICUBIC_MIN_WEIGHT`),
    and the bilinear premultiplied colour where it weighs less.

    Warp: let ``[R | t]`` = ref_from_tgt, ``d(p) = R K_tgt^-1 p`` the reference-frame direction
    of the ray through target pixel p (homogeneous, target z = 1) and ``e_k = z_k - t_z`` for
    the plane at reference depth z_k. The ray meets plane k at target depth
    ``lam_k = e_k / d_z(p)``, at the point ``t + lam_k d(p)``, whose plane grid coordinates are
    (M [2, 3]: K_ref followed by reference pixels -> grid, :meth:`MPIFrame.grid_from_pixels`)::

        g_k(p) = (e_k / z_k) m(p) + M t / z_k,    m(p) = M d(p) / d_z(p),

    an affine function of one plane-independent 2-vector per pixel, so each plane's warp is a
    single multiply-add. Crossings behind the target (lam_k <= 0: d_z(p) and e_k of opposite
    signs) are sent far outside the plane.

    Composite, front to back, with the exclusive transmittance ``T_k = prod_{j<k} (1 - a_j)``:
    premultiplied colour and coverage ``sum_k T_k (C_k, a_k)``; depth
    ``sum_k (T_k - T_{k+1}) lam_k = (sum_k T_k (e_k - e_{k-1}) - T_D e_{D-1}) / d_z(p)``
    (with e_{-1} = 0: the sum telescopes).

    Cost: the bilinear gathers of ``grid_sample`` dominate, and from main memory they stall. So
    the planes go one at a time over the whole image, each plane's texels first read in order
    (a streaming pass that leaves them in cache for the scattered gathers; a quarter off the
    whole render on the 2-core CPU of bench/render_speed.py), and the per-plane working set
    (one plane's texels, [4, P] samples and the accumulators) stays in cache. The pixels are
    split into ``blocks`` batches (default: torch's thread count) that grid_sample processes in
    parallel; the result does not depend on ``blocks``.

    Shape: rgba_premult [D, 4, h, w] (rgb * alpha, alpha); K_tgt [3, 3]; world_from_tgt [4, 4].
    Returns a RayOutput over the height * width pixels in row-major order.
    """
    dev, dt = rgba_premult.device, rgba_premult.dtype
    D, _, h, w = rgba_premult.shape
    B = blocks or max(1, torch.get_num_threads())
    warp = _TextureWarp.of(frame, K_tgt, world_from_tgt, width, height, B, dev, dt)
    P, Pb = width * height, warp.dz.shape[-1]
    out = torch.zeros(B, 4, 1, Pb, device=dev, dtype=dt)  # sum_k T_k (C_k, a_k)
    trans = torch.ones(B, 1, 1, Pb, device=dev, dtype=dt)  # T_k
    depth_sum = torch.zeros(B, 1, 1, Pb, device=dev, dtype=dt)  # d_z(p) x depth
    grid = torch.empty(B, 1, Pb, 2, device=dev, dtype=dt)
    for k in range(D):
        plane = rgba_premult[k : k + 1]
        if dev.type == "cpu":
            plane.sum()  # the streaming read that brings the plane's texels into cache
        torch.add(warp.offsets[k], warp.m_front if warp.e[k] > 0 else warp.m_behind, alpha=warp.scales[k], out=grid)
        if straight_rgb is None:
            s = F.grid_sample(plane.expand(B, 4, h, w), grid, align_corners=False)  # [B, 4, 1, Pb]
        else:  # the alpha channel alone bilinear, the colour bicubic where the sample weighs enough
            a = F.grid_sample(plane[:, 3:].expand(B, 1, h, w), grid, align_corners=False)
            rgb = sample_colour_bicubic(straight_rgb[k : k + 1].expand(B, 3, h, w), grid) * a
            faint = trans * a < bicubic_min_weight
            if faint.any():
                premultiplied = F.grid_sample(plane[:, :3].expand(B, 3, h, w), grid, align_corners=False)
                rgb = torch.where(faint, premultiplied, rgb)
            s = torch.cat([rgb, a], 1)
        depth_sum.add_(trans, alpha=warp.depth_steps[k])
        out.addcmul_(s, trans)
        trans.addcmul_(trans, s[:, 3:], value=-1)  # T_{k+1} = T_k (1 - a_k)
    depth_sum.add_(trans, alpha=warp.depth_steps[D])
    out = out.permute(1, 0, 2, 3).reshape(4, B * Pb)[:, :P]
    return RayOutput(out[:3].T, (depth_sum / warp.dz).reshape(-1)[:P], out[3])


def select_mpis(weights: ArrayT, mpi_index: int | None = None, min_weight: float = 0.0) -> tuple[ArrayT, list[int]]:
    """The blend weights [N] to render with (NumPy or torch, as given) and the MPIs to render:
    those weighing at least ``min_weight`` (at least the heaviest), or only ``mpi_index``
    (weights then all 1)."""
    if mpi_index is not None:
        return weights * 0 + 1, [mpi_index]
    use = [i for i in range(len(weights)) if weights[i] >= min_weight] or [int(weights.argmax())]
    return weights, use


def blend_selection(
    frames: Sequence[MPIFrame], world_from_cam: torch.Tensor, mpi_index: int | None = None, min_weight: float = 0.0
) -> tuple[torch.Tensor, list[int]]:
    """Blend weights [N] of the MPIs for a target camera (:func:`cmc.geometry.planes.blend_weights`)
    and the MPIs to render (:func:`select_mpis`)."""
    centers = torch.stack([f.world_from_ref[:3, 3] for f in frames])
    weights = blend_weights(centers, world_from_cam[:3, 3].to(centers.device), mean_baseline(centers))
    return select_mpis(weights, mpi_index, min_weight)


@torch.no_grad()
def render_image(
    fields: Sequence[MPIField],
    frames: Sequence[MPIFrame],
    K: np.ndarray | torch.Tensor,
    world_from_cam: np.ndarray | torch.Tensor,
    width: int,
    height: int,
    mpi_index: int | None = None,
    chunk: int = 1 << 16,
    min_weight: float = 0.0,
) -> ImageOutput:
    """Render a whole target image by blending the MPIs (or only MPI ``mpi_index``).

    MPIs whose blend weight (:func:`cmc.geometry.planes.blend_weights`) is below ``min_weight`` are
    skipped, which saves time when the target is next to one input camera.
    """
    device = frames[0].K.device
    K_t = torch.as_tensor(np.asarray(K), dtype=torch.float32, device=device)
    P_t = torch.as_tensor(np.asarray(world_from_cam), dtype=torch.float32, device=device)
    weights, use = blend_selection(frames, P_t, mpi_index, min_weight)
    parts = []
    if all(isinstance(fields[i], TextureField) for i in use):
        outs = [
            render_texture_image(
                fields[i].premultiplied,
                frames[i],
                K_t,
                P_t,
                width,
                height,
                straight_rgb=fields[i].rgba[:, :3] if fields[i].colour_interpolation == "bicubic" else None,
            )
            for i in use
        ]
        parts.append(blend(outs, weights[use]))
    else:
        uv = pixel_centers(width, height, device)
        for s in range(0, len(uv), chunk):
            outs = [render_rays(fields[i], frames[i], K_t, P_t, uv[s : s + chunk]) for i in use]
            parts.append(blend(outs, weights[use]))
    rgb = torch.cat([p.rgb for p in parts]).reshape(height, width, 3)
    depth = torch.cat([p.depth for p in parts]).reshape(height, width)
    acc = torch.cat([p.acc for p in parts]).reshape(height, width)
    return ImageOutput(rgb, depth, acc)
