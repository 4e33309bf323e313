"""Cameras for a few uploaded photos: structure from motion with pycolmap, or poses from the client.

Both entry points write a *scene folder* that ``cmc train`` reads directly: ``images/NAME.png``
(upright, long side ``long_side``), ``cameras.json`` (transforms.json shape with per-view
``near``/``far``) and, by default, the untouched uploads in ``originals/``.

* :func:`estimate_poses` runs SIFT (at most ``max_sift_size`` pixels), exhaustive matching and
  incremental mapping tuned for 2-5 photos, keeps the model that registers the most photos and
  fails naming the photos it could not register. Poses are up to a similarity (SfM has no scale).
* :func:`poses_from_client` takes intrinsics and poses from a transforms.json-shaped file (ARKit /
  ARCore), validates them against the photos and, without ``near``/``far`` in the file,
  triangulates matched features with the given poses to get the depth range.
* Aligning two reconstructions of the same photos (benchmarks against a dataset's own model):
  :func:`similarity_from_cameras` from their cameras, or through their 3D points:
  :func:`corresponding_points` pairs the points both see at the same pixels, and
  :func:`register_camera` finds the pose that sees given points at given pixels.

Conventions are :mod:`cmc.cameras`' (OpenCV axes, camera-to-world, pixel corner at 0). COLMAP
stores world-to-camera poses (``cam_from_world``) with the same axes and pixel convention; the one
conversion is :func:`_world_from_cam`. Depth bounds are camera z in scene units.

Pinned: pycolmap 4.2.1 (its Python API changes between releases).
"""

from __future__ import annotations

import argparse
import ctypes
import hashlib
import json
import os
import re
import shutil
import signal
import struct
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cmc.cameras import (
    CameraError,
    CameraFile,
    Cameras,
    PoseConvention,
    camera_file_from_dict,
    load_camera_file,
    nearest_rotation,
    save_camera_file,
)
from cmc.datasets import CAMERAS_FILE, SceneError
from cmc.images import MAX_PIXELS, PhotoInfo, load_resized, read_photo_info, resized_size, save_png

IMAGES_DIR = "images"
ORIGINALS_DIR = "originals"
SFM_CAMERA_MODEL = "SIMPLE_PINHOLE"  # f, cx, cy: what a Cameras entry can hold (no distortion)
NEAR_FAR_PERCENTILES = (0.5, 99.5)  # robust extremes of the per-view point depths ...
NEAR_FAR_MARGINS = (0.9, 1.1)  # ... widened by these factors so the MPI planes cover the scene
MIN_POINTS_PER_VIEW = 8
MIN_FEATURES = 100  # fewer SIFT features than this: blank, blurred or textureless photo
MIN_PAIR_INLIERS = 30  # fewer verified matches than this: unrelated photos or too little overlap
SUGGESTION = (
    "Retake the photos with more overlap (move the camera sideways a little between shots, keep the "
    "same subject in view) of a textured scene (avoid blank walls, glass and reflections), or send "
    "camera poses with a cameras file."
)


class PoseEstimationError(ValueError):
    """Poses could not be estimated from these photos; the message names the photos and a remedy."""


class PoseEstimationCancelled(Exception):
    """Raised when ``should_stop`` returned True; nothing usable was written."""


@dataclass
class PoseResult:
    """What :func:`estimate_poses` and :func:`poses_from_client` produced.

    Attributes:
        camera_file: cameras at the working resolution (OpenCV convention, ``file_paths`` relative
            to ``scene_dir``) with ``near_far`` [N, 2] (camera z, scene units).
        image_paths: [N] working images (PNG), in the order of the input photos.
        scene_dir: the scene folder; ``cameras_path`` is its cameras.json.
        timings: stage name -> seconds (wall clock), plus 'total'.
        stats: counts and diagnostics (registered photos, 3D points, reprojection error, ...).
        sparse: the SfM points and where the photos see them (working resolution); None for
            client poses.
    """

    camera_file: CameraFile
    image_paths: list[Path]
    scene_dir: Path
    cameras_path: Path
    timings: dict[str, float] = field(default_factory=dict)
    stats: dict[str, Any] = field(default_factory=dict)
    sparse: SparsePoints | None = None


@dataclass(frozen=True)
class SparsePoints:
    """3D points of a reconstruction and where its photos observe them.

    Attributes:
        xyz: [P, 3] world coordinates (the frame and units of the poses).
        pixels: [P, N, 2] pixel coordinates of each point in each of the N photos (cmc pixel
            convention, at the cameras' resolution); NaN where a photo does not observe the point.
    """

    xyz: np.ndarray
    pixels: np.ndarray

    def seen_by(self, k: int) -> np.ndarray:
        """[P] bool: the points photo ``k`` observes."""
        return ~np.isnan(self.pixels[:, k, 0])


