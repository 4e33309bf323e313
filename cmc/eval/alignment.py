"""Aligning two reconstructions of the same photos (benchmarks against a dataset's own model; not
part of pose estimation): :func:`similarity_from_cameras` from their cameras, or through their 3D
points: :func:`corresponding_points` pairs the points both see at the same pixels, and
:func:`register_camera` finds the pose that sees given points at given pixels.

Conventions are :mod:`cmc.geometry.cameras`' (OpenCV axes, camera-to-world [..., 4, 4], pixel corner at 0);
a similarity ``(scale, R [3, 3], t [3])`` maps ``X' = scale * R @ X + t``.
"""

from __future__ import annotations

import numpy as np

from cmc.errors import PoseEstimationError
from cmc.geometry.cameras import nearest_rotation
from cmc.poses.colmap import import_pycolmap, world_from_cam


def similarity_from_cameras(
    src_world_from_cam: np.ndarray, dst_world_from_cam: np.ndarray
) -> tuple[float, np.ndarray, np.ndarray]:
    """The similarity ``X_dst = scale * R @ X_src + t`` that best maps cameras ``src`` onto ``dst``.

    Made for few cameras (2-5 photos, where the centres alone leave the rotation ill-determined):

    * rotation: the chordal mean of the per-camera estimates ``R_dst_i @ R_src_i.T`` (the camera
      orientations alone fix it), projected to SO(3);
    * scale: ratio of the RMS distances of the centres from their centroids (needs >= 2 distinct
      centres; does not depend on the rotation);
    * translation: maps the centroid of the ``src`` centres onto that of the ``dst`` centres.

    Exact when ``dst`` is a similarity of ``src``. Args: [N, 4, 4] camera-to-world poses of the
    same N cameras in the two reconstructions. Returns: (scale, R [3, 3], t [3]).
    """
    src, dst = np.asarray(src_world_from_cam, np.float64), np.asarray(dst_world_from_cam, np.float64)
    if src.shape != dst.shape or src.ndim != 3 or src.shape[1:] != (4, 4):
        raise ValueError(f"need two [N, 4, 4] pose arrays of the same N, got {src.shape} and {dst.shape}")
    R = nearest_rotation(np.einsum("nij,nkj->ik", dst[:, :3, :3], src[:, :3, :3]))
    c_src, c_dst = src[:, :3, 3], dst[:, :3, 3]
    m_src, m_dst = c_src.mean(0), c_dst.mean(0)
    spread_src = np.sqrt(((c_src - m_src) ** 2).sum(1).mean())
    if spread_src < 1e-12:
        raise ValueError("the source camera centres coincide: the scale is undetermined")
    scale = float(np.sqrt(((c_dst - m_dst) ** 2).sum(1).mean()) / spread_src)
    return scale, R, m_dst - scale * R @ m_src


def apply_similarity_to_poses(world_from_cam: np.ndarray, scale: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Camera-to-world poses [..., 4, 4] expressed in the world ``X' = scale * R @ X + t``.

    The camera's orientation turns by ``R`` only and its centre maps like any point; the camera's
    own units are unchanged (depths along its axis scale by ``scale``). Stays rigid.
    """
    pose = np.array(world_from_cam, dtype=np.float64, copy=True)
    pose[..., :3, :3] = R @ pose[..., :3, :3]
    pose[..., :3, 3] = scale * pose[..., :3, 3] @ R.T + t
    return pose


def invert_similarity(scale: float, R: np.ndarray, t: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """The similarity undoing ``X' = scale * R @ X + t``: ``X = (1/scale) * R.T @ X' - R.T @ t / scale``."""
    return 1.0 / scale, R.T, -(R.T @ t) / scale


def corresponding_points(
    pixels_a: np.ndarray, pixels_b: np.ndarray, max_px: float = 0.75
) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of points of two reconstructions of the same photos that are the same scene point.

    Point ``a`` of one reconstruction and point ``b`` of the other correspond when ``b`` lies within
    ``max_px`` of ``a`` in every photo that observes ``a`` (at least two), and each is the other's
    nearest in that sense (so every point is used once at most).

    Args:
        pixels_a: [P, N, 2] where the N shared photos observe reconstruction a's points (NaN: unseen),
            e.g. :attr:`SparsePoints.pixels`.
        pixels_b: [Q, N, 2] where the same photos see reconstruction b's points (its points projected
            with its own cameras; NaN where unknown), same pixel grid.
    Returns:
        (index into a [M], index into b [M]).
    """
    pa, pb = np.asarray(pixels_a, np.float64), np.asarray(pixels_b, np.float64)
    if pa.ndim != 3 or pb.ndim != 3 or pa.shape[1:] != pb.shape[1:] or pa.shape[2] != 2:
        raise ValueError(f"need [P, N, 2] and [Q, N, 2] pixel arrays, got {pa.shape} and {pb.shape}")
    dist = np.full((len(pa), len(pb)), np.inf)  # worst distance over the photos observing a
    for start in range(0, len(pa), 512):  # chunks bound memory at [512, Q]
        block = pa[start : start + 512]
        d = np.linalg.norm(block[:, None] - pb[None], axis=-1)  # [B, Q, N]
        seen = ~np.isnan(block[:, :, 0])  # [B, N]
        d = np.where(seen[:, None], np.nan_to_num(d, nan=np.inf), 0.0).max(axis=2)
        d[seen.sum(1) < 2] = np.inf
        dist[start : start + 512] = d
    if dist.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    best_b, best_a = dist.argmin(axis=1), dist.argmin(axis=0)
    a = np.arange(len(pa))
    keep = (dist[a, best_b] <= max_px) & (best_a[best_b] == a)
    return a[keep], best_b[keep]


def register_camera(
    K: np.ndarray,
    width: int,
    height: int,
    points: np.ndarray,
    pixels: np.ndarray,
    max_error_px: float = 1.0,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Pose of a pinhole camera that sees the world ``points`` at ``pixels`` (absolute pose).

    pycolmap's LO-RANSAC P3P with non-linear refinement, as COLMAP registers a photo into a model.

    Args:
        K: [3, 3] intrinsics (cmc pixel convention) of a ``width`` x ``height`` image.
        points: [M, 3] world points; pixels: [M, 2] where the camera sees them.
        max_error_px: RANSAC inlier threshold in pixels.
    Returns:
        world_from_cam [4, 4], inlier mask [M].
    Raises:
        PoseEstimationError: fewer than 6 points, or no pose fits them.
    """
    pycolmap = import_pycolmap()
    X, uv = np.asarray(points, np.float64).reshape(-1, 3), np.asarray(pixels, np.float64).reshape(-1, 2)
    if len(X) != len(uv) or len(X) < 6:
        raise PoseEstimationError(f"need at least 6 matching points and pixels, got {len(X)} and {len(uv)}")
    camera = pycolmap.Camera.create_from_model_name(0, "PINHOLE", 1.0, int(width), int(height))
    camera.params = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
    options = pycolmap.AbsolutePoseEstimationOptions()
    options.ransac.max_error = max_error_px
    options.ransac.random_seed = seed
    found = pycolmap.estimate_and_refine_absolute_pose(uv, X, camera, options)
    if found is None or found["num_inliers"] < 6:
        raise PoseEstimationError(f"no camera pose fits these {len(X)} points within {max_error_px} px")
    return world_from_cam(found["cam_from_world"]), np.asarray(found["inlier_mask"], dtype=bool)
