"""COLMAP adapters: importing pycolmap, its reconstructions as cmc cameras and points, its binary
model files, and its cancellation and logging.

COLMAP stores world-to-camera poses (``cam_from_world``) with the same axes and pixel convention as
:mod:`cmc.geometry.cameras`; the one conversion is :func:`world_from_cam`. Pinned: pycolmap 4.2.1 (its
Python API changes between releases).
"""

from __future__ import annotations

import ctypes
import os
import signal
import struct
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager, nullcontext
from pathlib import Path
from typing import Any

import numpy as np

from cmc.errors import PoseEstimationError
from cmc.geometry.cameras import CameraError, Cameras
from cmc.poses.options import PoseEstimationCancelled, SparsePoints


def cameras_from_colmap(reconstruction: Any, image_names: Sequence[str]) -> Cameras:
    """Cameras of the named registered images of a ``pycolmap.Reconstruction``.

    COLMAP keeps ``cam_from_world`` (world -> camera, x right / y down / z forward) and puts the
    image's top-left corner at (0, 0) with pixel centres at +0.5, exactly like :mod:`cmc.geometry.cameras`;
    so K is COLMAP's calibration matrix unchanged and ``world_from_cam`` is the rigid inverse.

    Args:
        reconstruction: ``pycolmap.Reconstruction`` with pinhole cameras of one image size.
        image_names: COLMAP image names, in the output order.
    Raises:
        PoseEstimationError: an image is missing or not registered.
        CameraError: a camera with distortion, or images of different sizes.
    """
    Ks, poses, sizes = [], [], set()
    for name in image_names:
        image = reconstruction.find_image_with_name(name)
        if image is None or not image.has_pose:
            raise PoseEstimationError(f"image {name!r} is not registered in the reconstruction")
        camera = reconstruction.cameras[image.camera_id]
        if camera.model_name not in ("SIMPLE_PINHOLE", "PINHOLE"):
            raise CameraError(f"camera model {camera.model_name} has distortion; cmc cameras are pinhole")
        sizes.add((camera.width, camera.height))
        Ks.append(np.asarray(camera.calibration_matrix(), dtype=np.float64))
        poses.append(world_from_cam(image.cam_from_world()))
    if len(sizes) != 1:
        raise CameraError(f"images have different sizes: {sorted(sizes)}")
    (width, height) = sizes.pop()
    return Cameras(np.stack(Ks), np.stack(poses), width, height)


def world_from_cam(cam_from_world: Any) -> np.ndarray:
    """[4, 4] camera-to-world of a COLMAP ``Rigid3d`` world-to-camera transform."""
    m = np.asarray(cam_from_world.matrix(), dtype=np.float64)  # [3, 4]
    R, t = m[:, :3], m[:, 3]
    world_from_cam = np.eye(4)
    world_from_cam[:3, :3], world_from_cam[:3, 3] = R.T, -R.T @ t
    return world_from_cam


def sparse_points_from_colmap(
    reconstruction: Any, image_names: Sequence[str], pixel_scale: tuple[float, float] = (1.0, 1.0)
) -> SparsePoints:
    """The 3D points of a ``pycolmap.Reconstruction`` seen by the named images, with where each
    image observes them: COLMAP's keypoints times ``pixel_scale`` (x, y), e.g. to the working size."""
    column = {reconstruction.find_image_with_name(n).image_id: k for k, n in enumerate(image_names)}
    scale = np.asarray(pixel_scale, dtype=np.float64)
    xyz, pixels = [], []
    for point in reconstruction.points3D.values():
        seen = np.full((len(image_names), 2), np.nan)
        for element in point.track.elements:
            if element.image_id in column:
                image = reconstruction.images[element.image_id]
                seen[column[element.image_id]] = np.asarray(image.points2D[element.point2D_idx].xy) * scale
        if not np.isnan(seen).all():
            xyz.append(point.xyz)
            pixels.append(seen)
    return SparsePoints(
        np.asarray(xyz, dtype=np.float64).reshape(-1, 3),
        np.asarray(pixels, dtype=np.float64).reshape(-1, len(image_names), 2),
    )


def read_colmap_points(path: str | Path) -> np.ndarray:
    """[P, 3] world coordinates of a COLMAP ``points3D.bin`` (tracks skipped).

    Reads the file alone: pycolmap only reads whole models, and a published dataset may ship
    ``points3D.bin`` and ``cameras.bin`` without ``images.bin`` (LLFF's ``sparse/0`` does).
    """
    data = Path(path).read_bytes()
    (count,), offset = struct.unpack_from("<Q", data), 8
    xyz = np.empty((count, 3))
    for k in range(count):
        # point id (u64), x y z (f64), r g b (u8), error (f64), track length (u64), track (2 x i32 each)
        _, x, y, z, _, _, _, _, length = struct.unpack_from("<QdddBBBdQ", data, offset)
        xyz[k] = (x, y, z)
        offset += 51 + 8 * length
    if offset != len(data):
        raise ValueError(f"{path}: not a COLMAP points3D.bin ({len(data) - offset} bytes left over)")
    return xyz


