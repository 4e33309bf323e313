"""Pinhole cameras and the one camera convention of this project.

Convention (used everywhere inside ``cmc``; converters below are the only exceptions):

* Camera axes are OpenCV's: x right, y down, z forward (the camera looks along +z).
* Poses are camera-to-world rigid transforms named ``world_from_cam`` ([..., 4, 4]):
  ``X_world = world_from_cam @ X_cam`` for homogeneous column vectors.
* Intrinsics ``K`` ([..., 3, 3]) are in pixels. Continuous pixel coordinates put the image's
  top-left corner at (0, 0) and its bottom-right corner at (width, height), so the centre of
  pixel (col j, row i) is (j + 0.5, i + 0.5). This is what ``grid_sample(align_corners=False)``
  assumes, and what LLFF's ``cx = W / 2`` means.
* Scene units are whatever the poses are in; depth is the camera-space z (not ray length).

Converters: LLFF ``poses_bounds.npy`` ([down, right, backwards] axes) and nerfstudio-style
``transforms.json`` (OpenGL axes x right, y up, z backwards, as ARKit/ARCore give them, or OpenCV
axes when the file says ``"convention": "opencv"``).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from cmc.errors import CameraError

PoseConvention = Literal["opencv", "opengl"]

# Focal lengths in image widths (fl_x) / heights (fl_y): fields of view from about 169 down to 0.6 degrees.
FOCAL_RATIO = (0.05, 100.0)
# How far (in image sizes) the principal point may be from the image centre.
MAX_PRINCIPAL_OFFSET = 10.0

# Flips the y and z camera axes: maps OpenCV camera coordinates to OpenGL ones and back.
_CV_GL_FLIP = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class Cameras:
    """A batch of N pinhole cameras sharing one image size.

    Attributes:
        K: [N, 3, 3] float64 intrinsics in pixels (convention in the module docstring).
        world_from_cam: [N, 4, 4] float64 camera-to-world, OpenCV camera axes.
        width, height: image size in pixels.
    """

    K: np.ndarray
    world_from_cam: np.ndarray
    width: int
    height: int

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        pose = np.asarray(self.world_from_cam, dtype=np.float64)
        if K.ndim == 2:
            K = K[None]
        if pose.ndim == 2:
            pose = pose[None]
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "world_from_cam", pose)
        validate_cameras(K, pose, self.width, self.height)

    def __len__(self) -> int:
        return self.K.shape[0]

    def __getitem__(self, idx: int | slice | list[int] | np.ndarray) -> Cameras:
        K, pose = self.K[idx], self.world_from_cam[idx]
        return Cameras(K, pose, self.width, self.height)

    @property
    def cam_from_world(self) -> np.ndarray:
        """[N, 4, 4] world-to-camera transforms."""
        return np.linalg.inv(self.world_from_cam)

    @property
    def centers(self) -> np.ndarray:
        """[N, 3] camera centres in world coordinates."""
        return self.world_from_cam[:, :3, 3].copy()

    def project(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points into every camera.

        Args:
            points_world: [P, 3] points.
        Returns:
            uv: [N, P, 2] continuous pixel coordinates; depth: [N, P] camera-space z.
        """
        p = np.concatenate([points_world, np.ones((len(points_world), 1))], axis=1)
        cam = np.einsum("nij,pj->npi", self.cam_from_world, p)[..., :3]
        pix = np.einsum("nij,npj->npi", self.K, cam)
        return pix[..., :2] / pix[..., 2:3], cam[..., 2]

    def coverage(self, K: np.ndarray, world_from_cam: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Which pixels of another camera's depth map show a point some camera here saw.

        Args:
            K, world_from_cam: the other camera (intrinsics [3, 3], camera-to-world [4, 4]).
            depth: [H, W] its depth map, camera z in scene units, 0 = no surface.
        Returns:
            [H, W] bool: the pixel's point (at its centre) lies in front of some camera of these and
            projects inside its image. Occlusion is not modelled: a point hidden behind a nearer
            surface in every photo still counts as seen.
        """
        H, W = depth.shape
        uv = np.stack(np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5), -1).reshape(-1, 2)
        cam = pixel_rays(np.asarray(K, np.float64), uv) * depth.reshape(-1, 1)
        points = cam @ np.asarray(world_from_cam, np.float64)[:3, :3].T + np.asarray(world_from_cam)[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):  # points in a camera's plane: not seen
            seen_uv, z = self.project(points)
        inside = (seen_uv >= 0).all(-1) & (seen_uv[..., 0] <= self.width) & (seen_uv[..., 1] <= self.height)
        return ((inside & (z > 0)).any(0) & (depth.reshape(-1) > 0)).reshape(H, W)

    def scaled(self, width: int, height: int) -> Cameras:
        """The same cameras for images resized to (width, height)."""
        sx, sy = width / self.width, height / self.height
        S = np.diag([sx, sy, 1.0])
        return Cameras(S @ self.K, self.world_from_cam, width, height)


def validate_cameras(K: np.ndarray, world_from_cam: np.ndarray, width: int, height: int) -> None:
    """Raise CameraError unless intrinsics and poses are finite, rigid and consistent, and the
    intrinsics sane for the image size (:data:`FOCAL_RATIO`, :data:`MAX_PRINCIPAL_OFFSET`)."""
    if K.ndim != 3 or K.shape[1:] != (3, 3):
        raise CameraError(f"intrinsics must have shape [N, 3, 3], got {list(K.shape)}")
    if world_from_cam.ndim != 3 or world_from_cam.shape[1:] != (4, 4):
        raise CameraError(f"poses must have shape [N, 4, 4], got {list(world_from_cam.shape)}")
    if K.shape[0] != world_from_cam.shape[0]:
        raise CameraError(f"{K.shape[0]} intrinsics but {world_from_cam.shape[0]} poses")
    if int(width) <= 0 or int(height) <= 0:
        raise CameraError(f"image size must be positive, got {width}x{height}")
    for name, arr in (("intrinsics", K), ("poses", world_from_cam)):
        bad = np.where(~np.isfinite(arr).reshape(len(arr), -1).all(axis=1))[0]
        if len(bad):
            raise CameraError(f"{name} of camera(s) {bad.tolist()} contain NaN or infinity")
    # Bounded focal lengths and principal points keep K well conditioned (in float32 too).
    size = np.array([width, height], dtype=np.float64)
    ratio = np.stack([K[:, 0, 0], K[:, 1, 1]], axis=1) / size
    bad = np.where(((ratio < FOCAL_RATIO[0]) | (ratio > FOCAL_RATIO[1])).any(axis=1))[0]
    if len(bad):
        lo, hi = FOCAL_RATIO
        raise CameraError(
            f"focal lengths of camera(s) {bad.tolist()} must be {lo} to {hi:g} times the image width (fl_x) "
            f"and height (fl_y), got fl_x={K[bad[0], 0, 0]:.6g}, fl_y={K[bad[0], 1, 1]:.6g} for {width}x{height}"
        )
    offset = np.abs(K[:, :2, 2] - size / 2) / size
    bad = np.where((offset > MAX_PRINCIPAL_OFFSET).any(axis=1))[0]
    if len(bad):
        raise CameraError(
            f"principal point of camera(s) {bad.tolist()} must be within {MAX_PRINCIPAL_OFFSET} image sizes "
            f"of the image centre, got cx={K[bad[0], 0, 2]:.6g}, cy={K[bad[0], 1, 2]:.6g} for {width}x{height}"
        )
    R = world_from_cam[:, :3, :3]
    err = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(R)
    bad = np.where((err > 1e-3) | (det < 0))[0]
    if len(bad):
        raise CameraError(f"pose rotation of camera(s) {bad.tolist()} is not a proper rotation")
    if not np.allclose(world_from_cam[:, 3], [0, 0, 0, 1], atol=1e-6):
        raise CameraError("pose matrices must have last row [0, 0, 0, 1]")


def pixel_rays(K, uv):
    """[..., 3] camera-space ray directions with z = 1 (not unit length) through continuous pixel
    coordinates ``uv`` [..., 2] (corner at 0) of intrinsics ``K`` [3, 3]: ``K^-1 (u, v, 1)``.
    NumPy arrays or torch tensors, as given; the one pixel-to-ray of the project."""
    if isinstance(uv, np.ndarray):
        return np.concatenate([uv, np.ones_like(uv[..., :1])], -1) @ np.linalg.inv(K).T
    import torch

    return torch.cat([uv, torch.ones_like(uv[..., :1])], -1) @ torch.linalg.inv(K).T


def nearest_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation closest to the 3x3 matrix ``M`` in the Frobenius norm (SVD, det +1)."""
    U, _, Vt = np.linalg.svd(M)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    return R


def look_at(center: np.ndarray, target: np.ndarray, down: np.ndarray = (0.0, 1.0, 0.0)) -> np.ndarray:
    """[4, 4] world_from_cam at ``center`` with +z towards ``target`` and +y as close to ``down``
    as possible (OpenCV axes: x right, y down, z forward)."""
    center, target, down = (np.asarray(a, dtype=np.float64) for a in (center, target, down))
    z = target - center
    z = z / np.linalg.norm(z)
    x = np.cross(down, z)
    x = x / np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    pose[:3, 3] = center
    return pose


def intrinsics(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """[3, 3] pinhole intrinsics in pixels."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


# --- LLFF ---------------------------------------------------------------------------------


def cameras_from_llff(poses_bounds: np.ndarray, width: int, height: int) -> tuple[Cameras, np.ndarray]:
    """Cameras and per-view [near, far] bounds from an LLFF ``poses_bounds.npy`` array.

    Each row is a 3x5 matrix [R | t | (h, w, f)] flattened row-major, then near, far. The
    rotation columns are the camera's [down, right, backwards] axes in world coordinates and
    h, w, f are the full-resolution size and focal; intrinsics are scaled to ``width x height``.

    Returns:
        cameras, bounds [N, 2].
    """
    pb = np.asarray(poses_bounds, dtype=np.float64)
    if pb.ndim != 2 or pb.shape[1] != 17:
        raise CameraError(f"poses_bounds must have shape [N, 17], got {list(pb.shape)}")
    m = pb[:, :15].reshape(-1, 3, 5)
    h, w, f = m[:, 0, 4], m[:, 1, 4], m[:, 2, 4]
    down, right, back = m[:, :, 0], m[:, :, 1], m[:, :, 2]
    pose = np.tile(np.eye(4), (len(pb), 1, 1))
    pose[:, :3, 0], pose[:, :3, 1], pose[:, :3, 2] = right, down, -back
    pose[:, :3, 3] = m[:, :, 3]
    sx, sy = width / w, height / h
    K = np.stack([intrinsics(f[i] * sx[i], f[i] * sy[i], width / 2, height / 2) for i in range(len(pb))])
    return Cameras(K, pose, width, height), pb[:, 15:17].copy()


def cameras_to_llff(cameras: Cameras, bounds: np.ndarray) -> np.ndarray:
    """Inverse of :func:`cameras_from_llff` ([N, 17]); needs centred principal points and fx == fy."""
    K = cameras.K
    centred = np.allclose(K[:, 0, 2], cameras.width / 2) and np.allclose(K[:, 1, 2], cameras.height / 2)
    if not (np.allclose(K[:, 0, 0], K[:, 1, 1]) and centred):
        raise CameraError("LLFF stores one focal and a centred principal point per camera")
    pose = cameras.world_from_cam
    m = np.zeros((len(cameras), 3, 5))
    m[:, :, 0], m[:, :, 1], m[:, :, 2] = pose[:, :3, 1], pose[:, :3, 0], -pose[:, :3, 2]
    m[:, :, 3] = pose[:, :3, 3]
    m[:, 0, 4], m[:, 1, 4], m[:, 2, 4] = cameras.height, cameras.width, K[:, 0, 0]
    return np.concatenate([m.reshape(-1, 15), np.asarray(bounds, dtype=np.float64)], axis=1)


# --- transforms.json (nerfstudio shape) -----------------------------------------------------


def convert_pose(pose: np.ndarray, src: PoseConvention, dst: PoseConvention) -> np.ndarray:
    """Change the camera-axis convention of camera-to-world poses ([..., 4, 4])."""
    for c in (src, dst):
        if c not in ("opencv", "opengl"):
            raise CameraError(f"unknown pose convention {c!r}; use 'opencv' or 'opengl'")
    return pose if src == dst else pose @ _CV_GL_FLIP


@dataclass(frozen=True)
class CameraFile:
    """The contents of a ``cameras.json`` / ``transforms.json`` file.

    Attributes:
        cameras: the cameras, in this project's (OpenCV) convention.
        file_paths: [N] image file names, relative to the file's folder.
        near_far: [N, 2] depth bounds, or None when the file gives none.
    """

    cameras: Cameras
    file_paths: list[str]
    near_far: np.ndarray | None = None


def _error(where: str, message: str) -> CameraError:
    """A CameraError saying ``where: message`` (just ``message`` when ``where`` is empty)."""
    return CameraError(f"{where}: {message}" if where else message)


def _number(d: dict, key: str, where: str) -> float:
    if key not in d:
        raise _error(where, f"missing {key!r}")
    try:
        v = float(d[key])
    except (TypeError, ValueError):
        raise _error(where, f"{key!r} must be a number, got {d[key]!r}") from None
    if not np.isfinite(v):
        raise _error(where, f"{key!r} is not finite")
    return v


def _frame_camera(merged: dict, where: str) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """Intrinsics [3, 3], the raw ``transform_matrix`` [4, 4] (in the file's convention) and the
    size (w, h) of one frame, its keys ``merged`` over the file's shared ones."""
    w, h = _number(merged, "w", where), _number(merged, "h", where)
    fx = _number(merged, "fl_x", where)
    fy = _number(merged, "fl_y", where) if "fl_y" in merged else fx
    cx = _number(merged, "cx", where) if "cx" in merged else w / 2
    cy = _number(merged, "cy", where) if "cy" in merged else h / 2
    try:
        T = np.asarray(merged["transform_matrix"], dtype=np.float64)
    except KeyError:
        raise _error(where, "missing 'transform_matrix'") from None
    except (TypeError, ValueError):
        raise _error(where, "'transform_matrix' must be a 4x4 list of numbers") from None
    if T.shape == (3, 4):
        T = np.concatenate([T, [[0, 0, 0, 1]]])
    if T.shape != (4, 4):
        raise _error(where, f"'transform_matrix' must be 4x4, got {list(T.shape)}")
    return intrinsics(fx, fy, cx, cy), T, (int(w), int(h))


def camera_from_frame(frame: dict) -> Cameras:
    """The one camera of a frame that carries its own intrinsics (``fl_x``, optional ``fl_y``,
    ``cx``, ``cy``, ``w``, ``h``), ``transform_matrix`` (4x4 camera-to-world) and ``convention``
    (default 'opengl'), as a render request sends it; raises CameraError naming what is wrong."""
    if not isinstance(frame, dict):
        raise CameraError("a camera must be a JSON object")
    K, T, (w, h) = _frame_camera(frame, "")
    return Cameras(K[None], convert_pose(T[None], frame.get("convention", "opengl"), "opencv"), w, h)


def camera_file_from_dict(data: dict) -> CameraFile:
    """Parse a transforms.json-shaped dict; raises CameraError naming what is wrong.

    Shared intrinsics ``fl_x, fl_y, cx, cy, w, h`` at the top level (each frame may override
    them), ``frames[*].file_path`` and ``frames[*].transform_matrix`` (4x4 camera-to-world),
    ``convention`` ('opengl', the nerfstudio/ARKit default, or 'opencv'), and optional
    ``near``/``far`` (top level or per frame).
    """
    if not isinstance(data, dict):
        raise CameraError("cameras file must be a JSON object")
    convention = data.get("convention", "opengl")
    frames = data.get("frames")
    if not isinstance(frames, list) or not frames:
        raise CameraError("cameras file needs a non-empty 'frames' list")
    Ks, poses, paths, bounds = [], [], [], []
    size = None
    for i, fr in enumerate(frames):
        where = f"frame {i}"
        if not isinstance(fr, dict):
            raise CameraError(f"{where}: must be an object")
        merged = {**{k: v for k, v in data.items() if k != "transform_matrix"}, **fr}  # the pose: the frame's own
        w, h = _number(merged, "w", where), _number(merged, "h", where)
        if size is None:
            size = (int(w), int(h))
        elif size != (int(w), int(h)):
            raise CameraError(f"{where}: size {int(w)}x{int(h)} differs from {size[0]}x{size[1]}")
        K, T, _ = _frame_camera(merged, where)
        Ks.append(K)
        poses.append(T)
        fp = fr.get("file_path")
        if not isinstance(fp, str) or not fp:
            raise CameraError(f"{where}: missing 'file_path'")
        paths.append(fp)
        if "near" in merged or "far" in merged:
            near, far = _number(merged, "near", where), _number(merged, "far", where)
            if not 0 < near < far:
                raise CameraError(f"{where}: need 0 < near < far, got near={near}, far={far}")
            bounds.append((near, far))
    if bounds and len(bounds) != len(frames):
        raise CameraError("give near/far for every frame or for none")
    pose = convert_pose(np.stack(poses), convention, "opencv")
    assert size is not None
    cams = Cameras(np.stack(Ks), pose, size[0], size[1])
    return CameraFile(cams, paths, np.array(bounds) if bounds else None)


def camera_file_to_dict(cf: CameraFile, convention: PoseConvention = "opengl") -> dict:
    """Serialise to the transforms.json shape that :func:`camera_file_from_dict` reads."""
    cams = cf.cameras
    pose = convert_pose(cams.world_from_cam, "opencv", convention)
    frames = []
    for i in range(len(cams)):
        K = cams.K[i]
        fr = {
            "file_path": cf.file_paths[i],
            "fl_x": float(K[0, 0]),
            "fl_y": float(K[1, 1]),
            "cx": float(K[0, 2]),
            "cy": float(K[1, 2]),
            "transform_matrix": pose[i].tolist(),
        }
        if cf.near_far is not None:
            fr["near"], fr["far"] = float(cf.near_far[i, 0]), float(cf.near_far[i, 1])
        frames.append(fr)
    return {"convention": convention, "w": cams.width, "h": cams.height, "frames": frames}


def load_camera_file(path: str | Path) -> CameraFile:
    """Read a transforms.json-shaped cameras file (see :func:`camera_file_from_dict`)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise CameraError(f"cameras file not found: {path}") from None
    except IsADirectoryError:
        raise CameraError(f"cameras file {path} is a directory") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CameraError(f"cameras file {path} is not valid JSON: {e}") from None
    return camera_file_from_dict(data)


def save_camera_file(cf: CameraFile, path: str | Path, convention: PoseConvention = "opengl") -> None:
    """Write ``cf`` as a transforms.json-shaped file."""
    Path(path).write_text(json.dumps(camera_file_to_dict(cf, convention), indent=1))


def match_frames(file_paths: Sequence[str], photo_names: Sequence[Sequence[str]]) -> list[int]:
    """Index of the cameras-file frame for each photo, matching by file name, then by stem.

    Args:
        file_paths: the frames' ``file_path`` values (any folder part is ignored).
        photo_names: per photo, the names it answers to, the file name first (e.g. the upload's
            original name, then a sanitised alias).
    Raises:
        CameraError: a photo no frame names, a photo named by several frames, or frames naming no photo.
    """
    keys = [Path(fp.replace("\\", "/")).name for fp in file_paths]
    order = []
    for names in photo_names:
        hits = [f for f, key in enumerate(keys) if key == names[0]]
        if not hits:
            stems = {Path(n).stem for n in names}
            hits = [f for f, key in enumerate(keys) if Path(key).stem in stems]
        if not hits:
            raise CameraError(f"no frame in the cameras file is for photo {names[0]} (frames: {', '.join(keys)})")
        if len(hits) > 1:
            raise CameraError(f"{len(hits)} frames in the cameras file name photo {names[0]}")
        order.append(hits[0])
    extra = sorted(set(range(len(keys))) - set(order))
    if extra:
        raise CameraError(f"frames {', '.join(keys[f] for f in extra)} match none of the uploaded photos")
    return order