# --- COLMAP conversion (the only place that knows COLMAP's pose direction) -------------------


def cameras_from_colmap(reconstruction: Any, image_names: Sequence[str]) -> Cameras:
    """Cameras of the named registered images of a ``pycolmap.Reconstruction``.

    COLMAP keeps ``cam_from_world`` (world -> camera, x right / y down / z forward) and puts the
    image's top-left corner at (0, 0) with pixel centres at +0.5, exactly like :mod:`cmc.cameras`;
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
        poses.append(_world_from_cam(image.cam_from_world()))
    if len(sizes) != 1:
        raise CameraError(f"images have different sizes: {sorted(sizes)}")
    (width, height) = sizes.pop()
    return Cameras(np.stack(Ks), np.stack(poses), width, height)


def _world_from_cam(cam_from_world: Any) -> np.ndarray:
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
    pycolmap = _pycolmap()
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


# --- Near / far ------------------------------------------------------------------------------


def depth_range(depths: np.ndarray, name: str = "view") -> tuple[float, float]:
    """(near, far) covering the positive camera-z ``depths`` [P] of one view's 3D points.

    Robust percentiles (:data:`NEAR_FAR_PERCENTILES`) widened by :data:`NEAR_FAR_MARGINS`, as
    LLFF derives its bounds; raises PoseEstimationError with fewer than MIN_POINTS_PER_VIEW points.
    """
    z = np.asarray(depths, dtype=np.float64)
    z = z[np.isfinite(z) & (z > 0)]
    if len(z) < MIN_POINTS_PER_VIEW:
        raise PoseEstimationError(
            f"only {len(z)} 3D points are seen from {name}, too few for a depth range. {SUGGESTION}"
        )
    lo, hi = np.percentile(z, NEAR_FAR_PERCENTILES)
    near, far = lo * NEAR_FAR_MARGINS[0], hi * NEAR_FAR_MARGINS[1]
    return float(near), float(max(far, near * 1.01))


def triangulate_pair(
    cameras: Cameras, i: int, j: int, uv_i: np.ndarray, uv_j: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Linear (DLT) triangulation of matched pixels between two known cameras.

    Args:
        cameras: the cameras, intrinsics at the resolution of the pixel coordinates.
        i, j: the two camera indices.
        uv_i, uv_j: [M, 2] matched pixel coordinates (pixel-corner convention).
    Returns:
        points [M, 3] (world), depths [M, 2] (camera z in i and j), reprojection error [M]
        (pixels, the larger of the two views).
    """
    cam_from_world = cameras.cam_from_world[[i, j], :3]  # [2, 3, 4]
    rows = []
    for k, uv in enumerate((uv_i, uv_j)):
        P = cam_from_world[k]
        xn = np.concatenate([uv, np.ones((len(uv), 1))], axis=1) @ np.linalg.inv(cameras.K[(i, j)[k]]).T
        rows += [xn[:, 0:1] * P[2] - P[0], xn[:, 1:2] * P[2] - P[1]]  # x * (row 3) - (row 1), ... [M, 4]
    A = np.stack(rows, axis=1)  # [M, 4, 4]
    X = np.linalg.svd(A)[2][:, -1]
    X = X[:, :3] / X[:, 3:4]
    uv_proj, depth = cameras[[i, j]].project(X)  # [2, M, 2], [2, M]
    err = np.linalg.norm(uv_proj - np.stack([uv_i, uv_j]), axis=-1).max(axis=0)
    return X, depth.T, err


# --- Shared plumbing -------------------------------------------------------------------------


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


def _pycolmap():
    first = "pycolmap" not in sys.modules  # later imports run no module code
    try:
        with _IMPORT_LOCK, _keep_sigterm() if first else nullcontext():
            import pycolmap
    except ImportError:  # pragma: no cover - depends on the environment
        raise PoseEstimationError("pose estimation needs the pycolmap package (pip install pycolmap==4.2.1)") from None
    if not pycolmap.__version__.startswith("4."):
        raise PoseEstimationError(f"cmc.poses is written for pycolmap 4.x (pinned 4.2.1), found {pycolmap.__version__}")
    return pycolmap


class _Cancel:
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

    def __enter__(self) -> _Cancel:
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


class _Timings(dict):
    """Wall-clock seconds per stage; calls ``on_stage(name)`` as each stage starts (progress)."""

    def __init__(self, on_stage: Callable[[str], None] | None = None):
        super().__init__()
        self.on_stage = on_stage


@contextmanager
def _stage(timings: _Timings, name: str) -> Iterator[None]:
    if timings.on_stage is not None:
        timings.on_stage(name)
    t0 = time.perf_counter()
    try:
        yield
    finally:
        timings[name] = timings.get(name, 0.0) + time.perf_counter() - t0


