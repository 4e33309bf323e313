"""Near and far depth bounds of each view: from a reconstruction's points, or by triangulating
matched features with known cameras. Depths are camera z in scene units; pixels follow
:mod:`cmc.geometry.cameras` (corner at 0)."""

from __future__ import annotations

from typing import Any

import numpy as np

from cmc.errors import PoseEstimationError
from cmc.geometry.cameras import CameraError, Cameras, pixel_rays
from cmc.poses.intake import Matches, Photos
from cmc.poses.options import SUGGESTION, SparsePoints

NEAR_FAR_PERCENTILES = (0.5, 99.5)  # robust extremes of the per-view point depths ...
# ... widened by these factors: the few hundred points of a few photos miss the scene's nearest
# and farthest surfaces (room's nearest lie 2.5x nearer than its SfM points'), and the model
# fits its planes to where its plane sweep finds the scene within these bounds
# (ModelConfig.fit_depth_range), which a near bound 4x too close does not disturb.
NEAR_FAR_MARGINS = (0.25, 4.0)
MIN_POINTS_PER_VIEW = 8


def depth_range(depths: np.ndarray, name: str = "view") -> tuple[float, float]:
    """(near, far) covering the positive camera-z ``depths`` [P] of one view's 3D points.

    Robust percentiles (:data:`NEAR_FAR_PERCENTILES`) widened by :data:`NEAR_FAR_MARGINS`; raises
    PoseEstimationError with fewer than MIN_POINTS_PER_VIEW points.
    """
    z = np.asarray(depths, dtype=np.float64)
    z = z[np.isfinite(z) & (z > 0)]
    if len(z) < MIN_POINTS_PER_VIEW:
        raise PoseEstimationError(
            f"only {len(z)} 3D points are seen from {name}, too few for a depth range. {SUGGESTION}"
        )
    lo, hi = np.percentile(z, NEAR_FAR_PERCENTILES)
    near, far = lo * NEAR_FAR_MARGINS[0], hi * NEAR_FAR_MARGINS[1]
    return float(near), float(max(far, near * 1.01))


def triangulate_pair(
    cameras: Cameras, i: int, j: int, uv_i: np.ndarray, uv_j: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Linear (DLT) triangulation of matched pixels between two known cameras.

    Args:
        cameras: the cameras, intrinsics at the resolution of the pixel coordinates.
        i, j: the two camera indices.
        uv_i, uv_j: [M, 2] matched pixel coordinates (pixel-corner convention).
    Returns:
        points [M, 3] (world), depths [M, 2] (camera z in i and j), reprojection error [M]
        (pixels, the larger of the two views).
    """
    cam_from_world = cameras.cam_from_world[[i, j], :3]  # [2, 3, 4]
    rows = []
    for k, uv in enumerate((uv_i, uv_j)):
        P = cam_from_world[k]
        xn = pixel_rays(cameras.K[(i, j)[k]], uv)
        rows += [xn[:, 0:1] * P[2] - P[0], xn[:, 1:2] * P[2] - P[1]]  # x * (row 3) - (row 1), ... [M, 4]
    A = np.stack(rows, axis=1)  # [M, 4, 4]
    X = np.linalg.svd(A)[2][:, -1]
    X = X[:, :3] / X[:, 3:4]
    uv_proj, depth = cameras[[i, j]].project(X)  # [2, M, 2], [2, M]
    err = np.linalg.norm(uv_proj - np.stack([uv_i, uv_j]), axis=-1).max(axis=0)
    return X, depth.T, err


def near_far_from_points(sparse: SparsePoints, cameras: Cameras, photos: Photos) -> np.ndarray:
    """[N, 2] depth bounds from the camera z of the 3D points each photo observes."""
    _, depth = cameras.project(sparse.xyz)  # [N, P]
    return np.array(
        [depth_range(depth[k, sparse.seen_by(k)], photos.label(k)) for k in range(len(cameras))], dtype=np.float64
    )


def near_far_by_triangulation(
    cameras: Cameras, matches: Matches, photos: Photos, max_error_px: float, min_angle_deg: float
) -> tuple[np.ndarray, dict[str, Any]]:
    """[N, 2] depth bounds from matched features triangulated with the known cameras.

    Raises CameraError when most matches do not fit the poses (wrong convention or frame order).
    """
    depths: list[list[np.ndarray]] = [[] for _ in photos.names]
    total = consistent = 0
    for (i, j), m in matches.pairs.items():
        if len(m) == 0:
            continue
        uv_i, uv_j = matches.keypoints[i][m[:, 0]], matches.keypoints[j][m[:, 1]]
        X, depth, err = triangulate_pair(cameras, i, j, uv_i, uv_j)
        ok = (depth > 0).all(axis=1) & (err < max_error_px)
        centres = cameras.centers[[i, j]]
        r_i, r_j = X - centres[0], X - centres[1]
        cos = np.einsum("md,md->m", r_i, r_j) / (np.linalg.norm(r_i, axis=1) * np.linalg.norm(r_j, axis=1) + 1e-12)
        wide = cos < np.cos(np.radians(min_angle_deg))
        total += len(m)
        consistent += int(ok.sum())
        depths[i].append(depth[ok & wide, 0])
        depths[j].append(depth[ok & wide, 1])
    if total == 0:
        raise PoseEstimationError(
            "no features match between the photos, so the depth range cannot be triangulated: add near/far "
            "to the cameras file, or retake the photos with more overlap of a textured scene"
        )
    if consistent < 0.5 * total:
        raise CameraError(
            f"the poses in the cameras file do not fit the photos: only {consistent} of {total} matched "
            "features triangulate in front of both cameras; check the 'convention' field (opengl vs "
            "opencv) and that each frame's file_path names the right photo"
        )
    near_far = np.array(
        [depth_range(np.concatenate(d) if d else np.zeros(0), photos.label(k)) for k, d in enumerate(depths)]
    )
    return near_far, {"matches": total, "consistent_matches": consistent}
