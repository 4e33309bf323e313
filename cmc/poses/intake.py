"""Photo intake and matching for pose estimation: reading and checking the photos, writing the
working images, SIFT and exhaustive matching into a COLMAP database, why a photo failed to
register, and the scene folder (``images/``, ``originals/``, ``cameras.json``).

Sizes are (width, height) in pixels; keypoints are at the SfM resolution (``Photos.sfm_size``).
"""

from __future__ import annotations

import hashlib
import re
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cmc.data.datasets import CAMERAS_FILE, SceneError
from cmc.data.images import MemoryBudget, PhotoInfo, load_resized, read_photo_info, resized_size, save_png
from cmc.errors import PoseEstimationError
from cmc.geometry.cameras import CameraFile, Cameras, PoseConvention, save_camera_file
from cmc.poses.colmap import Cancel
from cmc.poses.options import PoseResult, SparsePoints

IMAGES_DIR = "images"
ORIGINALS_DIR = "originals"
SFM_CAMERA_MODEL = "SIMPLE_PINHOLE"  # f, cx, cy: what a Cameras entry can hold (no distortion)
MIN_FEATURES = 100  # fewer SIFT features than this: blank, blurred or textureless photo
MIN_PAIR_INLIERS = 30  # fewer verified matches than this: unrelated photos or too little overlap


class Timings(dict):
    """Wall-clock seconds per stage; calls ``on_stage(name)`` as each stage starts (progress)."""

    def __init__(self, on_stage: Callable[[str], None] | None = None):
        super().__init__()
        self.on_stage = on_stage


@contextmanager
def stage(timings: Timings, name: str) -> Iterator[None]:
    if timings.on_stage is not None:
        timings.on_stage(name)
    t0 = time.perf_counter()
    try:
        yield
    finally:
        timings[name] = timings.get(name, 0.0) + time.perf_counter() - t0


@contextmanager
def working_folder(work_dir: str | Path | None) -> Iterator[Path]:
    if work_dir is not None:
        path = Path(work_dir)
        path.mkdir(parents=True, exist_ok=True)
        yield path
    else:
        with tempfile.TemporaryDirectory(prefix="cmc-poses-") as tmp:
            yield Path(tmp)


