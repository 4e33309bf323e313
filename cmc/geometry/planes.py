"""Plane geometry of multiplane images: plane depths, plane-induced homographies, virtual poses.

Conventions are those of :mod:`cmc.geometry.cameras` (OpenCV axes, camera-to-world ``world_from_cam``,
pixel corners at integers). An MPI belongs to a reference camera ``ref``; its plane k is the
fronto-parallel plane ``z_ref = depth[k]`` in that camera. Planes are ordered front to back
(nearest first), which is the compositing order.
"""

from __future__ import annotations

from typing import TypeVar

import numpy as np
import torch

from cmc.geometry.cameras import nearest_rotation

ArrayT = TypeVar("ArrayT", np.ndarray, torch.Tensor)  # a function that takes either returns the same kind


def plane_depths(near: float, far: float, num_planes: int) -> np.ndarray:
    """[D] plane depths uniform in disparity from ``near`` (index 0) to ``far`` (index D-1)."""
    if not (np.isfinite(near) and np.isfinite(far)) or not 0 < near < far:
        raise ValueError(f"need 0 < near < far, got near={near}, far={far}")
    if num_planes < 2:
        raise ValueError(f"need at least 2 planes, got {num_planes}")
    return 1.0 / np.linspace(1.0 / near, 1.0 / far, num_planes)


def occupied_depth_range(
    near: float, far: float, surfaces: np.ndarray, share: float = 0.01, pad: float = 0.15
) -> tuple[float, float]:
    """The depth interval within [``near``, ``far``] where the scene's surfaces lie.

    ``surfaces`` [D] is how many surfaces lie at each plane of :func:`plane_depths` (``near``,
    ``far``, D), e.g. plane-sweep texels counted at their most likely plane. The interval runs
    from the plane where ``share`` of them lie nearer to the plane where ``share`` lie farther,
    widened in disparity by ``pad`` times its width plus one plane spacing at each end (the
    sweep places a surface to within a plane), and clipped to [near, far]. Returns (near, far).
    """
    surfaces = np.asarray(surfaces, dtype=np.float64)
    D = len(surfaces)
    if not np.all(np.isfinite(surfaces)) or np.any(surfaces < 0) or surfaces.sum() <= 0:
        raise ValueError("surface counts must be finite, non-negative and not all zero")
    disparity = 1.0 / plane_depths(near, far, D)  # decreasing: plane 0 is the nearest
    cdf = np.cumsum(surfaces) / surfaces.sum()
    first = int(np.searchsorted(cdf, share, side="right"))
    last = int(np.searchsorted(cdf, 1.0 - share, side="left"))
    spacing = disparity[0] - disparity[1]
    widen = pad * (disparity[first] - disparity[last]) + spacing
    hi = min(disparity[0], disparity[first] + widen)
    lo = max(disparity[-1], disparity[last] - widen)
    return (near if hi >= disparity[0] else 1.0 / hi), (far if lo <= disparity[-1] else 1.0 / lo)


def content_plane_depths(near: float, far: float, density: np.ndarray, floor: float) -> np.ndarray:
    """[D] plane depths from ``near`` (index 0) to ``far`` (index D-1), spaced in disparity so that
    the planes crowd where the scene's surfaces are.

    ``density`` [D] is how much of the scene lies at each plane of :func:`plane_depths` (any
    non-negative weights, e.g. plane-sweep probabilities summed over texels), spread evenly over
    the disparity interval nearest that plane. The planes follow the cube root of that density:
    the point density that minimises the mean squared distance, in disparity, from a surface to
    its nearest plane (Panter and Dite's companding law), so a large flat wall gets a few planes
    more, not all of them. Plane k of the result sits at the k / (D - 1) quantile of the mixture
    ``floor`` x uniform + ``(1 - floor)`` x that cube-root density. ``floor`` in (0, 1] bounds
    the spacing: no gap exceeds 1 / floor times the uniform spacing (``floor = 1``:
    :func:`plane_depths`). Nearest and farthest stay ``near`` and ``far``.
    """
    density = np.asarray(density, dtype=np.float64)
    D = len(density)
    if not 0 < floor <= 1:
        raise ValueError(f"plane density floor must be in (0, 1], got {floor}")
    uniform = plane_depths(near, far, D)
    total = density.sum()
    if not np.all(np.isfinite(density)) or np.any(density < 0) or total <= 0:
        raise ValueError("plane density must be finite, non-negative and not all zero")
    # Position t in [0, 1] along the disparity range (0 = near); uniform plane k at k / (D - 1)
    # owns the interval of t nearest it.
    edges = np.concatenate([[0.0], (np.arange(D - 1) + 0.5) / (D - 1), [1.0]])
    width = np.diff(edges)
    companded = np.cbrt(density / total / width) * width
    mass = floor * width + (1 - floor) * companded / companded.sum()
    cdf = np.concatenate([[0.0], np.cumsum(mass)])
    t = np.interp(np.linspace(0.0, 1.0, D), cdf / cdf[-1], edges)
    disparity = 1.0 / near + t * (1.0 / far - 1.0 / near)
    depths = 1.0 / disparity
    depths[0], depths[-1] = uniform[0], uniform[-1]
    return depths


