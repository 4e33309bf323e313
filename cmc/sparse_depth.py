"""Sparse depth of the input views: SIFT features matched between every pair of input photos and
triangulated with the known cameras. Training can pull each MPI's rendered depth towards these
points (``LossConfig.lambda_sparse_depth``, :func:`cmc.losses.sparse_depth_loss`): geometry that
the photos fix by distinctive features, where photometric training alone may drift.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cmc.datasets import Scene


@dataclass(frozen=True)
class ViewPoints:
    """Triangulated points seen by one input view: uv [P, 2] pixel coordinates (cmc convention,
    pixel corners at integers) and depth [P] (that camera's z, scene units)."""

    uv: np.ndarray
    depth: np.ndarray


def _features(image: np.ndarray, max_features: int) -> tuple[np.ndarray, np.ndarray]:
    """SIFT keypoints [M, 2] (COLMAP's convention: pixel corners at integers, as cmc's) and unit
    descriptors [M, 128] of an [H, W, 3] image in [0, 1]."""
    import pycolmap

    options = pycolmap.FeatureExtractionOptions()
    options.sift.max_num_features = max_features
    gray = (image @ np.array([0.299, 0.587, 0.114]) * 255 + 0.5).clip(0, 255).astype(np.uint8)
    keypoints, desc = pycolmap.Sift(options, pycolmap.Device.cpu).extract(np.ascontiguousarray(gray))
    desc = desc.astype(np.float32)
    return keypoints[:, :2].astype(np.float64), desc / np.linalg.norm(desc, axis=1, keepdims=True).clip(1e-12)


def _mutual_matches(d_a: np.ndarray, d_b: np.ndarray, ratio: float) -> np.ndarray:
    """[M, 2] index pairs: mutual nearest neighbours passing Lowe's ratio test both ways."""
    sim = d_a @ d_b.T
    dist = np.sqrt(np.maximum(2 - 2 * sim, 0))
    if dist.shape[0] < 2 or dist.shape[1] < 2:
        return np.zeros((0, 2), dtype=int)
    ab = np.argsort(dist, axis=1)[:, :2]
    ba = np.argsort(dist, axis=0)[:2].T
    rows = np.arange(len(d_a))
    ok = dist[rows, ab[:, 0]] < ratio * dist[rows, ab[:, 1]]
    cols = np.arange(len(d_b))
    ok_b = dist[ba[:, 0], cols] < ratio * dist[ba[:, 1], cols]
    mutual = ba[ab[:, 0], 0] == rows
    keep = ok & mutual & ok_b[ab[:, 0]]
    return np.stack([rows[keep], ab[keep, 0]], axis=1)


def triangulated_points(
    scene: Scene, max_error_px: float = 1.0, ratio: float = 0.8, max_features: int = 4096
) -> list[ViewPoints]:
    """Per input view, the points triangulated from its matches with every other view.

    A match is kept when it reprojects within ``max_error_px`` in both views and lies in front of
    both between 0.9 near and 1.1 far.
    """
    from cmc.poses import triangulate_pair

    feats = [_features(img, max_features) for img in scene.images]
    uv: list[list[np.ndarray]] = [[] for _ in feats]
    z: list[list[np.ndarray]] = [[] for _ in feats]
    for i in range(len(feats)):
        for j in range(i + 1, len(feats)):
            m = _mutual_matches(feats[i][1], feats[j][1], ratio)
            if len(m) == 0:
                continue
            uv_i, uv_j = feats[i][0][m[:, 0]], feats[j][0][m[:, 1]]
            _, depth, err = triangulate_pair(scene.cameras, i, j, uv_i, uv_j)
            ok = (err < max_error_px) & (depth > 0.9 * scene.near).all(1) & (depth < 1.1 * scene.far).all(1)
            uv[i].append(uv_i[ok])
            z[i].append(depth[ok, 0])
            uv[j].append(uv_j[ok])
            z[j].append(depth[ok, 1])
    return [
        ViewPoints(np.concatenate(u) if u else np.zeros((0, 2)), np.concatenate(d) if d else np.zeros(0))
        for u, d in zip(uv, z, strict=True)
    ]
