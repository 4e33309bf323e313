"""Tests of cmc.geometry.planes: plane depths, plane-induced homographies (checked against explicit 3D
projection), virtual poses and blend weights."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from helpers import apply_homography, rigid, rotation

from cmc.geometry.cameras import intrinsics
from cmc.geometry.planes import (
    blend_weights,
    content_plane_depths,
    homographies_ref_from_tgt,
    mean_baseline,
    pixel_centers,
    plane_depths,
    sample_virtual_pose,
)


def random_pair(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """K_ref, world_from_ref, K_tgt, world_from_tgt: an arbitrary reference pose and a target a few
    degrees and a fraction of the near depth away, with different intrinsics."""
    K_ref = intrinsics(*rng.uniform(40, 80, 2), *rng.uniform(25, 35, 2))
    K_tgt = intrinsics(*rng.uniform(40, 80, 2), *rng.uniform(25, 35, 2))
    world_from_ref = rigid(rotation(rng.normal(size=3), rng.uniform(0, math.pi)), rng.normal(size=3))
    small_rotation = rotation(rng.normal(size=3), math.radians(rng.uniform(2, 8)))
    ref_from_tgt = rigid(small_rotation, rng.uniform(-0.4, 0.4, 3))
    return K_ref, world_from_ref, K_tgt, world_from_ref @ ref_from_tgt


def project(K: np.ndarray, cam_from_world: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates [P, 2] and depth [P] of world points X [P, 3]."""
    Xc = X @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    p = Xc @ K.T
    return p[:, :2] / p[:, 2:3], Xc[:, 2]


def t64(a) -> torch.Tensor:
    return torch.as_tensor(np.asarray(a), dtype=torch.float64)


# --- plane_depths ----------------------------------------------------------------------------------


def test_plane_depths_uniform_in_disparity() -> None:
    d = plane_depths(1.5, 40.0, 7)
    assert d.shape == (7,)
    assert d[0] == pytest.approx(1.5, rel=1e-14) and d[-1] == pytest.approx(40.0, rel=1e-14)
    assert (np.diff(d) > 0).all()  # nearest first
    np.testing.assert_allclose(np.diff(1 / d), (1 / 40.0 - 1 / 1.5) / 6, rtol=1e-12)
    np.testing.assert_allclose(plane_depths(2.0, 8.0, 4), [2.0, 8 / 3, 4.0, 8.0], rtol=1e-14)
    np.testing.assert_allclose(plane_depths(1.0, 2.0, 2), [1.0, 2.0])


