"""Slow, obviously-correct twins of the fast renderers, for tests only (never imported by the
library): each intersects every world-space ray with each plane and projects the crossing into
the reference camera (no homography), one plane at a time. Conventions: :mod:`cmc.mpi.rendering`.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from cmc.geometry.cameras import pixel_rays
from cmc.geometry.planes import pixel_centers
from cmc.mpi.fields import MPIField, sample_colour_bicubic
from cmc.mpi.rendering import BICUBIC_MIN_WEIGHT, MPIFrame, RayOutput


def render_rays_reference(
    field: MPIField, frame: MPIFrame, K_tgt: torch.Tensor, world_from_tgt: torch.Tensor, uv: torch.Tensor
) -> RayOutput:
    """Slow, obviously-correct twin of :func:`cmc.mpi.rendering.render_rays` for tests: one plane at a time, by
    intersecting each world-space ray with the plane and projecting the point into the
    reference camera (no homography)."""
    origin = world_from_tgt[:3, 3]
    d_cam = pixel_rays(K_tgt, uv)
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


def render_texture_image_reference(
    rgba_premult: torch.Tensor,
    frame: MPIFrame,
    K_tgt: torch.Tensor,
    world_from_tgt: torch.Tensor,
    width: int,
    height: int,
    straight_rgb: torch.Tensor | None = None,
    bicubic_min_weight: float = BICUBIC_MIN_WEIGHT,
) -> RayOutput:
    """Slow, obviously-correct twin of :func:`cmc.mpi.rendering.render_texture_image` for tests: one plane at a time,
    by intersecting each pixel's world-space ray with the plane and projecting the point into the
    reference camera (no homography), one ``grid_sample`` per plane (zero padding: transparent
    outside the plane) and front-to-back "over" in a loop. Crossings behind the target camera
    are transparent.

    Shape: as :func:`cmc.mpi.rendering.render_texture_image`.
    """
    uv = pixel_centers(width, height, rgba_premult.device).to(rgba_premult.dtype)
    d_cam = pixel_rays(K_tgt, uv)
    d_world = d_cam @ world_from_tgt[:3, :3].T  # target z-depth parametrisation
    ref_from_world = frame.ref_from_world
    o_ref = ref_from_world[:3, :3] @ world_from_tgt[:3, 3] + ref_from_world[:3, 3]
    d_ref = d_world @ ref_from_world[:3, :3].T
    rgb = torch.zeros_like(d_ref)
    depth = torch.zeros_like(d_ref[:, 0])
    trans = torch.ones_like(depth)
    for k, z in enumerate(frame.depths):
        lam = (z - o_ref[2]) / d_ref[:, 2]  # target depth of the crossing
        in_front = lam > 0
        p = o_ref + lam[:, None] * d_ref
        pix = p @ frame.K.T
        g = frame.grid_from_pixels(pix[:, :2] / pix[:, 2:3])
        g = torch.where(in_front[:, None], g, torch.full_like(g, 3.0))
        s = F.grid_sample(rgba_premult[k : k + 1], g[None, None], align_corners=False)[0, :, 0].T  # [P, 4]
        if straight_rgb is not None:  # bicubic straight colour times bilinear alpha, where it weighs enough
            c = sample_colour_bicubic(straight_rgb[k : k + 1], g[None, None])[0, :, 0].T
            strong = trans[:, None] * s[:, 3:] >= bicubic_min_weight
            s = torch.cat([torch.where(strong, c * s[:, 3:], s[:, :3]), s[:, 3:]], 1)
        rgb = rgb + trans[:, None] * s[:, :3]
        depth = depth + trans * s[:, 3] * torch.where(in_front, lam, torch.zeros_like(lam))
        trans = trans * (1 - s[:, 3])
    return RayOutput(rgb, depth, 1 - trans)
