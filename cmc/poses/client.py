"""Client poses: :func:`poses_from_client` takes the app's intrinsics and poses (ARKit / ARCore,
a transforms.json-shaped file), checks them against the photos and, without ``near``/``far`` in
the file, triangulates matched features with the given poses to get the depth range."""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from cmc.errors import PoseEstimationError
from cmc.geometry.cameras import (
    CameraError,
    CameraFile,
    Cameras,
    PoseConvention,
    camera_file_from_dict,
    load_camera_file,
    match_frames,
)
from cmc.poses.bounds import near_far_by_triangulation
from cmc.poses.colmap import Cancel, import_pycolmap, quiet
from cmc.poses.intake import (
    Photos,
    Timings,
    features_and_matches,
    finish,
    prepare_scene_dir,
    read_photos,
    stage,
    working_folder,
    write_photos,
)
from cmc.poses.options import PoseOptions, PoseResult


def poses_from_client(
    image_paths: Sequence[str | Path],
    cameras: str | Path | dict,
    scene_dir: str | Path,
    options: PoseOptions | None = None,
    *,
    should_stop: Callable[[], bool] | None = None,
    on_stage: Callable[[str], None] | None = None,
    **changes: Any,
) -> PoseResult:
    """Use the app's cameras (ARKit/ARCore) for the photos; fill in near/far when absent.

    Args:
        image_paths: the uploaded photos.
        cameras: a transforms.json-shaped file or dict (``fl_x, fl_y, cx, cy, w, h``,
            ``frames[*].file_path`` / ``transform_matrix`` camera-to-world, ``convention``
            'opengl' (default, as ARKit) or 'opencv', optional per-frame ``near``/``far``).
            Frames are matched to photos by file name, else by name without extension; the
            intrinsics may be for any resolution with the photos' (upright) aspect ratio.
        scene_dir, options, should_stop, on_stage, changes: as in :func:`~cmc.poses.estimate_poses`
            (SIFT and matching only run when the file has no near/far; stages 'intake',
            ['features', 'matching', 'triangulation'], 'write'); ``options.convention`` None
            writes the input file's axes.
    Raises:
        CameraError: the file is malformed, does not match the photos, or its poses do not fit
        the matched features; SceneError, PoseEstimationError, PoseEstimationCancelled.
    """
    opt = (options or PoseOptions()).updated(**changes)
    t_start = time.perf_counter()
    timings = Timings(on_stage)
    client, data_convention = _read_client_cameras(cameras)
    out_convention: PoseConvention = opt.convention or data_convention
    need_depths = client.near_far is None
    if need_depths and len(image_paths) < 2:
        raise PoseEstimationError("with one photo the cameras file must give near and far")
    if len(client.file_paths) != len(image_paths):
        raise CameraError(f"the cameras file has {len(client.file_paths)} frames for {len(image_paths)} photos")
    pycolmap = import_pycolmap() if need_depths else None
    with working_folder(opt.work_dir) as work, Cancel(pycolmap, should_stop) as cancel:
        with stage(timings, "intake"):
            photos = read_photos(image_paths, opt.long_side, opt.max_sift_size, opt.max_pixels)
            aliases = [(info.path.name, name) for info, name in zip(photos.infos, photos.names, strict=True)]
            order = match_frames(client.file_paths, aliases)
            client_cams = client.cameras[order]
            _check_client_sizes(client_cams, photos)
            scene_dir = prepare_scene_dir(scene_dir)
            sfm_dir = work / "sfm_images" if need_depths else None
            write_photos(photos, scene_dir, sfm_dir, opt.max_pixels, opt.keep_originals, opt.decode_memory)
        cancel.check()
        stats: dict[str, Any] = {"method": "client", "near_far_from": "file" if not need_depths else "triangulation"}
        if not need_depths:
            assert client.near_far is not None
            near_far = client.near_far[order]
        else:
            near_far, tri_stats = _near_far_from_matches(pycolmap, photos, client_cams, work, opt, cancel, timings)
            stats.update(tri_stats)
        return finish(
            photos,
            scene_dir,
            client_cams.scaled(*photos.working_size),
            near_far,
            out_convention,
            timings,
            stats,
            t_start,
        )


def _read_client_cameras(cameras: str | Path | dict) -> tuple[CameraFile, PoseConvention]:
    """The app's cameras file (a path or its parsed dict) and the convention it is written in."""
    if isinstance(cameras, dict):
        return camera_file_from_dict(cameras), cameras.get("convention", "opengl")
    return load_camera_file(cameras), json.loads(Path(cameras).read_text()).get("convention", "opengl")


def _near_far_from_matches(
    pycolmap: Any,
    photos: Photos,
    client_cams: Cameras,
    work: Path,
    opt: PoseOptions,
    cancel: Cancel,
    timings: Timings,
) -> tuple[np.ndarray, dict[str, Any]]:
    """Near/far [N, 2] of each photo from SIFT matches triangulated with the app's cameras, and
    the triangulation's statistics (stages 'features', 'matching', 'triangulation')."""
    with quiet(pycolmap, opt.verbose):
        matches = features_and_matches(
            pycolmap,
            photos,
            work / "database.db",
            opt.max_sift_size,
            opt.seed,
            cancel,
            timings,
            single_camera=False,
            use_priors=False,
        )
    with stage(timings, "triangulation"):
        sfm_cams = client_cams.scaled(*photos.sfm_size)
        max_error = 0.01 * max(photos.sfm_size)  # loose: phone poses are off by a few pixels
        return near_far_by_triangulation(sfm_cams, matches, photos, max_error_px=max_error, min_angle_deg=1.0)


def _check_client_sizes(cameras: Cameras, photos: Photos) -> None:
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
