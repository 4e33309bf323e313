"""Camera paths through a forward-facing capture: spiral, orbit and dolly.

Conventions: :mod:`cmc.geometry.cameras` (OpenCV axes x right, y down, z forward; camera-to-world poses
``world_from_cam``). Every path is built around the *mean camera* of the inputs (centre = mean
of the input centres, rotation = the mean of the input rotations projected onto SO(3)) and stays
within the capture's baseline, where per-view MPIs are trustworthy:

* ``orbit``: a circle in the mean camera's image plane (its x/y axes) about the mean centre,
  radius half the capture radius (the largest distance of an input centre from the mean centre,
  measured in that plane); orientation fixed to the mean camera's.
* ``spiral``: LLFF's render path (``render_path_spiral``): two turns of an ellipse in the mean
  camera's x/y plane with radii the 90th percentile of the input centres' offsets along each
  axis, while moving forward and back along z at half the angular rate; each frame looks at the
  focus point on the mean optical axis at LLFF's focus depth ``1 / (0.25 / near + 0.75 / far)``.
* ``dolly``: forward and back along the mean viewing direction, ``s(t) = A sin(2 pi t)``, with
  amplitude the capture radius, at most a quarter of ``near`` so the camera never comes close to
  the nearest plane; orientation fixed.

All paths are closed loops (the frame after the last would be the first), so videos loop.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from cmc.geometry.cameras import Cameras, look_at, nearest_rotation

PathKind = Literal["spiral", "orbit", "dolly"]
PATH_KINDS: tuple[str, ...] = ("spiral", "orbit", "dolly")


def mean_pose(world_from_cam: np.ndarray) -> np.ndarray:
    """[4, 4] the mean camera of [N, 4, 4] poses: mean centre, mean rotation projected onto SO(3)."""
    P = np.asarray(world_from_cam, dtype=np.float64)
    pose = np.eye(4)
    pose[:3, :3] = nearest_rotation(P[:, :3, :3].mean(0))
    pose[:3, 3] = P[:, :3, 3].mean(0)
    return pose


def center_offsets(world_from_cam: np.ndarray) -> np.ndarray:
    """[N, 3] input centres relative to the mean centre, in the mean camera's axes (x, y, z)."""
    P = np.asarray(world_from_cam, dtype=np.float64)
    mean = mean_pose(P)
    return (P[:, :3, 3] - mean[:3, 3]) @ mean[:3, :3]


def capture_radius(world_from_cam: np.ndarray) -> float:
    """Largest distance of an input centre from the mean centre in the mean camera's x/y plane
    (scene units); the scale of every path. Falls back to the 3D distance, then to 1e-3, for
    degenerate captures (cameras on the optical axis or sharing a centre)."""
    off = center_offsets(world_from_cam)
    r = float(np.linalg.norm(off[:, :2], axis=1).max(initial=0.0))
    if r <= 1e-9:
        r = float(np.linalg.norm(off, axis=1).max(initial=0.0))
    return max(r, 1e-3)


def _with_center(mean: np.ndarray, offset_cam: np.ndarray) -> np.ndarray:
    p = mean.copy()
    p[:3, 3] = mean[:3, 3] + mean[:3, :3] @ offset_cam
    return p


def _angles(num_frames: int, turns: float = 1.0) -> np.ndarray:
    return np.linspace(0.0, 2 * np.pi * turns, num_frames, endpoint=False)


def orbit_path(world_from_cam: np.ndarray, num_frames: int, radius_fraction: float = 0.5) -> np.ndarray:
    """[F, 4, 4] a circle in the mean camera's image plane, radius ``radius_fraction`` times
    :func:`capture_radius`, starting on the mean camera's +x side; orientation the mean camera's."""
    mean = mean_pose(world_from_cam)
    r = radius_fraction * capture_radius(world_from_cam)
    return np.stack([_with_center(mean, np.array([r * np.cos(a), r * np.sin(a), 0.0])) for a in _angles(num_frames)])


def camera_path(kind: PathKind, world_from_cam: np.ndarray, near: float, far: float, num_frames: int) -> np.ndarray:
    """[F, 4, 4] camera-to-world poses (OpenCV axes) of a closed path through the capture.

    Args:
        kind: ``"spiral"``, ``"orbit"`` or ``"dolly"`` (module docstring).
        world_from_cam: [N, 4, 4] input cameras; near, far: scene depth bounds (scene units).
        num_frames: F >= 1.
    """
    P = np.asarray(world_from_cam, dtype=np.float64)
    if P.ndim != 3 or P.shape[1:] != (4, 4) or len(P) == 0:
        raise ValueError(f"world_from_cam must have shape [N, 4, 4] with N >= 1, got {list(P.shape)}")
    if not (np.isfinite(near) and np.isfinite(far)) or not 0 < near < far:
        raise ValueError(f"need 0 < near < far, got near={near}, far={far}")
    if int(num_frames) < 1:
        raise ValueError(f"need at least 1 frame, got {num_frames}")
    num_frames = int(num_frames)
    if kind == "orbit":
        return orbit_path(P, num_frames)
    mean = mean_pose(P)
    radius = capture_radius(P)
    if kind == "dolly":
        amp = min(radius, 0.25 * near)
        return np.stack([_with_center(mean, np.array([0.0, 0.0, amp * np.sin(a)])) for a in _angles(num_frames)])
    if kind == "spiral":
        rads = np.percentile(np.abs(center_offsets(P)), 90, axis=0)
        rx, ry = max(rads[0], 0.25 * rads[1], 0.1 * radius), max(rads[1], 0.25 * rads[0], 0.1 * radius)
        rz = min(max(rads[2], 0.25 * max(rx, ry)), 0.25 * near)
        focus = 1.0 / (0.25 / near + 0.75 / far)
        target = mean[:3, :3] @ np.array([0.0, 0.0, focus]) + mean[:3, 3]
        down = mean[:3, 1]
        poses = []
        for a in _angles(num_frames, turns=2.0):
            c = mean[:3, :3] @ np.array([rx * np.cos(a), -ry * np.sin(a), rz * np.sin(0.5 * a)]) + mean[:3, 3]
            poses.append(look_at(c, target, down))
        return np.stack(poses)
    raise ValueError(f"unknown camera path {kind!r}; use one of {', '.join(PATH_KINDS)}")


def baked_path_cameras(manifest: dict, kind: PathKind, num_frames: int) -> Cameras:
    """The cameras of a path through a baked scene, from its ``mpi.json`` alone (no torch).

    Args:
        manifest: the parsed ``mpi.json`` of a ``cmc-mpi`` folder (cmc.serving.baking).
        kind, num_frames: as in :func:`camera_path`.
    Returns:
        F cameras at the input image size: the first MPI's intrinsics and :func:`camera_path`
        through the MPIs' reference cameras and depth range (the videos' cameras,
        :func:`cmc.serving.video.path_cameras`, at that size).
    """
    refs = np.array([m["world_from_cam"] for m in manifest["mpis"]], dtype=np.float64)
    poses = camera_path(kind, refs, float(manifest["near"]), float(manifest["far"]), num_frames)
    K = np.asarray(manifest["mpis"][0]["K"], dtype=np.float64)
    return Cameras(np.repeat(K[None], len(poses), axis=0), poses, int(manifest["width"]), int(manifest["height"]))


def orbit_poses(cameras: Cameras, num_frames: int, radius_fraction: float = 0.5) -> np.ndarray:
    """[F, 4, 4] the orbit path (:func:`orbit_path`) of a batch of cameras."""
    return orbit_path(cameras.world_from_cam, num_frames, radius_fraction)
