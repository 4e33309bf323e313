"""Tests of aligning two reconstructions (cmc.eval.alignment):

* the similarity from cameras (``similarity_from_cameras``, ``apply_similarity_to_poses``): a known
  similarity applied to random cameras is recovered exactly, mapped poses stay rigid and keep their
  relative geometry, and the inverse undoes the mapping;
* registration through the structure: ``corresponding_points`` pairs the points two reconstructions
  see at the same pixels of the shared photos, ``register_camera`` recovers a known pose from points
  and pixels (outliers included), and the COLMAP readers give back what pycolmap wrote and the
  known fern model (skipped without the shared data).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from helpers import SHARED_DIR

from cmc.data.datasets import synthetic_cameras
from cmc.eval.alignment import (
    apply_similarity_to_poses,
    corresponding_points,
    invert_similarity,
    register_camera,
    similarity_from_cameras,
)
from cmc.geometry.cameras import Cameras, cameras_from_llff
from cmc.poses import PoseEstimationError, read_colmap_cameras, read_colmap_points

FERN_SPARSE = SHARED_DIR / "datasets" / "llff" / "fern" / "sparse" / "0"


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


# --- Registration through the structure ------------------------------------------------------


def scene_points(rng: np.random.Generator, count: int) -> np.ndarray:
    """[count, 3] points 2-8 units in front of ``synthetic_cameras``, inside their views."""
    z = rng.uniform(2.0, 8.0, count)
    return np.stack([rng.uniform(-0.4, 0.4, count) * z, rng.uniform(-0.3, 0.3, count) * z, z], 1)


def test_register_camera_recovers_a_known_pose_despite_outliers() -> None:
    rng = np.random.default_rng(0)
    cam = synthetic_cameras(3, 160, 120, baseline=0.6)[1]
    X = scene_points(rng, 300)
    uv, _ = cam.project(X)
    uv = uv[0] + rng.normal(scale=0.1, size=(300, 2))
    uv[:30] += rng.uniform(5, 40, size=(30, 2))  # 10 % wrong matches
    pose, inliers = register_camera(cam.K[0], cam.width, cam.height, X, uv)
    assert rotation_angle_deg(pose[:3, :3], cam.world_from_cam[0, :3, :3]) < 0.05
    assert np.linalg.norm(pose[:3, 3] - cam.world_from_cam[0, :3, 3]) < 0.01
    assert not inliers[:30].any() and inliers[30:].mean() > 0.95
    # a point lands where the registered camera must see it
    found = Cameras(cam.K, pose[None], cam.width, cam.height)
    assert np.abs(found.project(X[30:])[0][0] - uv[30:]).max() < 0.6
    with pytest.raises(PoseEstimationError, match="at least 6"):
        register_camera(cam.K[0], cam.width, cam.height, X[:5], uv[:5])


def test_corresponding_points_pairs_the_same_scene_points() -> None:
    rng = np.random.default_rng(1)
    cams = synthetic_cameras(3, 160, 120, baseline=0.6)
    X = scene_points(rng, 200)
    # reconstruction a: its points in another frame, observed with keypoint noise; a third of them
    # by one photo only (they cannot be paired), some not by the last photo
    seen = np.asarray(cams.project(X)[0]).transpose(1, 0, 2) + rng.normal(scale=0.1, size=(200, 3, 2))
    seen[:60, 1:] = np.nan
    seen[60:100, 2] = np.nan
    # reconstruction b: the same points shuffled, its own (exact) cameras, plus unrelated points
    extra = scene_points(rng, 150) + [0.0, 0.0, 0.5]
    order = rng.permutation(350)
    X_b = np.concatenate([X, extra])[order]
    pixels_b = np.asarray(cams.project(X_b)[0]).transpose(1, 0, 2)
    ia, ib = corresponding_points(seen, pixels_b, max_px=0.75)
    truth = np.argsort(order)[:200]  # where point k of X went in X_b
    assert set(ia) == set(range(60, 200))
    np.testing.assert_array_equal(ib, truth[ia])
    # nothing pairs with a tolerance below the keypoint noise; bad shapes are refused
    assert len(corresponding_points(seen, pixels_b, max_px=0.01)[0]) < 5
    with pytest.raises(ValueError, match="pixel arrays"):
        corresponding_points(seen, pixels_b[:, :2])


def test_colmap_readers_read_what_pycolmap_writes(tmp_path: Path) -> None:
    pycolmap = pytest.importorskip("pycolmap")
    model = pycolmap.Reconstruction()
    camera = pycolmap.Camera.create_from_model_name(3, "OPENCV", 100.0, 64, 48)
    camera.params = [101.0, 99.0, 31.5, 24.5, 0.01, -0.002, 0.0003, 0.0004]
    model.add_camera(camera)
    xyz = np.array([[1.0, 2.0, 3.0], [-1.0, 0.5, 7.0], [0.25, -4.0, 9.5]])
    for p in xyz:
        model.add_point3D(p, pycolmap.Track())
    model.write_binary(str(tmp_path))
    got = read_colmap_points(tmp_path / "points3D.bin")
    np.testing.assert_array_equal(got[np.argsort(got[:, 2])], xyz)
    (cam,) = read_colmap_cameras(tmp_path / "cameras.bin")
    assert (cam.model_name, cam.width, cam.height, cam.camera_id) == ("OPENCV", 64, 48, 3)
    np.testing.assert_array_equal(cam.params, camera.params)
    with pytest.raises(ValueError, match="not a COLMAP points3D.bin"):
        read_colmap_points(tmp_path / "cameras.bin")


@pytest.mark.skipif(not FERN_SPARSE.is_dir(), reason=f"shared dataset absent: {FERN_SPARSE}")
def test_fern_sparse_model_lies_in_the_dataset_frame() -> None:
    """The LLFF model (points3D.bin with tracks, cameras.bin, no images.bin) read as a known answer:
    its camera is the poses file's focal with radial distortion, and its points lie in front of
    every dataset camera within the depth bounds LLFF derived from them."""
    xyz = read_colmap_points(FERN_SPARSE / "points3D.bin")
    (camera,) = read_colmap_cameras(FERN_SPARSE / "cameras.bin")
    pb = np.load(FERN_SPARSE.parents[1] / "poses_bounds.npy")
    cams, bounds = cameras_from_llff(pb, 4032, 3024)
    assert len(xyz) == 10091 and camera.model_name == "SIMPLE_RADIAL"
    assert camera.params[0] == pytest.approx(cams.K[0, 0, 0], rel=1e-6) and 0 < camera.params[3] < 0.05
    _, depth = cams.project(xyz)  # [20, P]
    assert (depth > 0).mean() > 0.999
    lo, hi = np.percentile(depth, [1, 99], axis=1)
    assert (lo > 0.9 * bounds[:, 0]).all() and (hi < 1.1 * bounds[:, 1]).all()
