"""Rendering rays and images from per-view MPIs: homography warps and alpha compositing.

Conventions: :mod:`cmc.cameras`. A target ray is identified by its target camera and a
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

from cmc.fields import MPIField, TextureField
from cmc.geometry import (
    apply_homography,
    blend_weights,
    homographies_ref_from_tgt,
    mean_baseline,
    pixel_centers,
    plane_depths,
)


@dataclass(frozen=True)
class MPIFrame:
    """Where one MPI lives: its reference camera and planes.

    Attributes:
        K: [3, 3] reference intrinsics (pixels); world_from_ref: [4, 4] (OpenCV axes).
        depths: [D] plane depths in the reference camera, nearest first (uniform in disparity).
        width, height: reference image size in pixels.
        margin: the planes extend ``margin`` times the image's size about its centre, so that
            target views looking past the reference image's border still see plane content.
    """

    K: torch.Tensor
    world_from_ref: torch.Tensor
    depths: torch.Tensor
    width: int
    height: int
    margin: float

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
    ) -> MPIFrame:
        d = plane_depths(near, far, num_planes)
        t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32, device=device)  # noqa: E731
        return MPIFrame(t(K), t(world_from_ref), t(d), width, height, margin)

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
        return round(self.height * self.margin), round(self.width * self.margin)

    def grid_from_pixels(self, uv: torch.Tensor) -> torch.Tensor:
        """Reference pixel coordinates [..., 2] -> plane grid coordinates in [-1, 1] inside."""
        size = uv.new_tensor([self.width, self.height])
        return (uv / size * 2 - 1) / self.margin

    def pixels_from_grid(self, g: torch.Tensor) -> torch.Tensor:
        """Inverse of :meth:`grid_from_pixels`."""
        size = g.new_tensor([self.width, self.height])
        return (g * self.margin + 1) / 2 * size


@dataclass
class RayOutput:
    """Composited result for R rays.

    Attributes:
        rgb: [R, 3] colour in [0, 1]; depth: [R] target-camera depth (scene units, 0 where
        nothing is hit); acc: [R] accumulated alpha, 0 outside the MPI's planes.
    """

    rgb: torch.Tensor
    depth: torch.Tensor
    acc: torch.Tensor


def composite(rgb: torch.Tensor, alpha: torch.Tensor, depth: torch.Tensor) -> RayOutput:
    """Front-to-back alpha compositing (paper Eq. 3.4, 3.5).

    Shape: rgb [R, D, 3], alpha [R, D], depth [R, D] (per-sample depth), nearest plane first.
    """
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1]], dim=1), dim=1)
    w = alpha * trans
    return RayOutput((w[..., None] * rgb).sum(1), (w * depth).sum(1), w.sum(1))


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
    color_grad: Sequence[bool] | None = None,
) -> list[RayOutput]:
    """Render rays of several target cameras from one MPI with a single field query.

    One query instead of one per camera matters for explicit fields, whose backward pass
    touches every texture once per query.

    Args:
        groups: (K_tgt [3, 3], world_from_tgt [4, 4], uv [R_g, 2]) per target camera.
        color_grad: per group, whether gradients flow to the field's colours (default all);
            where False, only alpha (the geometry) receives the group's gradients.
    Returns:
        one RayOutput per group.
    """
    gs, lams, insides, dirss = [], [], [], []
    for K_tgt, world_from_tgt, uv in groups:
        H = homographies_ref_from_tgt(frame.K, frame.ref_from_world, K_tgt, world_from_tgt, frame.depths)
        uv_ref, in_front = apply_homography(H, uv)  # [R, D, 2], [R, D]
        g = frame.grid_from_pixels(uv_ref)
        insides.append(in_front & (g.abs() <= 1).all(-1))
        gs.append(g.clamp(-1.5, 1.5))
        # Ray directions in the reference frame, and the target depth of every plane crossing:
        # the point o + lam * d_ref (d_ref has target z = 1) lies on plane z_ref = depth.
        ref_from_tgt = frame.ref_from_world @ world_from_tgt
        d_tgt = torch.cat([uv, torch.ones_like(uv[:, :1])], -1) @ torch.linalg.inv(K_tgt).T
        d_ref = d_tgt @ ref_from_tgt[:3, :3].T
        lams.append((frame.depths[None] - ref_from_tgt[2, 3]) / d_ref[:, 2:3])  # [R, D]
        dirss.append(d_ref / d_ref.norm(dim=-1, keepdim=True))
    rgb, alpha = field(torch.cat(gs), frame.plane_z, torch.cat(dirss))
    outs, start = [], 0
    for g, (inside, lam) in enumerate(zip(insides, lams, strict=True)):
        sl = slice(start, start + len(lam))
        start += len(lam)
        rgb_g = rgb[sl] if color_grad is None or color_grad[g] else rgb[sl].detach()
        outs.append(composite(rgb_g, alpha[sl] * inside, torch.where(inside, lam, torch.zeros_like(lam))))
    return outs


def render_rays_reference(
    field: MPIField, frame: MPIFrame, K_tgt: torch.Tensor, world_from_tgt: torch.Tensor, uv: torch.Tensor
) -> RayOutput:
    """Slow, obviously-correct twin of :func:`render_rays` for tests: one plane at a time, by
    intersecting each world-space ray with the plane and projecting the point into the
    reference camera (no homography)."""
    origin = world_from_tgt[:3, 3]
    d_cam = torch.cat([uv, torch.ones_like(uv[:, :1])], -1) @ torch.linalg.inv(K_tgt).T
    d_world = d_cam @ world_from_tgt[:3, :3].T  # target z-depth parametrisation
    ref_from_world = frame.ref_from_world
    gs, lams, valids = [], [], []
    for z in frame.depths:
        o_ref = ref_from_world[:3, :3] @ origin + ref_from_world[:3, 3]
        d_ref = d_world @ ref_from_world[:3, :3].T
        lam = (z - o_ref[2]) / d_ref[:, 2]
        p = o_ref + lam[:, None] * d_ref
        pix = p @ frame.K.T
        uv_ref = pix[:, :2] / pix[:, 2:3]
        g = frame.grid_from_pixels(uv_ref)
        gs.append(g)
        lams.append(lam)
        valids.append((lam > 0) & (g.abs() <= 1).all(-1))
    g = torch.stack(gs, 1)
    lam = torch.stack(lams, 1)
    inside = torch.stack(valids, 1)
    dirs = d_world @ ref_from_world[:3, :3].T
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    rgb, alpha = field(g.clamp(-1.5, 1.5), frame.plane_z, dirs)
    alpha = alpha * inside
    out_rgb = torch.zeros_like(rgb[:, 0])
    out_depth = torch.zeros_like(lam[:, 0])
    trans = torch.ones_like(lam[:, 0])
    for k in range(lam.shape[1]):
        a = alpha[:, k]
        out_rgb = out_rgb + (trans * a)[:, None] * rgb[:, k]
        out_depth = out_depth + trans * a * torch.where(inside[:, k], lam[:, k], torch.zeros_like(a))
        trans = trans * (1 - a)
    return RayOutput(out_rgb, out_depth, 1 - trans)


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


def render_texture_image(
    rgba_premult: torch.Tensor,
    frame: MPIFrame,
    K_tgt: torch.Tensor,
    world_from_tgt: torch.Tensor,
    width: int,
    height: int,
    plane_chunk: int = 8,
) -> RayOutput:
    """Whole-image render of fixed textures: one warp of every plane, then compositing.

    The fast path for baked MPIs. Textures are premultiplied, so sampling outside a plane (zero
    padding) is simply transparent. The homography of plane k (depth z_k) is written as
    ``G_k = A + b c^T / (z_k - t_z)`` (A, b, c shared by all planes; G includes the map from
    reference pixels to plane grid coordinates), so the D warps cost a few broadcasts; the
    composite uses the inclusive transmittance ``T_k = prod_{j<=k} (1 - a_j)``:
    colour ``C_0 + sum_{k>=1} T_{k-1} C_k``, coverage ``1 - T_{D-1}``, and depth
    ``sum_k (T_{k-1} - T_k) lam_k`` with lam_k = (z_k - t_z) / dz(p) the target depth.

    Shape: rgba_premult [D, 4, h, w] (rgb * alpha, alpha); K_tgt [3, 3]; world_from_tgt [4, 4].
    Returns a RayOutput over the H * W pixels in row-major order.
    """
    dev, dt = rgba_premult.device, rgba_premult.dtype
    m = frame.margin
    N = torch.tensor(
        [[2 / (frame.width * m), 0, -1 / m], [0, 2 / (frame.height * m), -1 / m], [0, 0, 1]], device=dev, dtype=dt
    )
    ref_from_tgt = frame.ref_from_world @ world_from_tgt
    R, t = ref_from_tgt[:3, :3], ref_from_tgt[:3, 3]
    K_inv = torch.linalg.inv(K_tgt)
    A = N @ frame.K @ R @ K_inv
    b = N @ frame.K @ t
    c = K_inv.T @ R[2]  # n_t^T K^-1 p with n_t = R^T e_z
    uv = pixel_centers(width, height, dev)
    p = torch.cat([uv, torch.ones_like(uv[:, :1])], -1)  # [P, 3]
    Ap = p @ A.T  # [P, 3]
    cp = p @ c  # [P]: also dz(p), the reference z-component of the ray with target z = 1
    z = frame.depths
    inv_d = (1.0 / (z - t[2]))[:, None]  # [D, 1]
    rgb = torch.zeros(3, len(p), device=dev, dtype=dt)
    T_prev = torch.ones(len(p), device=dev, dtype=dt)  # transmittance in front of the chunk
    zsum = torch.zeros_like(T_prev)  # sum_k (T_{k-1} - T_k) z_k
    # Planes in chunks keep the working set in cache (one [chunk, 4, P] sample at a time).
    for k0 in range(0, len(z), plane_chunk):
        sl = slice(k0, k0 + plane_chunk)
        den = Ap[:, 2] + inv_d[sl] * (cp * b[2])
        den = torch.where(den > 1e-6, den, torch.full_like(den, 1e-12))  # behind the target: far outside
        gx = (Ap[:, 0] + inv_d[sl] * (cp * b[0])) / den
        gy = (Ap[:, 1] + inv_d[sl] * (cp * b[1])) / den
        grid = torch.stack([gx, gy], -1).reshape(-1, height, width, 2)
        s = F.grid_sample(rgba_premult[sl], grid, align_corners=False).reshape(len(den), 4, -1)  # [C, 4, P]
        T = torch.cumprod(1 - s[:, 3], 0) * T_prev  # inclusive transmittance of the chunk's planes
        for k in range(len(T)):
            rgb.addcmul_(T_prev if k == 0 else T[k - 1], s[k, :3])
        zc = z[sl]
        zsum += zc[0] * T_prev + (zc[1:] - zc[:-1]) @ T[:-1] - T[-1] * zc[-1]
        T_prev = T[-1]
    acc = 1 - T_prev
    depth = (zsum - acc * t[2]) / cp
    return RayOutput(rgb.T, depth, acc)


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

    MPIs whose blend weight (:func:`cmc.geometry.blend_weights`) is below ``min_weight`` are
    skipped, which saves time when the target is next to one input camera.
    """
    device = frames[0].K.device
    K_t = torch.as_tensor(np.asarray(K), dtype=torch.float32, device=device)
    P_t = torch.as_tensor(np.asarray(world_from_cam), dtype=torch.float32, device=device)
    uv = pixel_centers(width, height, device)
    centers = torch.stack([f.world_from_ref[:3, 3] for f in frames])
    baseline = mean_baseline(centers)
    if mpi_index is None:
        weights = blend_weights(centers, P_t[:3, 3], baseline)
        use = [i for i in range(len(frames)) if weights[i] >= min_weight] or [int(weights.argmax())]
    else:
        weights = torch.ones(len(frames), device=device)
        use = [mpi_index]
    parts = []
    if all(isinstance(fields[i], TextureField) for i in use):
        outs = [render_texture_image(fields[i].premultiplied, frames[i], K_t, P_t, width, height) for i in use]
        parts.append(blend(outs, weights[use]))
    else:
        for s in range(0, len(uv), chunk):
            outs = [render_rays(fields[i], frames[i], K_t, P_t, uv[s : s + chunk]) for i in use]
            parts.append(blend(outs, weights[use]))
    rgb = torch.cat([p.rgb for p in parts]).reshape(height, width, 3)
    depth = torch.cat([p.depth for p in parts]).reshape(height, width)
    acc = torch.cat([p.acc for p in parts]).reshape(height, width)
    return ImageOutput(rgb, depth, acc)
