"""Structure from motion for 2-5 photos: :func:`estimate_poses` (pycolmap SIFT, exhaustive matching,
incremental mapping tuned for a few photos). Poses are up to a similarity (SfM has no scale)."""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from cmc.errors import PoseEstimationError
from cmc.geometry.camera_paths import mean_pose
from cmc.geometry.cameras import Cameras
from cmc.poses.bounds import near_far_from_points
from cmc.poses.colmap import Cancel, cameras_from_colmap, import_pycolmap, quiet, sparse_points_from_colmap
from cmc.poses.intake import (
    Matches,
    Photos,
    Timings,
    diagnose,
    features_and_matches,
    finish,
    focal_priors,
    one_device,
    prepare_scene_dir,
    read_photos,
    refuse_identical,
    stage,
    working_folder,
    write_photos,
)
from cmc.poses.options import SUGGESTION, PoseOptions, PoseResult, SparsePoints


def estimate_poses(
    image_paths: Sequence[str | Path],
    scene_dir: str | Path,
    options: PoseOptions | None = None,
    *,
    should_stop: Callable[[], bool] | None = None,
    on_stage: Callable[[str], None] | None = None,
    **changes: Any,
) -> PoseResult:
    """Intrinsics, camera-to-world poses and near/far for 2-5 photos by structure from motion.

    Args:
        image_paths: the uploaded photos (JPEG/PNG/WebP/HEIC, any file names).
        scene_dir: output scene folder (``images/``, ``cameras.json``, ``originals/``).
        options: sizes, seed, folders, convention (default 'opengl' here); see :class:`PoseOptions`.
        should_stop: polled from a helper thread (make it thread-safe); True cancels at the next
            checkpoint of the running stage and raises PoseEstimationCancelled.
        on_stage: called with each stage's name as it starts ('intake', 'features', 'matching',
            'mapping', 'near_far', 'write'), e.g. to report progress.
        changes: :class:`PoseOptions` fields given as keywords (``long_side=160``), applied on top
            of ``options``.
    Returns:
        PoseResult; the poses are up to a similarity (SfM has no absolute scale or orientation).
    Raises:
        SceneError: unusable photos; PoseEstimationError: SfM failed (the message names the
        photos it could not register and what to do); PoseEstimationCancelled.
    """
    opt = (options or PoseOptions()).updated(**changes)
    t_start = time.perf_counter()
    pycolmap = import_pycolmap()
    timings = Timings(on_stage)
    if len(image_paths) < 2:
        raise PoseEstimationError(f"structure from motion needs at least 2 photos, got {len(image_paths)}")
    with working_folder(opt.work_dir) as work, Cancel(pycolmap, should_stop) as cancel, quiet(pycolmap, opt.verbose):
        with stage(timings, "intake"):
            photos = read_photos(image_paths, opt.long_side, opt.max_sift_size, opt.max_pixels)
            scene_dir = prepare_scene_dir(scene_dir)
            write_photos(photos, scene_dir, work / "sfm_images", opt.max_pixels, opt.keep_originals, opt.decode_memory)
        refuse_identical(photos)
        cancel.check()
        single_camera = one_device(photos)
        matches = features_and_matches(
            pycolmap,
            photos,
            work / "database.db",
            opt.max_sift_size,
            opt.seed,
            cancel,
            timings,
            single_camera,
            use_priors=True,
        )
        refine_focal = any(p is None for p in focal_priors(photos))
        with stage(timings, "mapping"), cancel.running():
            reconstruction = _best_model(pycolmap, work, photos, refine_focal, opt.seed, cancel)
        sfm_names = [p.name for p in photos.sfm_paths]
        _require_all_registered(reconstruction, sfm_names, photos, matches)
        with stage(timings, "near_far"):
            cameras = cameras_from_colmap(reconstruction, sfm_names).scaled(*photos.working_size)
            to_working = (photos.working_size[0] / photos.sfm_size[0], photos.working_size[1] / photos.sfm_size[1])
            sparse = sparse_points_from_colmap(reconstruction, sfm_names, to_working)
            near_far = near_far_from_points(sparse, cameras, photos)
            cameras, sparse = upright(cameras, sparse)
        stats = {
            "method": "sfm",
            "registered": len(sfm_names),
            "points3D": reconstruction.num_points3D(),
            "mean_reprojection_error_px": float(reconstruction.compute_mean_reprojection_error()),
            "sfm_size": list(photos.sfm_size),
            "focal_prior": [i.focal_source for i in photos.infos],
            "single_camera": single_camera,
            "pycolmap": pycolmap.__version__,
        }
        convention = opt.convention or "opengl"
        return finish(photos, scene_dir, cameras, near_far, convention, timings, stats, t_start, sparse)


def upright(cameras: Cameras, sparse: SparsePoints) -> tuple[Cameras, SparsePoints]:
    """The reconstruction turned about the world origin so that its mean camera
    (:func:`cmc.geometry.camera_paths.mean_pose`) looks down world -z with the photos' up along world +y,
    the axes of OpenGL and ARKit. SfM's own frame is a photo's OpenCV axes, where up is -y: a
    client that moves a camera of this scene with +y up (a look-at, an orbit) would turn the view
    upside down. Depths, near/far and every relative pose are unchanged."""
    R_mean = mean_pose(cameras.world_from_cam)[:3, :3] @ np.diag([1.0, -1.0, -1.0])  # OpenGL axes
    turn = R_mean.T
    poses = cameras.world_from_cam.copy()
    poses[:, :3, :3] = turn @ poses[:, :3, :3]
    poses[:, :3, 3] = poses[:, :3, 3] @ turn.T
    return replace(cameras, world_from_cam=poses), replace(sparse, xyz=sparse.xyz @ turn.T)


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


def _best_model(pycolmap: Any, work: Path, photos: Photos, refine_focal: bool, seed: int, cancel: Cancel) -> Any:
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


def _require_all_registered(reconstruction: Any, names: Sequence[str], photos: Photos, matches: Matches) -> None:
    """Raise PoseEstimationError naming each unregistered photo with a likely reason."""

    def registered(name: str) -> bool:
        image = None if reconstruction is None else reconstruction.find_image_with_name(name)
        return image is not None and image.has_pose

    ok = [registered(n) for n in names]
    if all(ok):
        return
    failed = [k for k, good in enumerate(ok) if not good]
    detail = "; ".join(f"{photos.label(k)}: {diagnose(photos, matches, k)}" for k in failed)
    got = ", ".join(photos.label(k) for k, good in enumerate(ok) if good) or "none"
    raise PoseEstimationError(
        f"could not register {len(failed)} of {len(ok)} photos ({detail}); registered: {got}. {SUGGESTION}"
    )