@contextmanager
def _quiet(pycolmap: Any, verbose: bool) -> Iterator[None]:
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


@contextmanager
def _work_dir(work_dir: str | Path | None) -> Iterator[Path]:
    if work_dir is not None:
        path = Path(work_dir)
        path.mkdir(parents=True, exist_ok=True)
        yield path
    else:
        with tempfile.TemporaryDirectory(prefix="cmc-poses-") as tmp:
            yield Path(tmp)


@dataclass
class _Photos:
    """The photos: header facts, then (after :func:`_write_photos`) the files written.

    Names are unique, file-system safe stems; sizes are (width, height) in pixels."""

    infos: list[PhotoInfo]
    names: list[str]
    working_paths: list[Path]
    working_size: tuple[int, int]
    sfm_paths: list[Path]
    sfm_size: tuple[int, int]
    digests: list[str]  # of the decoded pixels, to spot identical photos

    def label(self, k: int) -> str:
        return self.infos[k].path.name


def _unique_names(paths: Sequence[Path]) -> list[str]:
    names: list[str] = []
    for p in paths:
        base = re.sub(r"[^A-Za-z0-9._-]+", "_", p.stem).strip("._") or "photo"
        name, k = base, 2
        while name in names:
            name, k = f"{base}_{k}", k + 1
        names.append(name)
    return names


def _read_photos(image_paths: Sequence[str | Path], long_side: int, max_sift_size: int, max_pixels: int) -> _Photos:
    """Check the photos from their headers (format, size, orientation, EXIF); decodes nothing."""
    if long_side < 16 or max_sift_size < 16:
        raise SceneError(f"image sizes must be at least 16 pixels (long side {long_side}, SIFT {max_sift_size})")
    paths = [Path(p) for p in image_paths]
    if not paths:
        raise SceneError("no photos given")
    resolved = [p.resolve() for p in paths]
    dupes = sorted({p.name for p, r in zip(paths, resolved, strict=True) if resolved.count(r) > 1})
    if dupes:
        raise SceneError(f"the same photo is given more than once: {', '.join(dupes)}")
    infos = [read_photo_info(p, max_pixels) for p in paths]
    sizes = [resized_size(i.width, i.height, long_side) for i in infos]
    if len(set(sizes)) > 1:
        listing = ", ".join(f"{i.path.name} {i.width}x{i.height}" for i in infos)
        raise SceneError(
            f"the photos must have one size and orientation (after EXIF rotation), got: {listing}. "
            "Take all photos with the same camera held the same way (all landscape or all portrait)."
        )
    min_long = min(max(i.width, i.height) for i in infos)
    sfm_size = resized_size(infos[0].width, infos[0].height, min(max_sift_size, min_long))
    return _Photos(infos, _unique_names(paths), [], sizes[0], [], sfm_size, [])


def _write_photos(
    photos: _Photos, scene_dir: Path, sfm_dir: Path | None, max_pixels: int, keep_originals: bool
) -> None:
    """Decode each photo once; write its working image (and SfM-size copy into ``sfm_dir``)."""
    photos.working_paths = [scene_dir / IMAGES_DIR / f"{n}.png" for n in photos.names]
    photos.sfm_paths = [sfm_dir / f"{n}.png" for n in photos.names] if sfm_dir is not None else []
    wanted = [photos.working_size] + ([photos.sfm_size] if sfm_dir is not None else [])
    for k, info in enumerate(photos.infos):
        decoded = load_resized(info, wanted, max_pixels)
        save_png(decoded[0], photos.working_paths[k])
        if sfm_dir is not None:
            save_png(decoded[1], photos.sfm_paths[k], fast=True)
        photos.digests.append(hashlib.sha256(decoded[-1].tobytes()).hexdigest())
    if keep_originals:
        originals = scene_dir / ORIGINALS_DIR
        originals.mkdir(parents=True, exist_ok=True)
        for info, name in zip(photos.infos, photos.names, strict=True):
            dst = originals / f"{name}{info.path.suffix.lower()}"
            if dst.resolve() != info.path.resolve():
                shutil.copyfile(info.path, dst)


@dataclass
class _Matches:
    """Features and verified matches read back from the COLMAP database (indices = photo order)."""

    keypoints: list[np.ndarray]  # [K_i, 2] pixel coordinates at the SfM resolution
    pairs: dict[tuple[int, int], np.ndarray]  # (i, j), i < j -> [M, 2] inlier keypoint indices


def _focal_priors(photos: _Photos) -> list[float | None]:
    """EXIF focal priors in pixels at the SfM resolution."""
    return [None if i.focal_px is None else i.focal_px * photos.sfm_size[0] / i.width for i in photos.infos]