@pytest.mark.parametrize(
    ("near", "far", "n", "message"),
    [
        (2.0, 1.0, 4, "near < far"),
        (1.0, 1.0, 4, "near < far"),
        (0.0, 1.0, 4, "near < far"),
        (-1.0, 1.0, 4, "near < far"),
        (float("nan"), 1.0, 4, "near < far"),
        (1.0, float("nan"), 4, "near < far"),
        (1.0, float("inf"), 4, "near < far"),
        (1.0, 2.0, 1, "at least 2 planes"),
        (1.0, 2.0, 0, "at least 2 planes"),
    ],
)
def test_plane_depths_rejects(near: float, far: float, n: int, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        plane_depths(near, far, n)


def _cells(D: int) -> np.ndarray:
    """Width of the disparity interval nearest each of D uniform planes (ends half as wide)."""
    return np.diff(np.concatenate([[0.0], (np.arange(D - 1) + 0.5) / (D - 1), [1.0]]))


def test_content_plane_depths_follow_the_scene() -> None:
    near, far, D = 1.0, 10.0, 12
    uniform = plane_depths(near, far, D)
    # Surfaces spread evenly in disparity (each plane's share its interval): the uniform planes.
    np.testing.assert_allclose(content_plane_depths(near, far, _cells(D), 0.25), uniform, rtol=1e-12)
    # floor 1: uniform whatever the scene
    peaked = np.full(D, 1e-3)
    peaked[4] = 1.0
    np.testing.assert_allclose(content_plane_depths(near, far, peaked, 1.0), uniform, rtol=1e-12)
    for floor in (0.5, 0.25):
        d = content_plane_depths(near, far, peaked, floor)
        assert d[0] == near and d[-1] == far and (np.diff(d) > 0).all()
        spacing = np.diff(1 / d) / np.diff(1 / uniform)  # relative to the uniform spacing
        # crowded about the surface at uniform plane 4 (disparity interval [3.5, 4.5] / 11) ...
        t = (1 / d - 1 / near) / (1 / far - 1 / near) * (D - 1)
        assert ((t > 3.5) & (t < 4.5)).sum() >= 3
        assert spacing.min() < 0.5
        # ... and nowhere sparser than 1 / floor times the uniform spacing
        assert spacing.max() <= 1 / floor + 1e-9


def test_content_plane_depths_bring_surfaces_nearer_a_plane() -> None:
    """The claim of the cube-root law: surfaces, on average, lie nearer their nearest plane."""
    near, far, D = 1.5, 12.0, 16
    rng = np.random.default_rng(0)
    surfaces = np.concatenate([rng.uniform(2.0, 2.6, 300), rng.uniform(5.0, 6.0, 600), [11.0] * 100])
    disp = lambda z: (1 / np.asarray(z) - 1 / near) / (1 / far - 1 / near)  # noqa: E731

    def rms_to_nearest_plane(depths: np.ndarray) -> float:
        return float(np.sqrt(np.mean(np.min(np.abs(disp(surfaces)[:, None] - disp(depths)[None]), 1) ** 2)))

    # the density a plane sweep would report: each surface counted at its nearest uniform plane
    counts = np.bincount(np.abs(disp(surfaces)[:, None] - np.linspace(0, 1, D)).argmin(1), minlength=D)
    uniform = rms_to_nearest_plane(plane_depths(near, far, D))
    assert rms_to_nearest_plane(content_plane_depths(near, far, counts + 1e-3, 0.25)) < 0.7 * uniform


@pytest.mark.parametrize(
    ("density", "floor", "message"),
    [
        (np.ones(4), 0.0, "floor"),
        (np.ones(4), 1.5, "floor"),
        (np.zeros(4), 0.5, "not all zero"),
        (np.array([1.0, -1.0, 1.0, 1.0]), 0.5, "non-negative"),
        (np.array([1.0, np.nan, 1.0, 1.0]), 0.5, "finite"),
    ],
)
def test_content_plane_depths_rejects(density: np.ndarray, floor: float, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        content_plane_depths(1.0, 5.0, density, floor)


# --- homographies ----------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(6))
def test_homography_maps_target_projection_to_reference_projection(seed: int) -> None:
    """THE key test: a point on reference plane k, seen at p_t in the target, maps to its reference pixel."""
    rng = np.random.default_rng(seed)
    K_ref, world_from_ref, K_tgt, world_from_tgt = random_pair(rng)
    ref_from_world, tgt_from_world = np.linalg.inv(world_from_ref), np.linalg.inv(world_from_tgt)
    depths = plane_depths(2.0, 25.0, 6)
    args = (K_ref, ref_from_world, K_tgt, world_from_tgt, depths)
    H = homographies_ref_from_tgt(*map(t64, args))
    assert H.shape == (6, 3, 3) and H.dtype == torch.float64
    for k, z in enumerate(depths):
        uv_ref = rng.uniform([0, 0], [64, 48], size=(20, 2))
        X_ref = z * np.concatenate([uv_ref, np.ones((20, 1))], 1) @ np.linalg.inv(K_ref).T  # z_ref = depth[k]
        np.testing.assert_allclose(X_ref[:, 2], z)
        X_world = X_ref @ world_from_ref[:3, :3].T + world_from_ref[:3, 3]
        p_t, z_t = project(K_tgt, tgt_from_world, X_world)
        assert (z_t > 0).all()
        # The target projection is genuinely different from the reference one (a non-trivial test).
        assert np.abs(p_t - uv_ref).max() > 1.0
        mapped, valid = apply_homography(H[k : k + 1], t64(p_t))
        assert mapped.shape == (20, 1, 2) and valid.all()
        np.testing.assert_allclose(mapped[:, 0].numpy(), uv_ref, atol=1e-3, rtol=0)
        # And the plane the point is not on maps it elsewhere (wrong-plane sanity check).
        other = (k + 3) % len(depths)
        wrong, _ = apply_homography(H[other : other + 1], t64(p_t))
        assert np.abs(wrong[:, 0].numpy() - uv_ref).max() > 0.1


def test_homography_float32_close_to_float64() -> None:
    K_ref, world_from_ref, K_tgt, world_from_tgt = random_pair(np.random.default_rng(10))
    args = (K_ref, np.linalg.inv(world_from_ref), K_tgt, world_from_tgt, plane_depths(2.0, 25.0, 5))
    H64 = homographies_ref_from_tgt(*map(t64, args))
    H32 = homographies_ref_from_tgt(*(torch.as_tensor(a, dtype=torch.float32) for a in args))
    assert H32.dtype == torch.float32
    uv = t64(np.random.default_rng(11).uniform(0, 48, size=(30, 2)))
    a, _ = apply_homography(H64, uv)
    b, _ = apply_homography(H32, uv.float())
    np.testing.assert_allclose(b.double().numpy(), a.numpy(), atol=2e-3)


def test_homography_identity_when_target_is_reference() -> None:
    K_ref, world_from_ref, _, _ = random_pair(np.random.default_rng(12))
    depths = t64(plane_depths(1.0, 100.0, 8))
    H = homographies_ref_from_tgt(
        t64(K_ref), t64(np.linalg.inv(world_from_ref)), t64(K_ref), t64(world_from_ref), depths
    )
    np.testing.assert_allclose(H.numpy(), np.tile(np.eye(3), (8, 1, 1)), atol=1e-10)


def test_homography_pure_rotation_is_depth_independent() -> None:
    """A target rotating about the reference centre sees every plane through K_ref R K_tgt^-1."""
    rng = np.random.default_rng(13)
    K_ref, K_tgt = intrinsics(50, 55, 30, 20), intrinsics(70, 65, 33, 26)
    R = rotation([0.3, 1.0, -0.2], math.radians(6))
    world_from_ref = rigid(rotation(rng.normal(size=3), 1.0), rng.normal(size=3))
    world_from_tgt = world_from_ref @ rigid(R, [0, 0, 0])
    H = homographies_ref_from_tgt(
        t64(K_ref),
        t64(np.linalg.inv(world_from_ref)),
        t64(K_tgt),
        t64(world_from_tgt),
        t64(plane_depths(1, 50, 5)),
    )
    expected = K_ref @ R @ np.linalg.inv(K_tgt)
    np.testing.assert_allclose(H.numpy(), np.tile(expected, (5, 1, 1)), atol=1e-12)


def test_homography_sideways_translation_known_disparity() -> None:
    """Target moved right by tx: target pixel u sees reference pixel u + fx * tx / z (same K)."""
    K = intrinsics(50.0, 50.0, 32.0, 24.0)
    tx = 0.6
    depths = np.array([2.0, 3.0, 5.0, 10.0])
    world_from_tgt = rigid(np.eye(3), [tx, 0, 0])
    H = homographies_ref_from_tgt(t64(K), t64(np.eye(4)), t64(K), t64(world_from_tgt), t64(depths))
    uv = t64([[10.5, 7.5], [40.0, 30.0]])
    mapped, valid = apply_homography(H, uv)
    assert valid.all()
    expected = uv.numpy()[:, None] + np.stack([50.0 * tx / depths, np.zeros(4)], -1)[None]
    np.testing.assert_allclose(mapped.numpy(), expected, atol=1e-12)


def test_homography_batched_matches_loop() -> None:
    rng = np.random.default_rng(14)
    pairs = [random_pair(rng) for _ in range(3)]
    K_ref = t64(np.stack([p[0] for p in pairs]))  # [3, 3, 3]
    ref_from_world = t64(np.stack([np.linalg.inv(p[1]) for p in pairs]))
    K_tgt = t64(np.stack([p[2] for p in pairs]))
    world_from_tgt = t64(np.stack([p[3] for p in pairs]))
    depths = t64(np.stack([plane_depths(1.0 + b, 20.0 + b, 4) for b in range(3)]))  # [3, 4]
    H = homographies_ref_from_tgt(K_ref, ref_from_world, K_tgt, world_from_tgt, depths)
    assert H.shape == (3, 4, 3, 3)
    uv = t64(rng.uniform(0, 60, size=(3, 7, 2)))
    mapped, valid = apply_homography(H, uv)
    assert mapped.shape == (3, 7, 4, 2) and valid.shape == (3, 7, 4)
    for b in range(3):
        Hb = homographies_ref_from_tgt(K_ref[b], ref_from_world[b], K_tgt[b], world_from_tgt[b], depths[b])
        torch.testing.assert_close(H[b], Hb, rtol=0, atol=1e-12)
        mb, vb = apply_homography(Hb, uv[b])
        torch.testing.assert_close(mapped[b], mb, rtol=0, atol=1e-10)
        assert torch.equal(valid[b], vb)
        for k in range(4):  # one plane at a time
            Hbk = homographies_ref_from_tgt(
                K_ref[b], ref_from_world[b], K_tgt[b], world_from_tgt[b], depths[b, k : k + 1]
            )
            torch.testing.assert_close(H[b, k], Hbk[0], rtol=0, atol=1e-12)
    # Shared reference intrinsics and depths broadcast against batched poses.
    Hs = homographies_ref_from_tgt(K_ref[0], ref_from_world, K_ref[0], world_from_tgt, depths[0])
    assert Hs.shape == (3, 4, 3, 3)
    for b in range(3):
        Hb = homographies_ref_from_tgt(K_ref[0], ref_from_world[b], K_ref[0], world_from_tgt[b], depths[0])
        torch.testing.assert_close(Hs[b], Hb, rtol=0, atol=1e-12)


def test_apply_homography_flags_points_behind() -> None:
    H = torch.stack([torch.eye(3), torch.diag(torch.tensor([1.0, 1.0, -1.0])), 2 * torch.eye(3)])
    uv = torch.tensor([[3.0, 4.0], [-1.0, 2.5]])
    mapped, valid = apply_homography(H, uv)
    assert mapped.shape == (2, 3, 2)
    assert valid.tolist() == [[True, False, True], [True, False, True]]
    torch.testing.assert_close(mapped[:, 0], uv)
    torch.testing.assert_close(mapped[:, 2], uv)  # homogeneous scale does not matter
    assert torch.isfinite(mapped).all()


# --- pixels and rays -------------------------------------------------------------------------------


def test_pixel_centers() -> None:
    uv = pixel_centers(3, 2)
    assert uv.shape == (6, 2)
    assert uv.tolist() == [[0.5, 0.5], [1.5, 0.5], [2.5, 0.5], [0.5, 1.5], [1.5, 1.5], [2.5, 1.5]]


def _input_poses() -> np.ndarray:
    base = rotation([0.2, 1.0, 0.1], 0.5)
    return np.stack(
        [
            rigid(base @ rotation([0, 1, 0], math.radians(-8)), [-1.0, 0.1, 0.0]),
            rigid(base @ rotation([1, 0, 0], math.radians(5)), [0.0, -0.2, 0.3]),
            rigid(base @ rotation([0, 1, 1], math.radians(10)), [1.2, 0.0, -0.1]),
        ]
    )


def _angle(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return math.acos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1, 1))


def test_sample_virtual_pose_is_proper_and_near_inputs() -> None:
    poses = _input_poses()
    centers = poses[:, :3, 3]
    centroid = centers.mean(0)
    radius = np.linalg.norm(centers - centroid, axis=1).max()
    baseline = mean_baseline(centers)
    max_angle = max(_angle(a[:3, :3], b[:3, :3]) for a in poses for b in poses)
    rng = np.random.default_rng(20)
    samples = [sample_virtual_pose(poses, rng, jitter=0.1) for _ in range(200)]
    for pose in samples:
        assert pose.shape == (4, 4)
        np.testing.assert_array_equal(pose[3], [0, 0, 0, 1])
        R = pose[:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
        assert np.linalg.norm(pose[:3, 3] - centroid) < radius + 6 * 0.1 * baseline
        assert min(_angle(R, p[:3, :3]) for p in poses) <= max_angle
    # Not all the same: the samples spread over the inputs.
    spread = np.ptp(np.stack([p[:3, 3] for p in samples]), axis=0)
    assert spread[0] > 1.0


def test_sample_virtual_pose_proper_for_opposed_rotations() -> None:
    """Half-turns about x, y and z: their weighted mean is often a reflection (det < 0), which must
    still come back as a proper rotation."""
    poses = np.stack([rigid(rotation(axis, math.pi), axis) for axis in np.eye(3)])
    rng = np.random.default_rng(21)
    for _ in range(40):
        R = sample_virtual_pose(poses, rng)[:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-9)


def test_sample_virtual_pose_deterministic() -> None:
    poses = _input_poses()
    a = sample_virtual_pose(poses, np.random.default_rng(7))
    b = sample_virtual_pose(poses, np.random.default_rng(7))
    c = sample_virtual_pose(poses, np.random.default_rng(8))
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)


def test_sample_virtual_pose_known_answers() -> None:
    poses = _input_poses()
    # One camera and no jitter: the camera itself.
    one = sample_virtual_pose(poses[:1], np.random.default_rng(0), jitter=0.0)
    np.testing.assert_allclose(one, poses[0], atol=1e-12)
    # Cameras sharing a rotation, no jitter: that rotation, and a centre inside the triangle.
    same = poses.copy()
    same[:, :3, :3] = poses[0, :3, :3]
    pose = sample_virtual_pose(same, np.random.default_rng(1), jitter=0.0)
    np.testing.assert_allclose(pose[:3, :3], poses[0, :3, :3], atol=1e-12)
    w = np.linalg.lstsq(np.vstack([same[:, :3, 3].T, np.ones(3)]), np.append(pose[:3, 3], 1.0), rcond=None)[0]
    assert (w > -1e-9).all() and w.sum() == pytest.approx(1.0)


# --- blend weights ---------------------------------------------------------------------------------


def test_blend_weights() -> None:
    centers = t64([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 3.0, 0.0]])
    w = blend_weights(centers, t64([0.5, 0.2, 0.0]), baseline=2.0)
    assert w.shape == (3,)
    assert float(w.sum()) == pytest.approx(1.0, abs=1e-12)
    assert int(w.argmax()) == 0 and (w > 0).all()
    # Known answer: inverse squared distance with eps = (0.1 * baseline)^2 + 1e-12.
    mu = np.array([0.5**2 + 0.2**2, 1.5**2 + 0.2**2, 0.5**2 + 2.8**2])
    inv = 1 / (mu + 0.04 + 1e-12)
    np.testing.assert_allclose(w.numpy(), inv / inv.sum(), rtol=1e-12)
    # At an input camera: finite, and that camera dominates.
    w0 = blend_weights(centers, centers[1], baseline=2.0)
    assert torch.isfinite(w0).all() and float(w0[1]) > 0.95
    # Equal distances give equal weights.
    square = t64([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])
    we = blend_weights(square, t64([0.0, 0.0, 0.7]), baseline=1.5)
    np.testing.assert_allclose(we.numpy(), 0.25, atol=1e-12)


def test_mean_baseline() -> None:
    assert mean_baseline(np.zeros((1, 3))) == 1.0
    assert mean_baseline(np.array([[0.0, 0, 0], [1.0, 0, 0], [3.0, 0, 0]])) == pytest.approx(2.0)
    tri = np.array([[0.0, 0, 0], [1.0, 0, 0], [0.5, math.sqrt(3) / 2, 0]])
    assert mean_baseline(torch.as_tensor(tri)) == pytest.approx(1.0)