def homographies_ref_from_tgt(
    K_ref: torch.Tensor,
    ref_from_world: torch.Tensor,
    K_tgt: torch.Tensor,
    world_from_tgt: torch.Tensor,
    depths: torch.Tensor,
) -> torch.Tensor:
    """Plane-induced homographies taking target pixels to reference pixels (paper Eq. 4.1-4.2).

    For plane ``z_ref = depth`` of the reference camera, a target pixel ``p_t`` (homogeneous,
    continuous pixel coordinates) sees the plane point that projects to ``H @ p_t`` in the
    reference image, with ``H = K_ref (R + t n_t^T / d_t) K_tgt^-1``, where ``[R | t]`` is
    ``ref_from_tgt`` and ``n_t^T X_t = d_t`` is the plane in target coordinates.

    Shape:
        K_ref, K_tgt: [..., 3, 3]; ref_from_world, world_from_tgt: [..., 4, 4];
        depths: [..., D]. Leading dims broadcast. Returns [..., D, 3, 3].
    """
    ref_from_tgt = ref_from_world @ world_from_tgt
    R = ref_from_tgt[..., :3, :3]
    t = ref_from_tgt[..., :3, 3]
    # Plane n^T X_ref = z with n = e_z; in target coordinates n_t = R^T n, d_t = z - n^T t.
    n_t = R[..., 2, :]  # [..., 3]
    d_t = depths - t[..., 2:3]  # [..., D]
    H_cam = R[..., None, :, :] + t[..., None, :, None] * n_t[..., None, None, :] / d_t[..., None, None]
    return K_ref[..., None, :, :] @ H_cam @ torch.linalg.inv(K_tgt)[..., None, :, :]


def texel_grid(height: int, width: int, device: torch.device | str = "cpu") -> torch.Tensor:
    """[height, width, 2] plane grid coordinates (x, y) in [-1, 1] of the centres of a texel grid
    (``grid_sample(align_corners=False)``'s convention: texel c of w sits at (c + 0.5) / w * 2 - 1)."""
    ys = (torch.arange(height, device=device, dtype=torch.float32) + 0.5) / height * 2 - 1
    xs = (torch.arange(width, device=device, dtype=torch.float32) + 0.5) / width * 2 - 1
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([gx, gy], -1)


def pixel_centers(width: int, height: int, device: torch.device | str = "cpu") -> torch.Tensor:
    """[H*W, 2] continuous (u, v) coordinates of every pixel centre, row-major."""
    v, u = torch.meshgrid(
        torch.arange(height, device=device, dtype=torch.float32) + 0.5,
        torch.arange(width, device=device, dtype=torch.float32) + 0.5,
        indexing="ij",
    )
    return torch.stack([u, v], dim=-1).reshape(-1, 2)


def sample_virtual_pose(world_from_cams: np.ndarray, rng: np.random.Generator, jitter: float = 0.1) -> np.ndarray:
    """A random unseen camera-to-world pose near the input cameras ([4, 4]).

    The centre is a random convex combination (Dirichlet(1) weights) of the input centres plus
    isotropic Gaussian jitter of ``jitter`` times the mean distance between input centres; the
    rotation is the same weighted mean of the input rotations, projected back onto SO(3).
    """
    w = rng.dirichlet(np.ones(len(world_from_cams)))
    centers = world_from_cams[:, :3, 3]
    baseline = mean_baseline(centers)
    pose = np.eye(4)
    pose[:3, :3] = nearest_rotation(np.einsum("n,nij->ij", w, world_from_cams[:, :3, :3]))
    pose[:3, 3] = w @ centers + rng.normal(scale=jitter * baseline, size=3)
    return pose


def blend_weights(ref_centers: ArrayT, target_center: ArrayT, baseline: float) -> ArrayT:
    """Weights of the per-view MPIs for one target camera: nearer MPIs weigh more.

    The paper's printed formula (w_i proportional to the squared distance mu_i) gives the
    *farthest* MPI the most weight, contradicting its own text ("the closest MPI ... should have
    a greater impact"). We follow the text with inverse squared distance:
    ``w_i = (1 / (mu_i + eps)) / sum_j (1 / (mu_j + eps))``, ``mu_i = ||o_t - o_i||^2``,
    ``eps = (0.1 * baseline)^2`` (plus 1e-12) so that weights stay finite and smooth at an
    input camera, also when cameras share a centre.

    Shape: ref_centers [N, 3], target_center [3] -> [N], summing to 1 (NumPy or torch, as given).
    """
    mu = ((ref_centers - target_center) ** 2).sum(-1)
    inv = 1.0 / (mu + (0.1 * baseline) ** 2 + 1e-12)
    return inv / inv.sum()


def mean_baseline(centers: np.ndarray | torch.Tensor) -> float:
    """Mean distance between distinct camera centres ([N, 3]); 1.0 for a single camera."""
    c = torch.as_tensor(centers, dtype=torch.float64)
    n = len(c)
    if n < 2:
        return 1.0
    return float(torch.cdist(c, c).sum() / (n * (n - 1)))