def _one_device(photos: _Photos) -> bool:
    """True when the photos look like one camera (same EXIF device and focal, or no EXIF at all)."""
    devices = {i.device for i in photos.infos}
    focals = [i.focal_px for i in photos.infos]
    if len(devices) > 1 or len({f is None for f in focals}) > 1:
        return False
    known = [f for f in focals if f is not None]
    return not known or (max(known) - min(known)) <= 0.01 * max(known)


def _features_and_matches(
    pycolmap: Any,
    photos: _Photos,
    database: Path,
    max_sift_size: int,
    seed: int,
    cancel: _Cancel,
    timings: _Timings,
    single_camera: bool,
    use_priors: bool,
) -> _Matches:
    """SIFT into a fresh database, EXIF focal priors into its cameras, exhaustive matching."""
    database.unlink(missing_ok=True)
    sfm_dir = photos.sfm_paths[0].parent
    file_names = [p.name for p in photos.sfm_paths]
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = SFM_CAMERA_MODEL
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = max_sift_size
    mode = pycolmap.CameraMode.SINGLE if single_camera else pycolmap.CameraMode.PER_IMAGE
    with _stage(timings, "features"), cancel.running():
        pycolmap.Database.open(database).close()
        # import first so image ids follow the photo order (threaded extraction numbers them as
        # they finish, and the mapper's choices depend on the ids): reruns are then identical
        pycolmap.import_images(database, sfm_dir, camera_mode=mode, image_names=file_names, options=reader)
        pycolmap.extract_features(
            database,
            sfm_dir,
            image_names=file_names,
            camera_mode=mode,
            reader_options=reader,
            extraction_options=extraction,
            cancellation_token=cancel.token,
        )
    priors = _focal_priors(photos) if use_priors else [None] * len(file_names)
    with pycolmap.Database.open(database) as db:
        images = db.read_all_images()
        assert len(images) == len(file_names), "COLMAP database holds unexpected images"
        ids = {im.name: im.image_id for im in images}
        cam_of = {im.name: im.camera_id for im in images}
        for name, prior in zip(file_names, priors, strict=True):
            if prior is not None:
                camera = db.read_camera(cam_of[name])
                camera.params = [prior, photos.sfm_size[0] / 2, photos.sfm_size[1] / 2]
                camera.has_prior_focal_length = True
                db.update_camera(camera)
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = seed
    with _stage(timings, "matching"), cancel.running():
        pycolmap.match_exhaustive(database, verification_options=verification, cancellation_token=cancel.token)
    index = {ids[name]: k for k, name in enumerate(file_names)}
    with pycolmap.Database.open(database) as db:
        keypoints = [np.asarray(db.read_keypoints(ids[name]))[:, :2].astype(np.float64) for name in file_names]
        pairs = {}
        pair_ids, geometries = db.read_two_view_geometries()
        for pair_id, geometry in zip(pair_ids, geometries, strict=True):
            a, b = pycolmap.pair_id_to_image_pair(pair_id)
            m = np.asarray(geometry.inlier_matches, dtype=np.int64).reshape(-1, 2)
            i, j = index[a], index[b]
            pairs[(i, j) if i < j else (j, i)] = m if i < j else m[:, ::-1]
    return _Matches(keypoints, pairs)


def _pair_shift(matches: _Matches, i: int, j: int) -> float:
    """Median image displacement (pixels, SfM resolution) of the verified matches of (i, j)."""
    m = matches.pairs.get((i, j))
    if m is None or len(m) == 0:
        return float("nan")
    return float(np.median(np.linalg.norm(matches.keypoints[i][m[:, 0]] - matches.keypoints[j][m[:, 1]], axis=1)))


def _diagnose(photos: _Photos, matches: _Matches, k: int) -> str:
    """Why photo ``k`` probably failed to register, as a short phrase."""
    n = len(photos.names)
    if len(matches.keypoints[k]) < MIN_FEATURES:
        return f"only {len(matches.keypoints[k])} image features (blank, blurred or textureless?)"
    long_side = max(photos.sfm_size)
    for other in range(n):
        if other != k:
            pair = (min(k, other), max(k, other))
            if len(matches.pairs.get(pair, ())) >= MIN_PAIR_INLIERS and _pair_shift(matches, *pair) < 0.002 * long_side:
                return f"taken from the same spot as {photos.label(other)} (the camera did not move)"
    best = max(
        ((len(matches.pairs.get((min(k, o), max(k, o)), ())), o) for o in range(n) if o != k),
        default=(0, k),
    )
    if best[0] < MIN_PAIR_INLIERS:
        return f"too few features shared with the other photos (best: {best[0]} matches): unrelated, or little overlap?"
    return f"{best[0]} matches with {photos.label(best[1])} but no consistent 3D geometry (too little camera motion?)"


