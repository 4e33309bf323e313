"""Aligning two reconstructions of the same photos (benchmarks against a dataset's own model; not
part of pose estimation): :func:`similarity_from_cameras` from their cameras, or through their 3D
points: :func:`corresponding_points` pairs the points both see at the same pixels, and
:func:`register_camera` finds the pose that sees given points at given pixels;
:func:`register_photo` registers a further photo into a reconstruction by SIFT matches to its photos.

Conventions are :mod:`cmc.geometry.cameras`' (OpenCV axes, camera-to-world [..., 4, 4], pixel corner at 0);
a similarity ``(scale, R [3, 3], t [3])`` maps ``X' = scale * R @ X + t``.
"""

from __future__ import annotations

import numpy as np

from cmc.errors import PoseEstimationError
from cmc.geometry.cameras import nearest_rotation
from cmc.poses.colmap import import_pycolmap, world_from_cam
from cmc.poses.intake import sift_options
from cmc.poses.options import SparsePoints


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


def sift_features(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """SIFT keypoints [M, 2] (cmc pixel convention, as COLMAP's) and unit descriptors [M, 128] of an
    [H, W, 3] image in [0, 1], as :mod:`cmc.poses` extracts them from a photo of that size (8-bit
    grey, :func:`~cmc.poses.intake.sift_options`)."""
    pycolmap = import_pycolmap()
    image = np.asarray(image, np.float32)
    grey = np.clip(np.rint(image @ np.array([0.299, 0.587, 0.114], np.float32) * 255), 0, 255).astype(np.uint8)
    options = sift_options(pycolmap, max(grey.shape), max(grey.shape))
    extractor = pycolmap.FeatureExtractor.create(options, pycolmap.Device.cpu)
    keypoints, descriptors = extractor.extract_from_uint8_array(np.ascontiguousarray(grey))
    xy = np.array([[k.x, k.y] for k in keypoints], np.float64).reshape(-1, 2)
    desc = np.asarray(descriptors.data, np.float32).reshape(-1, 128)
    return xy, desc / np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-12)


def mutual_matches(desc_a: np.ndarray, desc_b: np.ndarray, ratio: float = 0.8) -> np.ndarray:
    """[M, 2] index pairs of mutual nearest neighbours between unit descriptors [A, 128] and
    [B, 128] that pass Lowe's ratio test in both directions."""
    dist = np.sqrt(np.maximum(2 - 2 * desc_a @ desc_b.T, 0))
    if dist.shape[0] < 2 or dist.shape[1] < 2:
        return np.zeros((0, 2), np.int64)
    ab, ba = dist.argmin(1), dist.argmin(0)
    two_a = np.partition(dist, 1, axis=1)[:, :2]
    two_b = np.partition(dist, 1, axis=0)[:2]
    i = np.arange(len(desc_a))
    keep = (ba[ab] == i) & (two_a[:, 0] < ratio * two_a[:, 1]) & (two_b[0, ab] < ratio * two_b[1, ab])
    return np.stack([i[keep], ab[keep]], 1)


def register_photo(
    photo: np.ndarray,
    images: np.ndarray,
    sparse: SparsePoints,
    K: np.ndarray,
    max_px: float = 1.0,
    max_error_px: float = 2.0,
    seed: int = 0,
    image_features: list[tuple[np.ndarray, np.ndarray]] | None = None,
) -> tuple[np.ndarray, dict[str, int]]:
    """Pose of a further photo of a scene in the frame of its reconstruction from ``images``, as
    structure from motion registers a new photo into a model, the model left as it is.

    SIFT matches between ``photo`` and each of ``images``; a match whose keypoint in image k lies
    within ``max_px`` of where image k observes one of ``sparse``'s points gives that point's
    pixel in ``photo``; the pose is :func:`register_camera`'s on those pairs, with the intrinsics
    ``K`` the photos share.

    Args:
        photo: [H, W, 3] in [0, 1], the size of ``images`` [N, H, W, 3] (the reconstruction's
            working images, whose pixels ``sparse.pixels`` [P, N, 2] are in).
        K: [3, 3] the reconstruction's intrinsics.
        image_features: :func:`sift_features` of each of ``images``, for a caller registering
            several photos into one reconstruction; computed here when not given.
    Returns:
        world_from_cam [4, 4], and counts: matches to a point, distinct points, RANSAC inliers.
    Raises:
        PoseEstimationError: too few matches to the points, or no pose fits them.
        ValueError: a photo of another size than the images, or points seen in another number of photos.
    """
    images = np.asarray(images)
    if images.ndim != 4 or np.asarray(photo).shape != images.shape[1:] or sparse.pixels.shape[1] != len(images):
        raise ValueError(
            f"need a photo [H, W, 3] the size of images [N, H, W, 3] and points seen in N photos, got "
            f"{np.asarray(photo).shape}, {images.shape} and {sparse.pixels.shape}"
        )
    height, width = images.shape[1:3]
    if image_features is None:
        image_features = [sift_features(image) for image in images]
    kp_photo, desc_photo = sift_features(photo)
    points, pixels = [], []
    for k, (kp, desc) in enumerate(image_features):
        seen = np.flatnonzero(sparse.seen_by(k))
        if len(seen) == 0:
            continue
        m = mutual_matches(desc_photo, desc)
        d = np.linalg.norm(kp[m[:, 1], None] - sparse.pixels[seen, k][None], axis=-1)  # [M, seen]
        nearest = d.argmin(1)
        on_point = d[np.arange(len(m)), nearest] <= max_px
        points.append(sparse.xyz[seen[nearest[on_point]]])
        pixels.append(kp_photo[m[on_point, 0]])
    pairs = np.concatenate([np.c_[X, uv] for X, uv in zip(points, pixels, strict=True)]) if points else np.zeros((0, 5))
    pairs = np.unique(pairs, axis=0)  # one point matched to one pixel through several images counts once
    X, uv = pairs[:, :3], pairs[:, 3:]
    pose, inliers = register_camera(K, width, height, X, uv, max_error_px=max_error_px, seed=seed)
    distinct = len(np.unique(X, axis=0))
    return pose, {"matches": len(X), "points": distinct, "inliers": int(inliers.sum())}
