"""Camera paths: known answers for the mean camera, orbit, dolly and spiral."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import rigid, rotation

from cmc.data.datasets import synthetic_cameras
from cmc.geometry.camera_paths import camera_path, capture_radius, mean_pose, orbit_path, orbit_poses

NEAR, FAR = 1.6, 6.6


@pytest.fixture()
def cams():
    return synthetic_cameras(3, 64, 48)


def _is_rotation(R):
    return np.allclose(R.T @ R, np.eye(3), atol=1e-9) and np.isclose(np.linalg.det(R), 1.0)


def test_mean_pose_of_symmetric_cameras():
    """Two cameras turned +-10 degrees about y around a shared axis: the mean looks straight
    ahead from the midpoint."""
    a = rigid(rotation([0, 1, 0], np.radians(10)), [0.2, 0.0, 1.0])
    b = rigid(rotation([0, 1, 0], -np.radians(10)), [-0.2, 0.0, 1.0])
    m = mean_pose(np.stack([a, b]))
    assert np.allclose(m[:3, :3], np.eye(3), atol=1e-12)
    assert np.allclose(m[:3, 3], [0.0, 0.0, 1.0])
    assert np.isclose(capture_radius(np.stack([a, b])), 0.2)


def test_orbit_is_a_circle_in_the_mean_image_plane(cams):
    P = cams.world_from_cam
    mean, r = mean_pose(P), 0.5 * capture_radius(P)
    path = camera_path("orbit", P, NEAR, FAR, 16)
    assert path.shape == (16, 4, 4)
    off = (path[:, :3, 3] - mean[:3, 3]) @ mean[:3, :3]  # offsets in the mean camera's axes
    assert np.allclose(np.linalg.norm(off[:, :2], axis=1), r)
    assert np.allclose(off[:, 2], 0.0, atol=1e-12)
    assert np.allclose(off[0], [r, 0.0, 0.0]) and np.allclose(off[4], [0.0, r, 0.0])  # starts at +x, turns to +y
    assert np.allclose(path[:, :3, :3], mean[:3, :3])  # everything looks the way the mean camera looks
    assert np.allclose(orbit_poses(cams, 16), path) and np.allclose(orbit_path(P, 16, 0.5), path)


def test_dolly_moves_along_the_mean_axis_within_the_near_bound(cams):
    P = cams.world_from_cam
    mean = mean_pose(P)
    path = camera_path("dolly", P, NEAR, FAR, 20)
    off = path[:, :3, 3] - mean[:3, 3]
    along = off @ mean[:3, 2]
    assert np.allclose(off, along[:, None] * mean[:3, 2])  # on the optical axis
    amp = min(capture_radius(P), NEAR / 4)
    assert np.isclose(along.max(), amp) and np.isclose(along.min(), -amp)  # forward and back, bounded
    assert np.allclose(path[:, :3, :3], mean[:3, :3])
    near_bound = camera_path("dolly", P, 0.2, FAR, 20)[:, :3, 3] - mean[:3, 3]
    assert np.abs(near_bound @ mean[:3, 2]).max() <= 0.05 + 1e-12  # a close near plane caps it at near / 4


def test_spiral_looks_at_the_focus_point_from_within_the_baseline(cams):
    P = cams.world_from_cam
    mean = mean_pose(P)
    path = camera_path("spiral", P, NEAR, FAR, 30)
    focus = mean[:3, 3] + (1 / (0.25 / NEAR + 0.75 / FAR)) * mean[:3, 2]
    for pose in path:
        assert _is_rotation(pose[:3, :3])
        to_focus = focus - pose[:3, 3]
        assert np.allclose(pose[:3, 2], to_focus / np.linalg.norm(to_focus))  # optical axis through the focus
        assert pose[:3, 2] @ mean[:3, 2] > np.cos(np.radians(5))  # looks (almost) the mean camera's way
    off = (path[:, :3, 3] - mean[:3, 3]) @ mean[:3, :3]
    assert np.linalg.norm(off[:, :2], axis=1).max() <= capture_radius(P) + 1e-9
    assert np.abs(off[:, 2]).max() <= NEAR / 4
    assert (np.linalg.norm(np.diff(path[:, :3, 3], axis=0), axis=1) > 1e-3).all()  # every frame moves


def test_single_frame_and_bad_arguments(cams):
    P = cams.world_from_cam
    assert camera_path("orbit", P, NEAR, FAR, 1).shape == (1, 4, 4)
    with pytest.raises(ValueError, match="unknown camera path"):
        camera_path("zoom", P, NEAR, FAR, 4)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="near < far"):
        camera_path("spiral", P, 2.0, 1.0, 4)
    with pytest.raises(ValueError, match="at least 1 frame"):
        camera_path("dolly", P, NEAR, FAR, 0)