def _mapping_options(pycolmap: Any, refine_focal: bool, seed: int) -> Any:
    """Incremental mapping options for 2-5 photos (COLMAP's defaults target large collections)."""
    options = pycolmap.IncrementalPipelineOptions()
    options.min_model_size = 2  # default 10 would discard every model of a few photos
    options.max_num_models = 10
    options.extract_colors = False
    options.num_threads = options.mapper.num_threads = 1  # a few photos map fast; one thread is repeatable
    options.random_seed = seed
    options.ba_refine_focal_length = refine_focal  # with 2-5 views an EXIF focal beats a refined one
    options.ba_refine_principal_point = False
    options.ba_refine_extra_params = False
    options.mapper.init_min_num_inliers = 30  # default 100
    options.mapper.init_min_tri_angle = 4.0  # degrees; default 16 suits wide baselines, not handheld shots
    options.mapper.abs_pose_min_num_inliers = 15  # default 30
    options.mapper.random_seed = seed
    options.triangulation.ignore_two_view_tracks = False  # with 3 photos most tracks have two views
    options.triangulation.random_seed = seed
    return options


def _finish(
    photos: _Photos,
    scene_dir: Path,
    cameras: Cameras,
    near_far: np.ndarray,
    convention: PoseConvention,
    timings: _Timings,
    stats: dict[str, Any],
    t_start: float,
    sparse: SparsePoints | None = None,
) -> PoseResult:
    """Write cameras.json (working resolution) last, so a scene folder with it is complete."""
    with _stage(timings, "write"):
        file_paths = [f"{IMAGES_DIR}/{p.name}" for p in photos.working_paths]
        camera_file = CameraFile(cameras, file_paths, np.asarray(near_far, dtype=np.float64))
        path = scene_dir / CAMERAS_FILE
        save_camera_file(camera_file, path, convention)
    timings["total"] = time.perf_counter() - t_start
    return PoseResult(camera_file, list(photos.working_paths), scene_dir, path, timings, stats, sparse)


def _prepare_scene_dir(scene_dir: str | Path) -> Path:
    scene_dir = Path(scene_dir)
    scene_dir.mkdir(parents=True, exist_ok=True)
    (scene_dir / CAMERAS_FILE).unlink(missing_ok=True)  # a stale file would pair old cameras with new images
    return scene_dir


# --- Structure from motion -------------------------------------------------------------------


def estimate_poses(
    image_paths: Sequence[str | Path],
    scene_dir: str | Path,
    *,
    long_side: int = 504,
    max_sift_size: int = 1600,
    seed: int = 0,
    should_stop: Callable[[], bool] | None = None,
    work_dir: str | Path | None = None,
    keep_originals: bool = True,
    max_pixels: int = MAX_PIXELS,
    convention: PoseConvention = "opengl",
    verbose: bool = False,
    on_stage: Callable[[str], None] | None = None,
) -> PoseResult:
    """Intrinsics, camera-to-world poses and near/far for 2-5 photos by structure from motion.

    Args:
        image_paths: the uploaded photos (JPEG/PNG/WebP/HEIC, any file names).
        scene_dir: output scene folder (``images/``, ``cameras.json``, ``originals/``).
        long_side: long side of the working images in pixels (never enlarged).
        max_sift_size: long side of the images SIFT runs on (pixels); bounds time and memory.
        seed: seeds COLMAP's RANSAC and mapper, so reruns give the same result.
        should_stop: polled from a helper thread (make it thread-safe); True cancels at the next
            checkpoint of the running stage and raises PoseEstimationCancelled.
        work_dir: keep COLMAP's database, SfM images and sparse model here (default: a
            temporary folder, removed afterwards).
        keep_originals: copy the uploads, unchanged, into ``scene_dir/originals``.
        max_pixels: refuse photos with more pixels (decompression bombs).
        convention: camera axes written to cameras.json ('opengl' as nerfstudio/ARKit, or 'opencv').
        verbose: let COLMAP log to stderr.
        on_stage: called with each stage's name as it starts ('intake', 'features', 'matching',
            'mapping', 'near_far', 'write'), e.g. to report progress.
    Returns:
        PoseResult; the poses are up to a similarity (SfM has no absolute scale or orientation).
    Raises:
        SceneError: unusable photos; PoseEstimationError: SfM failed (the message names the
        photos it could not register and what to do); PoseEstimationCancelled.
    """
    t_start = time.perf_counter()
    pycolmap = _pycolmap()
    timings = _Timings(on_stage)
    if len(image_paths) < 2:
        raise PoseEstimationError(f"structure from motion needs at least 2 photos, got {len(image_paths)}")
    with _work_dir(work_dir) as work, _Cancel(pycolmap, should_stop) as cancel, _quiet(pycolmap, verbose):
        with _stage(timings, "intake"):
            photos = _read_photos(image_paths, long_side, max_sift_size, max_pixels)
            scene_dir = _prepare_scene_dir(scene_dir)
            _write_photos(photos, scene_dir, work / "sfm_images", max_pixels, keep_originals)
        _refuse_identical(photos)
        cancel.check()
        one_device = _one_device(photos)
        pycolmap.set_random_seed(seed)
        matches = _features_and_matches(
            pycolmap, photos, work / "database.db", max_sift_size, seed, cancel, timings, one_device, use_priors=True
        )
        refine_focal = any(p is None for p in _focal_priors(photos))
        with _stage(timings, "mapping"), cancel.running():
            reconstruction = _best_model(pycolmap, work, photos, refine_focal, seed, cancel)
        sfm_names = [p.name for p in photos.sfm_paths]
        _require_all_registered(reconstruction, sfm_names, photos, matches)
        with _stage(timings, "near_far"):
            cameras = cameras_from_colmap(reconstruction, sfm_names).scaled(*photos.working_size)
            to_working = (photos.working_size[0] / photos.sfm_size[0], photos.working_size[1] / photos.sfm_size[1])
            sparse = sparse_points_from_colmap(reconstruction, sfm_names, to_working)
            near_far = _near_far_from_points(sparse, cameras, photos)
        stats = {
            "method": "sfm",
            "registered": len(sfm_names),
            "points3D": reconstruction.num_points3D(),
            "mean_reprojection_error_px": float(reconstruction.compute_mean_reprojection_error()),
            "sfm_size": list(photos.sfm_size),
            "focal_prior": [i.focal_source for i in photos.infos],
            "single_camera": one_device,
            "pycolmap": pycolmap.__version__,
        }
        return _finish(photos, scene_dir, cameras, near_far, convention, timings, stats, t_start, sparse)


