"""Tests of the similarity alignment of two reconstructions (cmc.poses.similarity_from_cameras and
apply_similarity_to_poses): a known similarity applied to random cameras is recovered exactly, mapped
poses stay rigid and keep their relative geometry (rotations, centre distances up to the scale), and
the inverse undoes the mapping."""

from __future__ import annotations

import numpy as np
import pytest

from cmc.poses import apply_similarity_to_poses, invert_similarity, similarity_from_cameras


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def random_cameras(rng: np.random.Generator, n: int) -> np.ndarray:
    poses = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        poses[i, :3, :3] = random_rotation(rng)
        poses[i, :3, 3] = rng.normal(scale=3.0, size=3)
    return poses


@pytest.mark.parametrize("n", [2, 3, 5])
def test_known_similarity_is_recovered(n: int) -> None:
    rng = np.random.default_rng(n)
    src = random_cameras(rng, n)
    scale, R, t = 0.37, random_rotation(rng), rng.normal(size=3) * 10
    dst = apply_similarity_to_poses(src, scale, R, t)
    s_est, R_est, t_est = similarity_from_cameras(src, dst)
    assert s_est == pytest.approx(scale, rel=1e-12)
    np.testing.assert_allclose(R_est, R, atol=1e-12)
    np.testing.assert_allclose(t_est, t, atol=1e-10)
    np.testing.assert_allclose(apply_similarity_to_poses(src, s_est, R_est, t_est), dst, atol=1e-10)


def test_mapped_poses_keep_relative_geometry() -> None:
    rng = np.random.default_rng(7)
    src = random_cameras(rng, 4)
    scale, R, t = 2.5, random_rotation(rng), rng.normal(size=3)
    dst = apply_similarity_to_poses(src, scale, R, t)
    rot = dst[:, :3, :3]
    np.testing.assert_allclose(np.einsum("nji,njk->nik", rot, rot), np.broadcast_to(np.eye(3), (4, 3, 3)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-12)
    np.testing.assert_allclose(dst[:, 3], np.tile([0, 0, 0, 1.0], (4, 1)))
    for i in range(4):
        for j in range(4):
            rel_src = np.linalg.inv(src[i]) @ src[j]
            rel_dst = np.linalg.inv(dst[i]) @ dst[j]
            np.testing.assert_allclose(rel_dst[:3, :3], rel_src[:3, :3], atol=1e-12)  # same relative rotation
            np.testing.assert_allclose(rel_dst[:3, 3], scale * rel_src[:3, 3], atol=1e-10)  # baseline x scale
    # a world point seen by a camera keeps its pixel: camera coordinates scale by `scale` only
    X = rng.normal(size=3)
    X_dst = scale * R @ X + t
    cam_src = np.linalg.inv(src[0]) @ np.append(X, 1)
    cam_dst = np.linalg.inv(dst[0]) @ np.append(X_dst, 1)
    np.testing.assert_allclose(cam_dst[:3], scale * cam_src[:3], atol=1e-10)


def test_inverse_undoes_the_mapping() -> None:
    rng = np.random.default_rng(3)
    src = random_cameras(rng, 3)
    sim = (0.8, random_rotation(rng), rng.normal(size=3))
    back = apply_similarity_to_poses(apply_similarity_to_poses(src, *sim), *invert_similarity(*sim))
    np.testing.assert_allclose(back, src, atol=1e-12)


def small_rotation(rng: np.random.Generator, degrees: float) -> np.ndarray:
    """Rotation by ``degrees`` about a random axis (Rodrigues)."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    a = np.radians(degrees)
    return np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * k @ k


def rotation_angle_deg(A: np.ndarray, B: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(A.T @ B) - 1) / 2, -1, 1))))


def test_noisy_cameras_give_a_close_similarity() -> None:
    rng = np.random.default_rng(11)
    src = random_cameras(rng, 3)
    scale, R, t = 1.7, random_rotation(rng), rng.normal(size=3)
    noisy = apply_similarity_to_poses(src, scale, R, t)
    for i in range(3):
        noisy[i, :3, :3] = small_rotation(rng, 0.1) @ noisy[i, :3, :3]
        noisy[i, :3, 3] += 1e-3 * rng.normal(size=3)
    s_est, R_est, _ = similarity_from_cameras(src, noisy)
    assert abs(s_est / scale - 1) < 1e-3
    assert rotation_angle_deg(R_est, R) < 0.1


def test_bad_input_is_refused() -> None:
    same = np.tile(np.eye(4), (3, 1, 1))
    with pytest.raises(ValueError, match="coincide"):
        similarity_from_cameras(same, same)
    with pytest.raises(ValueError, match="same N"):
        similarity_from_cameras(same, same[:2])