def read_colmap_cameras(path: str | Path) -> list[Any]:
    """The cameras of a COLMAP ``cameras.bin`` as ``pycolmap.Camera`` objects (any model; their
    ``img_from_cam`` projects with the model's distortion)."""
    pycolmap = import_pycolmap()
    data = Path(path).read_bytes()
    (count,), offset = struct.unpack_from("<Q", data), 8
    cameras = []
    for _ in range(count):
        camera_id, model_id, width, height = struct.unpack_from("<iiQQ", data, offset)
        offset += 24
        camera = pycolmap.Camera.create_from_model_id(camera_id, pycolmap.CameraModelId(model_id), 1.0, width, height)
        n = len(camera.params)
        camera.params = struct.unpack_from(f"<{n}d", data, offset)
        offset += 8 * n
        cameras.append(camera)
    if offset != len(data):
        raise ValueError(f"{path}: not a COLMAP cameras.bin ({len(data) - offset} bytes left over)")
    return cameras


_IMPORT_LOCK = threading.Lock()


@contextmanager
def _keep_sigterm() -> Iterator[None]:
    """Restore the process's SIGTERM handler afterwards. Importing pycolmap installs glog's
    failure handler for SIGTERM, which aborts the process instead of the graceful stop the
    server or worker set up (checkpoint, then exit). Saved and restored with sigaction itself,
    as opaque bytes: Python's ``signal`` module only works on the main thread, and jobs run
    pose estimation on others."""
    if os.name != "posix":  # pragma: no cover - the project runs on Linux
        yield
        return
    libc = ctypes.CDLL(None, use_errno=True)
    saved = ctypes.create_string_buffer(256)  # larger than any libc's struct sigaction
    if libc.sigaction(int(signal.SIGTERM), None, saved) != 0:
        raise OSError(ctypes.get_errno(), "sigaction")
    try:
        yield
    finally:
        libc.sigaction(int(signal.SIGTERM), saved, None)


def import_pycolmap():
    first = "pycolmap" not in sys.modules  # later imports run no module code
    try:
        with _IMPORT_LOCK, _keep_sigterm() if first else nullcontext():
            import pycolmap
    except ImportError:  # pragma: no cover - depends on the environment
        raise PoseEstimationError("pose estimation needs the pycolmap package (pip install pycolmap==4.2.1)") from None
    if not pycolmap.__version__.startswith("4."):
        raise PoseEstimationError(f"cmc.poses is written for pycolmap 4.x (pinned 4.2.1), found {pycolmap.__version__}")
    return pycolmap


class Cancel:
    """A pycolmap CancellationToken driven by ``should_stop`` (polled every 0.1 s on a thread,
    so a running pycolmap stage stops at its next checkpoint, typically the next image).
    Without pycolmap (client poses with near/far) only :meth:`check` is used."""

    def __init__(self, pycolmap: Any | None, should_stop: Callable[[], bool] | None):
        self.token = pycolmap.CancellationToken() if pycolmap is not None else None
        self.should_stop = should_stop
        self._done = threading.Event()
        self._thread: threading.Thread | None = None

    def _poll(self) -> None:
        while not self._done.wait(0.1):
            if self.should_stop is not None and self.should_stop() and self.token is not None:
                self.token.cancel()
                return

    def __enter__(self) -> Cancel:
        if self.should_stop is not None and self.token is not None:
            self._thread = threading.Thread(target=self._poll, name="cmc-poses-cancel", daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._done.set()
        if self._thread is not None:
            self._thread.join()

    def check(self) -> None:
        stop = self.should_stop is not None and self.should_stop()
        if stop and self.token is not None:
            self.token.cancel()
        if stop or (self.token is not None and self.token.is_cancelled):
            raise PoseEstimationCancelled("pose estimation cancelled")

    @contextmanager
    def running(self) -> Iterator[None]:
        """Around a pycolmap call: translate its InterruptedError into PoseEstimationCancelled."""
        self.check()
        try:
            yield
        except InterruptedError:
            raise PoseEstimationCancelled("pose estimation cancelled") from None
        self.check()


@contextmanager
def quiet(pycolmap: Any, verbose: bool) -> Iterator[None]:
    """Silence COLMAP's log (glog, process-wide) unless ``verbose``; our errors say what failed."""
    if verbose:
        yield
        return
    previous = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 3
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = previous