def _best_model(pycolmap: Any, work: Path, photos: _Photos, refine_focal: bool, seed: int, cancel: _Cancel) -> Any:
    """Incremental mapping; the model registering the most photos (then most points), or None."""
    sparse_dir = work / "sparse"
    shutil.rmtree(sparse_dir, ignore_errors=True)
    sparse_dir.mkdir(parents=True)
    models = pycolmap.incremental_mapping(
        work / "database.db",
        photos.sfm_paths[0].parent,
        sparse_dir,
        _mapping_options(pycolmap, refine_focal, seed),
        cancellation_token=cancel.token,
    )
    return max(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()), default=None)


def _require_all_registered(reconstruction: Any, names: Sequence[str], photos: _Photos, matches: _Matches) -> None:
    """Raise PoseEstimationError naming each unregistered photo with a likely reason."""

    def registered(name: str) -> bool:
        image = None if reconstruction is None else reconstruction.find_image_with_name(name)
        return image is not None and image.has_pose

    ok = [registered(n) for n in names]
    if all(ok):
        return
    failed = [k for k, good in enumerate(ok) if not good]
    detail = "; ".join(f"{photos.label(k)}: {_diagnose(photos, matches, k)}" for k in failed)
    got = ", ".join(photos.label(k) for k, good in enumerate(ok) if good) or "none"
    raise PoseEstimationError(
        f"could not register {len(failed)} of {len(ok)} photos ({detail}); registered: {got}. {SUGGESTION}"
    )


def _refuse_identical(photos: _Photos) -> None:
    seen: dict[str, int] = {}
    for k, d in enumerate(photos.digests):
        if d in seen:
            raise PoseEstimationError(
                f"photos {photos.label(seen[d])} and {photos.label(k)} are identical; "
                "take each photo from a slightly different position."
            )
        seen[d] = k


def _near_far_from_points(sparse: SparsePoints, cameras: Cameras, photos: _Photos) -> np.ndarray:
    """[N, 2] depth bounds from the camera z of the 3D points each photo observes."""
    _, depth = cameras.project(sparse.xyz)  # [N, P]
    return np.array(
        [depth_range(depth[k, sparse.seen_by(k)], photos.label(k)) for k in range(len(cameras))], dtype=np.float64
    )


# --- Client poses ----------------------------------------------------------------------------


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


def _check_client_sizes(cameras: Cameras, photos: _Photos) -> None:
    """The file's image size must have the photos' (upright) aspect ratio; principal points inside."""
    w, h = cameras.width, cameras.height
    pw, ph = photos.infos[0].width, photos.infos[0].height
    if abs(w / h - pw / ph) > 0.01 * pw / ph:
        hint = (
            " (rotated: is the photo portrait and the file landscape?)" if abs(h / w - pw / ph) < 0.01 * pw / ph else ""
        )
        raise CameraError(f"the cameras file is for {w}x{h} images but the photos are {pw}x{ph}{hint}")
    cx, cy = cameras.K[:, 0, 2], cameras.K[:, 1, 2]
    bad = np.where((cx <= 0) | (cx >= w) | (cy <= 0) | (cy >= h))[0]
    if len(bad):
        raise CameraError(f"principal point (cx, cy) outside the {w}x{h} image for frame(s) {bad.tolist()}")