@dataclass
class Photos:
    """The photos: header facts, then (after :func:`write_photos`) the files written.

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


def read_photos(image_paths: Sequence[str | Path], long_side: int, max_sift_size: int, max_pixels: int) -> Photos:
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
    return Photos(infos, _unique_names(paths), [], sizes[0], [], sfm_size, [])


def write_photos(
    photos: Photos,
    scene_dir: Path,
    sfm_dir: Path | None,
    max_pixels: int,
    keep_originals: bool,
    decode_memory: MemoryBudget | None = None,
) -> None:
    """Decode each photo once (waiting for its memory in ``decode_memory``, when given); write its
    working image (and SfM-size copy into ``sfm_dir``)."""
    photos.working_paths = [scene_dir / IMAGES_DIR / f"{n}.png" for n in photos.names]
    photos.sfm_paths = [sfm_dir / f"{n}.png" for n in photos.names] if sfm_dir is not None else []
    wanted = [photos.working_size] + ([photos.sfm_size] if sfm_dir is not None else [])
    for k, info in enumerate(photos.infos):
        decoded = load_resized(info, wanted, max_pixels, decode_memory)
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
class Matches:
    """Features and verified matches read back from the COLMAP database (indices = photo order)."""

    keypoints: list[np.ndarray]  # [K_i, 2] pixel coordinates at the SfM resolution
    pairs: dict[tuple[int, int], np.ndarray]  # (i, j), i < j -> [M, 2] inlier keypoint indices


def focal_priors(photos: Photos) -> list[float | None]:
    """EXIF focal priors in pixels at the SfM resolution."""
    return [None if i.focal_px is None else i.focal_px * photos.sfm_size[0] / i.width for i in photos.infos]


def one_device(photos: Photos) -> bool:
    """True when the photos look like one camera (same EXIF device and focal, or no EXIF at all)."""
    devices = {i.device for i in photos.infos}
    focals = [i.focal_px for i in photos.infos]
    if len(devices) > 1 or len({f is None for f in focals}) > 1:
        return False
    known = [f for f in focals if f is not None]
    return not known or (max(known) - min(known)) <= 0.01 * max(known)


def features_and_matches(
    pycolmap: Any,
    photos: Photos,
    database: Path,
    max_sift_size: int,
    seed: int,
    cancel: Cancel,
    timings: Timings,
    single_camera: bool,
    use_priors: bool,
) -> Matches:
    """SIFT into a fresh database, EXIF focal priors into its cameras, exhaustive matching
    (pycolmap's random seed set to ``seed`` first, so reruns match the same)."""
    pycolmap.set_random_seed(seed)
    database.unlink(missing_ok=True)
    sfm_dir = photos.sfm_paths[0].parent
    file_names = [p.name for p in photos.sfm_paths]
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = SFM_CAMERA_MODEL
    extraction = sift_options(pycolmap, max_sift_size, max(photos.sfm_size))
    mode = pycolmap.CameraMode.SINGLE if single_camera else pycolmap.CameraMode.PER_IMAGE
    with stage(timings, "features"), cancel.running():
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
    priors = focal_priors(photos) if use_priors else [None] * len(file_names)
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
    with stage(timings, "matching"), cancel.running():
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
    return Matches(keypoints, pairs)


SIFT_FULL_SIZE = 1600  # long side (pixels) from which SIFT keeps COLMAP's threshold and skips the doubled octave


def sift_options(pycolmap: Any, max_image_size: int, long_side: int) -> Any:
    """pycolmap's feature extraction options as cmc extracts SIFT from photos of ``long_side``
    pixels, scaled down to at most ``max_image_size``: COLMAP's defaults with the contrast
    threshold of :func:`sift_peak_threshold` and the first octave of :func:`sift_first_octave`."""
    options = pycolmap.FeatureExtractionOptions()
    options.max_image_size = max_image_size
    options.sift.peak_threshold = sift_peak_threshold(long_side, options.sift.peak_threshold)
    options.sift.first_octave = sift_first_octave(long_side, options.sift.first_octave)
    return options


def sift_peak_threshold(long_side: int, default: float) -> float:
    """SIFT's contrast threshold for photos of ``long_side`` pixels: COLMAP's ``default`` at
    :data:`SIFT_FULL_SIZE` and above, lowered in proportion below it. A small photo holds fewer
    features over that threshold (a 504-pixel photo of a plain room about 500), too few for three
    photos to share the matches structure from motion needs."""
    return default * min(1.0, long_side / SIFT_FULL_SIZE)


def sift_first_octave(long_side: int, default: int) -> int:
    """SIFT's first octave for photos of ``long_side`` pixels: COLMAP's ``default`` (-1: the
    photo doubled) below :data:`SIFT_FULL_SIZE`, where small photos need it for features enough;
    0 (the photo's own scale) at and above it, where the doubled octave adds features of a
    scale finer than phone optics resolve and takes 60 % of the pose stage's time (fern's phone
    photos: 6.47 -> 2.45 s, their poses as accurate: bench/reports/history/sift_octave.md)."""
    return default if long_side < SIFT_FULL_SIZE else 0


def _pair_shift(matches: Matches, i: int, j: int) -> float:
    """Median image displacement (pixels, SfM resolution) of the verified matches of (i, j)."""
    m = matches.pairs.get((i, j))
    if m is None or len(m) == 0:
        return float("nan")
    return float(np.median(np.linalg.norm(matches.keypoints[i][m[:, 0]] - matches.keypoints[j][m[:, 1]], axis=1)))


def diagnose(photos: Photos, matches: Matches, k: int) -> str:
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


def refuse_identical(photos: Photos) -> None:
    seen: dict[str, int] = {}
    for k, d in enumerate(photos.digests):
        if d in seen:
            raise PoseEstimationError(
                f"photos {photos.label(seen[d])} and {photos.label(k)} are identical; "
                "take each photo from a slightly different position."
            )
        seen[d] = k


def finish(
    photos: Photos,
    scene_dir: Path,
    cameras: Cameras,
    near_far: np.ndarray,
    convention: PoseConvention,
    timings: Timings,
    stats: dict[str, Any],
    t_start: float,
    sparse: SparsePoints | None = None,
) -> PoseResult:
    """Write cameras.json (working resolution) last, so a scene folder with it is complete."""
    with stage(timings, "write"):
        file_paths = [f"{IMAGES_DIR}/{p.name}" for p in photos.working_paths]
        camera_file = CameraFile(cameras, file_paths, np.asarray(near_far, dtype=np.float64))
        path = scene_dir / CAMERAS_FILE
        save_camera_file(camera_file, path, convention)
    timings["total"] = time.perf_counter() - t_start
    return PoseResult(camera_file, list(photos.working_paths), scene_dir, path, timings, stats, sparse)


def prepare_scene_dir(scene_dir: str | Path) -> Path:
    scene_dir = Path(scene_dir)
    scene_dir.mkdir(parents=True, exist_ok=True)
    (scene_dir / CAMERAS_FILE).unlink(missing_ok=True)  # a stale file would pair old cameras with new images
    return scene_dir
