"""Tests of cmc.geometry.cameras: LLFF and transforms.json converters (round trips and hand-computed axes),
projection known answers, scaling, and the errors bad camera input must raise.

The real LLFF file lives in the shared folder: ``$CMC_SHARED_DIR`` or else ``../shared`` next to the
repository; the test that needs it is skipped when it is absent.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from helpers import SHARED_DIR, rigid, rotation

from cmc.data.datasets import load_llff
from cmc.geometry.cameras import (
    CameraError,
    CameraFile,
    Cameras,
    camera_file_from_dict,
    camera_file_to_dict,
    camera_from_frame,
    cameras_from_llff,
    cameras_to_llff,
    convert_pose,
    intrinsics,
    load_camera_file,
    save_camera_file,
)

FERN_POSES = SHARED_DIR / "datasets" / "llff" / "fern" / "poses_bounds.npy"

# LLFF's full-resolution iPhone X size and focal (fern), and the few-shot protocol's resolution.
FULL_H, FULL_W, FULL_F = 3024.0, 4032.0, 3260.5
SMALL_W, SMALL_H = 504, 378


def random_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    """[n, 4, 4] camera-to-world poses with arbitrary (not small) rotations."""
    rotations = [rotation(rng.normal(size=3), rng.uniform(0.1, 3.0)) for _ in range(n)]
    return np.stack([rigid(R, rng.normal(size=3)) for R in rotations])


def synthetic_poses_bounds(rng: np.random.Generator, n: int = 5) -> np.ndarray:
    """[n, 17] LLFF rows built by hand from OpenCV poses: columns [down, right, backwards] = [y, x, -z]."""
    rows = []
    for pose in random_poses(rng, n):
        R, t = pose[:3, :3], pose[:3, 3]
        m = np.stack([R[:, 1], R[:, 0], -R[:, 2], t, [FULL_H, FULL_W, FULL_F]], axis=1)  # [3, 5]
        near = rng.uniform(1.0, 3.0)
        rows.append(np.concatenate([m.reshape(-1), [near, near * rng.uniform(5.0, 20.0)]]))
    return np.stack(rows)


def make_cameras(rng: np.random.Generator, n: int = 3, width: int = 64, height: int = 48) -> Cameras:
    K = np.stack(
        [
            intrinsics(rng.uniform(40, 80), rng.uniform(40, 80), rng.uniform(20, 40), rng.uniform(15, 30))
            for _ in range(n)
        ]
    )
    return Cameras(K, random_poses(rng, n), width, height)


def assert_same_cameras(a: Cameras, b: Cameras, atol: float = 1e-12) -> None:
    assert (a.width, a.height) == (b.width, b.height)
    np.testing.assert_allclose(a.K, b.K, atol=atol, rtol=0)
    np.testing.assert_allclose(a.world_from_cam, b.world_from_cam, atol=atol, rtol=0)


# --- LLFF ---------------------------------------------------------------------------------


def test_llff_axes_hand_computed() -> None:
    """A hand-written LLFF row: down = -Z, right = +Y, backwards = +X (the camera looks along -X)."""
    down, right, back = np.array([0.0, 0, -1]), np.array([0.0, 1, 0]), np.array([1.0, 0, 0])
    centre = np.array([1.0, 2.0, 3.0])
    m = np.stack([down, right, back, centre, [FULL_H, FULL_W, FULL_F]], axis=1)
    pb = np.concatenate([m.reshape(-1), [2.0, 50.0]])[None]
    cams, bounds = cameras_from_llff(pb, SMALL_W, SMALL_H)
    pose = cams.world_from_cam[0]
    np.testing.assert_array_equal(pose[:3, 0], right)  # x = right column
    np.testing.assert_array_equal(pose[:3, 1], down)  # y = down column
    np.testing.assert_array_equal(pose[:3, 2], -back)  # z = -backwards column
    np.testing.assert_array_equal(pose[:3, 3], centre)
    np.testing.assert_array_equal(bounds, [[2.0, 50.0]])
    K = cams.K[0]
    assert K[0, 0] == pytest.approx(FULL_F * SMALL_W / 4032)
    assert K[1, 1] == pytest.approx(FULL_F * SMALL_H / 3024)
    assert (K[0, 2], K[1, 2]) == (SMALL_W / 2, SMALL_H / 2) == (252.0, 189.0)
    # The camera looks along world -X: 5 units ahead lands on the principal point; one unit to the
    # camera's right (world +Y) moves right in the image; world -Z is down in the image.
    f = FULL_F / 8
    uv, depth = cams.project(np.array([centre + [-5, 0, 0], centre + [-4, 1, 0], centre + [-4, 0, -2]]))
    np.testing.assert_allclose(uv[0], [[252, 189], [252 + f / 4, 189], [252, 189 + f * 2 / 4]], atol=1e-9)
    np.testing.assert_allclose(depth[0], [5, 4, 4], atol=1e-12)


def test_llff_synthetic_columns_and_intrinsics() -> None:
    pb = synthetic_poses_bounds(np.random.default_rng(0))
    cams, bounds = cameras_from_llff(pb, SMALL_W, SMALL_H)
    m = pb[:, :15].reshape(-1, 3, 5)
    np.testing.assert_allclose(cams.world_from_cam[:, :3, 0], m[:, :, 1], atol=1e-15)
    np.testing.assert_allclose(cams.world_from_cam[:, :3, 1], m[:, :, 0], atol=1e-15)
    np.testing.assert_allclose(cams.world_from_cam[:, :3, 2], -m[:, :, 2], atol=1e-15)
    np.testing.assert_allclose(cams.world_from_cam[:, :3, 3], m[:, :, 3], atol=1e-15)
    np.testing.assert_allclose(cams.world_from_cam[:, 3], np.tile([0, 0, 0, 1.0], (len(pb), 1)))
    np.testing.assert_allclose(np.linalg.det(cams.world_from_cam[:, :3, :3]), 1.0, atol=1e-12)
    np.testing.assert_array_equal(bounds, pb[:, 15:])
    np.testing.assert_allclose(cams.K[:, 0, 0], FULL_F * 504 / 4032)
    np.testing.assert_allclose(cams.K[:, 1, 1], FULL_F * 378 / 3024)
    np.testing.assert_allclose(cams.K[:, 0, 2], 252.0)
    np.testing.assert_allclose(cams.K[:, 1, 2], 189.0)
    assert (cams.width, cams.height) == (SMALL_W, SMALL_H)


def _check_llff_round_trip(pb: np.ndarray) -> None:
    # Full resolution: the array comes back unchanged, hwf included.
    cams, bounds = cameras_from_llff(pb, int(FULL_W), int(FULL_H))
    np.testing.assert_allclose(cameras_to_llff(cams, bounds), pb, atol=1e-9, rtol=0)
    # Reduced resolution: poses and bounds come back unchanged, hwf describes the reduced images,
    # and reading that back gives the same cameras.
    small, bounds = cameras_from_llff(pb, SMALL_W, SMALL_H)
    pb_small = cameras_to_llff(small, bounds)
    assert pb_small.shape == pb.shape
    m, m_small = pb.reshape(-1, 17)[:, :15].reshape(-1, 3, 5), pb_small[:, :15].reshape(-1, 3, 5)
    np.testing.assert_allclose(m_small[:, :, :4], m[:, :, :4], atol=1e-12, rtol=0)
    np.testing.assert_array_equal(m_small[:, 0, 4], SMALL_H)
    np.testing.assert_array_equal(m_small[:, 1, 4], SMALL_W)
    np.testing.assert_allclose(m_small[:, 2, 4], m[:, 2, 4] * SMALL_W / FULL_W, rtol=1e-12)
    np.testing.assert_array_equal(pb_small[:, 15:], pb[:, 15:])
    again, bounds_again = cameras_from_llff(pb_small, SMALL_W, SMALL_H)
    assert_same_cameras(again, small, atol=1e-9)
    np.testing.assert_array_equal(bounds_again, bounds)


def test_llff_round_trip_synthetic() -> None:
    _check_llff_round_trip(synthetic_poses_bounds(np.random.default_rng(1), n=7))


@pytest.mark.skipif(not FERN_POSES.is_file(), reason=f"{FERN_POSES} not found (set CMC_SHARED_DIR)")
def test_llff_round_trip_real_fern() -> None:
    pb = np.load(FERN_POSES)
    assert pb.shape == (20, 17)
    _check_llff_round_trip(pb)
    cams, bounds = cameras_from_llff(pb, SMALL_W, SMALL_H)
    f = pb[:, 14]
    np.testing.assert_allclose(cams.K[:, 0, 0], f * 504 / 4032)
    np.testing.assert_allclose(cams.K[:, 0, 2], 252.0)
    np.testing.assert_allclose(cams.K[:, 1, 2], 189.0)
    # Fern's cameras all look the same way (forward-facing capture): every optical axis is within
    # 30 degrees of their mean, and the scene (at the near bound) lies in front of every camera.
    z = cams.world_from_cam[:, :3, 2]
    mean_z = z.mean(0) / np.linalg.norm(z.mean(0))
    assert (z @ mean_z > math.cos(math.radians(30))).all()
    ahead = cams.centers.mean(0) + mean_z * bounds[:, 0].min() * 1.5
    _, depth = cams.project(ahead[None])
    assert (depth > 0).all()


@pytest.mark.skipif(not FERN_POSES.is_file(), reason=f"{FERN_POSES} not found (set CMC_SHARED_DIR)")
def test_llff_split_holds_train_test_and_validation_views() -> None:
    """RegNeRF's split of fern (20 images): test every 8th, 3 training views evenly from the rest,
    and the validation views (neither) that may choose settings; each image in one set."""
    split = load_llff(FERN_POSES.parent)
    assert split.test_ids == [0, 8, 16] and split.train_ids == [1, 10, 19]
    assert split.val_ids == [2, 3, 4, 5, 6, 7, 9, 11, 12, 13, 14, 15, 17, 18]
    assert split.val is not None and len(split.val) == 14 and split.val.names[1] == "image003.png"
    every = load_llff(FERN_POSES.parent, num_train=17)  # every image but the test views trains
    assert every.val is None
    np.testing.assert_array_equal(split.val.cameras.world_from_cam[1], every.train.cameras.world_from_cam[2])
    np.testing.assert_array_equal(split.val.images[1], every.train.images[2])


def test_llff_rejects_bad_shape() -> None:
    with pytest.raises(CameraError, match=r"\[N, 17\]"):
        cameras_from_llff(np.zeros((3, 15)), SMALL_W, SMALL_H)


def test_llff_export_rejects_off_centre_principal_point_x() -> None:
    cams = Cameras(intrinsics(100.0, 100.0, 40.0, 24.0), np.eye(4), 64, 48)
    with pytest.raises(CameraError, match="centred principal point"):
        cameras_to_llff(cams, np.array([[1.0, 10.0]]))


def test_llff_export_rejects_off_centre_principal_point_y() -> None:
    cams = Cameras(intrinsics(100.0, 100.0, 32.0, 30.0), np.eye(4), 64, 48)
    with pytest.raises(CameraError, match="centred principal point"):
        cameras_to_llff(cams, np.array([[1.0, 10.0]]))


def test_llff_export_rejects_unequal_focals() -> None:
    cams = Cameras(intrinsics(100.0, 90.0, 32.0, 24.0), np.eye(4), 64, 48)
    with pytest.raises(CameraError, match="one focal"):
        cameras_to_llff(cams, np.array([[1.0, 10.0]]))


# --- transforms.json --------------------------------------------------------------------------


@pytest.mark.parametrize("convention", ["opengl", "opencv"])
@pytest.mark.parametrize("with_bounds", [True, False])
def test_camera_file_round_trip(convention: str, with_bounds: bool, tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    cams = make_cameras(rng, n=4)
    near_far = np.stack([rng.uniform(0.5, 1.0, 4), rng.uniform(5.0, 9.0, 4)], 1) if with_bounds else None
    cf = CameraFile(cams, [f"images/{i:03d}.png" for i in range(4)], near_far)
    data = camera_file_to_dict(cf, convention)  # type: ignore[arg-type]
    assert data["convention"] == convention
    assert (data["w"], data["h"]) == (64, 48)
    # What the file stores: OpenCV poses verbatim, OpenGL poses with the y and z axes negated.
    stored = np.array([fr["transform_matrix"] for fr in data["frames"]])
    flip = np.array([1.0, -1.0, -1.0, 1.0]) if convention == "opengl" else np.ones(4)
    np.testing.assert_array_equal(stored, cams.world_from_cam * flip)
    # Through JSON text, the dict reader and the file reader.
    back = camera_file_from_dict(json.loads(json.dumps(data)))
    path = tmp_path / "transforms.json"
    save_camera_file(cf, path, convention)  # type: ignore[arg-type]
    for cf2 in (back, load_camera_file(path)):
        assert_same_cameras(cf2.cameras, cams, atol=0)
        assert cf2.file_paths == cf.file_paths
        if with_bounds:
            np.testing.assert_array_equal(cf2.near_far, near_far)
        else:
            assert cf2.near_far is None


def test_opengl_camera_hand_computed() -> None:
    """An OpenGL camera with identity rotation looks down world -z with world +y up."""
    centre = [1.0, 2.0, 3.0]
    data = {
        "w": 64,
        "h": 48,
        "fl_x": 50.0,
        "fl_y": 60.0,
        "cx": 30.0,
        "cy": 20.0,
        "frames": [{"file_path": "a.png", "transform_matrix": rigid(np.eye(3), centre).tolist()}],
    }
    for d in (data, {**data, "convention": "opengl"}):  # opengl is the default
        cams = camera_file_from_dict(d).cameras
        np.testing.assert_array_equal(cams.world_from_cam[0, :3, 2], [0, 0, -1])  # +z(cv) = -z(gl)
        np.testing.assert_array_equal(cams.world_from_cam[0, :3, 1], [0, -1, 0])  # down = -up
        np.testing.assert_array_equal(cams.world_from_cam[0, :3, 0], [1, 0, 0])
        np.testing.assert_array_equal(cams.world_from_cam[0, :3, 3], centre)
        uv, depth = cams.project(np.array([[1.0, 2.0, -2.0], [2.0, 4.0, -1.0]]))
        np.testing.assert_allclose(uv[0], [[30, 20], [30 + 50 * 1 / 4, 20 - 60 * 2 / 4]], atol=1e-12)
        np.testing.assert_allclose(depth[0], [5, 4], atol=1e-12)
    # The same file in OpenCV convention: the camera looks down world +z.
    cams = camera_file_from_dict({**data, "convention": "opencv"}).cameras
    np.testing.assert_array_equal(cams.world_from_cam[0], rigid(np.eye(3), centre))


def test_convert_pose_is_an_involution() -> None:
    pose = random_poses(np.random.default_rng(3), 3)
    gl = convert_pose(pose, "opencv", "opengl")
    np.testing.assert_array_equal(gl[:, :3, 0], pose[:, :3, 0])
    np.testing.assert_array_equal(gl[:, :3, 1:3], -pose[:, :3, 1:3])
    np.testing.assert_array_equal(gl[:, :3, 3], pose[:, :3, 3])
    np.testing.assert_array_equal(convert_pose(gl, "opengl", "opencv"), pose)
    np.testing.assert_array_equal(convert_pose(pose, "opencv", "opencv"), pose)


def test_camera_file_defaults_and_overrides() -> None:
    data = {
        "w": 64,
        "h": 48,
        "fl_x": 50.0,
        "convention": "opencv",
        "frames": [
            {"file_path": "a.png", "transform_matrix": np.eye(4).tolist()},
            {"file_path": "b.png", "fl_x": 70.0, "cy": 10.0, "transform_matrix": np.eye(4)[:3].tolist()},
        ],
    }
    cams = camera_file_from_dict(data).cameras
    np.testing.assert_array_equal(cams.K[0], intrinsics(50, 50, 32, 24))  # fl_y = fl_x, centred
    np.testing.assert_array_equal(cams.K[1], intrinsics(70, 70, 32, 10))  # per-frame override
    np.testing.assert_array_equal(cams.world_from_cam[1], np.eye(4))  # 3x4 accepted


# --- Cameras ------------------------------------------------------------------------------------


def test_project_known_answers() -> None:
    K = np.stack([intrinsics(50.0, 60.0, 31.0, 22.0), intrinsics(80.0, 70.0, 30.0, 25.0)])
    poses = random_poses(np.random.default_rng(4), 2)
    cams = Cameras(K, poses, 64, 48)
    for n in range(2):
        on_axis = poses[n, :3, 3] + 5 * poses[n, :3, 2]
        cam_point = (poses[n] @ [1.0, 2.0, 4.0, 1.0])[:3]
        uv, depth = cams.project(np.stack([on_axis, cam_point]))
        assert uv.shape == (2, 2, 2) and depth.shape == (2, 2)
        fx, fy, cx, cy = K[n, 0, 0], K[n, 1, 1], K[n, 0, 2], K[n, 1, 2]
        np.testing.assert_allclose(uv[n], [[cx, cy], [fx * 1 / 4 + cx, fy * 2 / 4 + cy]], atol=1e-9)
        np.testing.assert_allclose(depth[n], [5, 4], atol=1e-12)


def test_cameras_accessors() -> None:
    cams = make_cameras(np.random.default_rng(5), n=3)
    assert len(cams) == 3
    identity = np.tile(np.eye(4), (3, 1, 1))
    np.testing.assert_allclose(cams.cam_from_world @ cams.world_from_cam, identity, atol=1e-12)
    np.testing.assert_array_equal(cams.centers, cams.world_from_cam[:, :3, 3])
    one = cams[1]
    assert len(one) == 1 and one.K.shape == (1, 3, 3)
    np.testing.assert_array_equal(one.world_from_cam[0], cams.world_from_cam[1])
    assert len(cams[[0, 2]]) == 2


def test_scaled_halves_intrinsics() -> None:
    cams = make_cameras(np.random.default_rng(6), n=2, width=64, height=48)
    half = cams.scaled(32, 24)
    assert (half.width, half.height) == (32, 24)
    expected = cams.K.copy()
    expected[:, :2] /= 2
    np.testing.assert_allclose(half.K, expected, atol=1e-12)
    assert (half.K[:, 2] == [0, 0, 1]).all()
    np.testing.assert_array_equal(half.world_from_cam, cams.world_from_cam)
    points = np.random.default_rng(7).normal(size=(5, 3)) + cams.centers.mean(0)
    np.testing.assert_allclose(half.project(points)[0], cams.project(points)[0] / 2, atol=1e-9)


def test_scaled_anisotropic() -> None:
    cams = Cameras(intrinsics(50.0, 60.0, 32.0, 24.0), np.eye(4), 64, 48)
    other = cams.scaled(32, 12)
    np.testing.assert_allclose(other.K[0], intrinsics(25.0, 15.0, 16.0, 6.0), atol=1e-12)
    # The image corners stay the image corners (pixel-corner convention).
    corner = np.array([[64 / 50 * 1.0 - 32 / 50, 48 / 60 - 24 / 60, 1.0]])  # projects to (64, 48)
    np.testing.assert_allclose(cams.project(corner)[0][0, 0], [64, 48], atol=1e-12)
    np.testing.assert_allclose(other.project(corner)[0][0, 0], [32, 12], atol=1e-12)


# --- errors -----------------------------------------------------------------------------------


def _pose_with(row: int, col: int, value: float) -> np.ndarray:
    pose = np.eye(4)
    pose[row, col] = value
    return pose


@pytest.mark.parametrize(
    ("K", "pose", "message"),
    [
        (intrinsics(50, 50, 32, 24), _pose_with(1, 2, np.nan), r"poses of camera\(s\) \[0\] contain NaN"),
        (intrinsics(50, 50, 32, 24), rigid(np.eye(3), [0, np.inf, 0]), r"poses .*NaN or infinity"),
        (intrinsics(np.nan, 50, 32, 24), np.eye(4), r"intrinsics .*NaN"),
        (intrinsics(50, 50, 32, 24), _pose_with(0, 0, 2.0), "not a proper rotation"),
        (intrinsics(50, 50, 32, 24), np.diag([1.0, 1.0, -1.0, 1.0]), "not a proper rotation"),  # reflection
        (intrinsics(-50, 50, 32, 24), np.eye(4), r"focal lengths of camera\(s\) \[0\] must be"),
        (intrinsics(50, 0, 32, 24), np.eye(4), "focal lengths .* must be"),
        (intrinsics(1e-300, 50, 32, 24), np.eye(4), "focal lengths .* must be"),  # K underflows to singular
        (intrinsics(50, 1e300, 32, 24), np.eye(4), "focal lengths .* must be"),
        (intrinsics(2, 50, 32, 24), np.eye(4), "focal lengths .* must be"),  # a 172 degree field of view
        (intrinsics(50, 50, 1e300, 24), np.eye(4), "principal point"),
        (intrinsics(50, 50, 32, -1000), np.eye(4), "principal point"),
        (intrinsics(50, 50, 32, 24), _pose_with(3, 0, 0.5), r"last row \[0, 0, 0, 1\]"),
        (np.eye(4), np.eye(4), r"\[N, 3, 3\]"),
        (np.stack([intrinsics(50, 50, 32, 24)] * 2), np.eye(4), "2 intrinsics but 1 poses"),
    ],
)
def test_cameras_reject_bad_parameters(K: np.ndarray, pose: np.ndarray, message: str) -> None:
    with pytest.raises(CameraError, match=message):
        Cameras(K, pose, 64, 48)


def test_cameras_reject_bad_size() -> None:
    with pytest.raises(CameraError, match="image size must be positive"):
        Cameras(intrinsics(50, 50, 32, 24), np.eye(4), 0, 48)


def _file(**top) -> dict:
    default = [
        {"file_path": "a.png", "transform_matrix": np.eye(4).tolist()},
        {"file_path": "b.png", "transform_matrix": rigid(np.eye(3), [1, 0, 0]).tolist()},
    ]
    frames = top.pop("frames", default)
    return {"w": 64, "h": 48, "fl_x": 50.0, **top, "frames": frames}


def _frame(**kw) -> dict:
    return {"file_path": "c.png", "transform_matrix": np.eye(4).tolist(), **kw}


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (_file(frames=[_frame(transform_matrix=np.full((4, 4), np.nan).tolist())]), r"poses .*NaN"),
        (
            _file(frames=[_frame(transform_matrix=np.diag([1.0, 3.0, 1.0, 1.0]).tolist())]),
            "not a proper rotation",
        ),
        (_file(fl_x=-50.0), "focal lengths .* must be"),
        (_file(fl_x="fifty"), r"'fl_x' must be a number"),
        (_file(fl_x=float("nan")), r"'fl_x' is not finite"),
        (_file(frames=[_frame(), _frame(w=32)]), r"frame 1: size 32x48 differs from 64x48"),
        (_file(frames=[_frame(), {"file_path": "x.png"}]), r"frame 1: missing 'transform_matrix'"),
        (_file(frames=[_frame(transform_matrix=[[1, 0], [0, 1]])]), r"'transform_matrix' must be 4x4"),
        (
            _file(frames=[_frame(transform_matrix=[[1, 0, 0, 0], [0, 1]])]),
            r"'transform_matrix' must be a 4x4",
        ),
        (_file(frames=[{"transform_matrix": np.eye(4).tolist()}]), r"frame 0: missing 'file_path'"),
        (_file(convention="blender"), r"unknown pose convention 'blender'"),
        (_file(near=5.0, far=5.0), r"need 0 < near < far"),
        (_file(near=6.0, far=2.0), r"need 0 < near < far"),
        (_file(near=-1.0, far=2.0), r"need 0 < near < far"),
        (_file(frames=[_frame(near=1.0, far=2.0), _frame()]), "near/far for every frame or for none"),
        (_file(frames=[_frame(near=1.0)]), r"frame 0: missing 'far'"),
        (_file(frames=[]), "non-empty 'frames' list"),
        (_file(frames=[3]), "frame 0: must be an object"),
        ({"w": 64, "h": 48, "fl_x": 50.0}, "non-empty 'frames' list"),
        ({"h": 48, "fl_x": 50.0, "frames": [_frame()]}, r"frame 0: missing 'w'"),
        ({"w": 64, "h": 48, "frames": [_frame()]}, r"frame 0: missing 'fl_x'"),
        ([1, 2], "must be a JSON object"),
    ],
)
def test_camera_file_rejects_bad_input(data: dict, message: str) -> None:
    with pytest.raises(CameraError, match=message):
        camera_file_from_dict(data)


def test_convert_pose_rejects_unknown_convention() -> None:
    with pytest.raises(CameraError, match="unknown pose convention 'z_up'"):
        convert_pose(np.eye(4), "opencv", "z_up")  # type: ignore[arg-type]


def test_load_camera_file_errors(tmp_path: Path) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text('{"frames": [')
    with pytest.raises(CameraError, match="is not valid JSON"):
        load_camera_file(bad)
    with pytest.raises(CameraError, match="not found"):
        load_camera_file(tmp_path / "missing.json")


def test_load_camera_file_rejects_binary_file(tmp_path: Path) -> None:
    bad = tmp_path / "transforms.json"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe")
    with pytest.raises(CameraError, match="not valid JSON"):
        load_camera_file(bad)


def test_coverage_of_a_sideways_view_of_a_wall() -> None:
    """One input camera at the origin looking along +z at a wall z = 4; a target camera moved
    0.5 to the right sees the wall's points u + f * 0.5 / 4 in the input image, so its last
    f * 0.5 / 4 = 10 columns (and nothing else) lie outside it. No surface, or a point behind
    the input camera, is never covered."""
    W, H, f = 64, 48, 80.0
    K = intrinsics(f, f, W / 2, H / 2)
    inputs = Cameras(K, np.eye(4), W, H)
    target = rigid(np.eye(3), [0.5, 0.0, 0.0])
    depth = np.full((H, W), 4.0)
    seen = inputs.coverage(K, target, depth)
    assert seen.shape == (H, W)
    assert seen[:, : W - 10].all() and not seen[:, W - 10 :].any()
    depth[:5] = 0.0  # no surface
    assert not inputs.coverage(K, target, depth)[:5].any()
    behind = rigid(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, 0.0])  # looking along -z
    assert not inputs.coverage(K, behind, np.full((H, W), 4.0)).any()


def test_camera_from_frame_reads_one_camera_as_the_cameras_file_does():
    """A render request's camera (intrinsics and pose in one frame, OpenGL by default): the same
    camera the cameras file gives for that frame; errors name the field without a frame number."""
    pose = rigid(np.eye(3), [0.5, -1, 2]).tolist()
    frame = {"w": 64, "h": 48, "fl_x": 50.0, "fl_y": 52.0, "cx": 30.0, "cy": 25.0, "transform_matrix": pose}
    one = camera_from_frame(frame)
    ref = camera_file_from_dict({**frame, "frames": [{"file_path": "x", "transform_matrix": pose}]}).cameras
    assert (one.width, one.height) == (64, 48)
    np.testing.assert_allclose(one.K, ref.K)
    np.testing.assert_allclose(one.world_from_cam, ref.world_from_cam)
    opencv = camera_from_frame({**frame, "convention": "opencv"})
    np.testing.assert_allclose(opencv.world_from_cam[0], np.asarray(pose))
    with pytest.raises(CameraError, match=r"^missing 'fl_x'$"):
        camera_from_frame({k: v for k, v in frame.items() if k != "fl_x"})
    with pytest.raises(CameraError, match=r"^'transform_matrix' must be 4x4, got \[2, 2\]$"):
        camera_from_frame({**frame, "transform_matrix": [[1, 0], [0, 1]]})