def _near_far_by_triangulation(
    cameras: Cameras, matches: _Matches, photos: _Photos, max_error_px: float, min_angle_deg: float
) -> tuple[np.ndarray, dict[str, Any]]:
    """[N, 2] depth bounds from matched features triangulated with the known cameras.

    Raises CameraError when most matches do not fit the poses (wrong convention or frame order).
    """
    depths: list[list[np.ndarray]] = [[] for _ in photos.names]
    total = consistent = 0
    for (i, j), m in matches.pairs.items():
        if len(m) == 0:
            continue
        uv_i, uv_j = matches.keypoints[i][m[:, 0]], matches.keypoints[j][m[:, 1]]
        X, depth, err = triangulate_pair(cameras, i, j, uv_i, uv_j)
        ok = (depth > 0).all(axis=1) & (err < max_error_px)
        centres = cameras.centers[[i, j]]
        r_i, r_j = X - centres[0], X - centres[1]
        cos = np.einsum("md,md->m", r_i, r_j) / (np.linalg.norm(r_i, axis=1) * np.linalg.norm(r_j, axis=1) + 1e-12)
        wide = cos < np.cos(np.radians(min_angle_deg))
        total += len(m)
        consistent += int(ok.sum())
        depths[i].append(depth[ok & wide, 0])
        depths[j].append(depth[ok & wide, 1])
    if total == 0:
        raise PoseEstimationError(
            "no features match between the photos, so the depth range cannot be triangulated: add near/far "
            "to the cameras file, or retake the photos with more overlap of a textured scene"
        )
    if consistent < 0.5 * total:
        raise CameraError(
            f"the poses in the cameras file do not fit the photos: only {consistent} of {total} matched "
            "features triangulate in front of both cameras; check the 'convention' field (opengl vs "
            "opencv) and that each frame's file_path names the right photo"
        )
    near_far = np.array(
        [depth_range(np.concatenate(d) if d else np.zeros(0), photos.label(k)) for k, d in enumerate(depths)]
    )
    return near_far, {"matches": total, "consistent_matches": consistent}


def poses_from_client(
    image_paths: Sequence[str | Path],
    cameras: str | Path | dict,
    scene_dir: str | Path,
    *,
    long_side: int = 504,
    max_sift_size: int = 1600,
    seed: int = 0,
    should_stop: Callable[[], bool] | None = None,
    work_dir: str | Path | None = None,
    keep_originals: bool = True,
    max_pixels: int = MAX_PIXELS,
    convention: PoseConvention | None = None,
    verbose: bool = False,
    on_stage: Callable[[str], None] | None = None,
) -> PoseResult:
    """Use the app's cameras (ARKit/ARCore) for the photos; fill in near/far when absent.

    Args:
        image_paths: the uploaded photos.
        cameras: a transforms.json-shaped file or dict (``fl_x, fl_y, cx, cy, w, h``,
            ``frames[*].file_path`` / ``transform_matrix`` camera-to-world, ``convention``
            'opengl' (default, as ARKit) or 'opencv', optional per-frame ``near``/``far``).
            Frames are matched to photos by file name, else by name without extension; the
            intrinsics may be for any resolution with the photos' (upright) aspect ratio.
        scene_dir, long_side, max_sift_size, seed, should_stop, work_dir, keep_originals,
            max_pixels, verbose, on_stage: as in :func:`estimate_poses` (SIFT and matching only
            run when the file has no near/far; stages 'intake', ['features', 'matching',
            'triangulation'], 'write').
        convention: axes written to cameras.json; default: the input file's.
    Raises:
        CameraError: the file is malformed, does not match the photos, or its poses do not fit
        the matched features; SceneError, PoseEstimationError, PoseEstimationCancelled.
    """
    t_start = time.perf_counter()
    timings = _Timings(on_stage)
    if isinstance(cameras, dict):
        data_convention = cameras.get("convention", "opengl")
        client = camera_file_from_dict(cameras)
    else:
        client = load_camera_file(cameras)
        data_convention = json.loads(Path(cameras).read_text()).get("convention", "opengl")
    out_convention: PoseConvention = convention or data_convention
    need_depths = client.near_far is None
    if need_depths and len(image_paths) < 2:
        raise PoseEstimationError("with one photo the cameras file must give near and far")
    if len(client.file_paths) != len(image_paths):
        raise CameraError(f"the cameras file has {len(client.file_paths)} frames for {len(image_paths)} photos")
    pycolmap = _pycolmap() if need_depths else None
    with _work_dir(work_dir) as work, _Cancel(pycolmap, should_stop) as cancel:
        with _stage(timings, "intake"):
            photos = _read_photos(image_paths, long_side, max_sift_size, max_pixels)
            aliases = [(info.path.name, name) for info, name in zip(photos.infos, photos.names, strict=True)]
            order = match_frames(client.file_paths, aliases)
            client_cams = client.cameras[order]
            _check_client_sizes(client_cams, photos)
            scene_dir = _prepare_scene_dir(scene_dir)
            _write_photos(photos, scene_dir, work / "sfm_images" if need_depths else None, max_pixels, keep_originals)
        cancel.check()
        stats: dict[str, Any] = {"method": "client", "near_far_from": "file" if not need_depths else "triangulation"}
        if not need_depths:
            assert client.near_far is not None
            near_far = client.near_far[order]
        else:
            with _quiet(pycolmap, verbose):
                pycolmap.set_random_seed(seed)
                matches = _features_and_matches(
                    pycolmap,
                    photos,
                    work / "database.db",
                    max_sift_size,
                    seed,
                    cancel,
                    timings,
                    single_camera=False,
                    use_priors=False,
                )
            with _stage(timings, "triangulation"):
                sfm_cams = client_cams.scaled(*photos.sfm_size)
                max_error = 0.01 * max(photos.sfm_size)  # loose: phone poses are off by a few pixels
                near_far, tri_stats = _near_far_by_triangulation(
                    sfm_cams, matches, photos, max_error_px=max_error, min_angle_deg=1.0
                )
            stats.update(tri_stats)
        return _finish(
            photos,
            scene_dir,
            client_cams.scaled(*photos.working_size),
            near_far,
            out_convention,
            timings,
            stats,
            t_start,
        )


# --- Aligning two reconstructions ------------------------------------------------------------


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
    pycolmap = _pycolmap()
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
    return _world_from_cam(found["cam_from_world"]), np.asarray(found["inlier_mask"], dtype=bool)


# --- CLI -------------------------------------------------------------------------------------


def _cmd_poses(args: argparse.Namespace) -> None:
    out = Path(args.out)
    scene_dir = out.parent if out.suffix.lower() == ".json" else out
    common = dict(
        long_side=args.long_side,
        max_sift_size=args.max_sift_size,
        seed=args.seed,
        work_dir=args.work_dir,
        convention=args.convention,
        verbose=args.verbose,
    )
    if args.cameras:
        result = poses_from_client(args.images, args.cameras, scene_dir, **common)
    else:
        result = estimate_poses(args.images, scene_dir, **{**common, "convention": args.convention or "opengl"})
    written = result.cameras_path
    if out.suffix.lower() == ".json" and out.name != CAMERAS_FILE:
        shutil.copyfile(written, out)
        written = out
    nf = result.camera_file.near_far
    assert nf is not None
    cams = result.camera_file.cameras
    print(
        f"poses ({result.stats['method']}): {len(cams)} photos at {cams.width}x{cams.height}, "
        f"near {nf[:, 0].min():.4g}, far {nf[:, 1].max():.4g}"
    )
    for stage, seconds in result.timings.items():
        print(f"  {stage:<14}{seconds:8.2f} s")
    images = scene_dir / IMAGES_DIR
    print(f"wrote {written} and {len(result.image_paths)} images in {images}; train with: cmc train {scene_dir}")


def register_cli(subparsers: Any) -> None:
    """Add the ``poses`` subcommand to ``cmc``'s argparse subparsers."""
    p = subparsers.add_parser(
        "poses",
        help="cameras and near/far for a few photos (pycolmap SfM, or the app's poses); writes a scene folder",
    )
    p.add_argument("images", nargs="+", help="the photos (JPEG, PNG, WebP or HEIC)")
    p.add_argument(
        "--out",
        required=True,
        help="scene folder to write (images/, cameras.json, originals/); a path ending in .json names "
        "the cameras file and its folder is the scene folder",
    )
    p.add_argument("--cameras", help="the app's cameras (transforms.json shape) instead of structure from motion")
    p.add_argument("--long-side", type=int, default=504, help="long side of the working images, pixels (default 504)")
    p.add_argument("--max-sift-size", type=int, default=1600, help="long side SIFT runs at, pixels (default 1600)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument(
        "--convention", choices=["opengl", "opencv"], help="camera axes to write (default opengl, or the input file's)"
    )
    p.add_argument("--work-dir", help="keep COLMAP's database and sparse model here (default: a temporary folder)")
    p.add_argument("--verbose", action="store_true", help="show COLMAP's log")
    p.set_defaults(func=_cmd_poses)
