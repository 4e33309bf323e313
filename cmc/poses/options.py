"""What pose estimation takes and gives: :class:`PoseOptions`, :class:`PoseResult`, cancellation.

Conventions are :mod:`cmc.geometry.cameras`' (OpenCV axes, camera-to-world, pixel corner at 0); depth
bounds are camera z in scene units.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from cmc.data.images import MAX_PIXELS, MemoryBudget
from cmc.geometry.cameras import CameraFile, PoseConvention

# the remedy a PoseEstimationError about the photos ends with
SUGGESTION = (
    "Retake the photos with more overlap (move the camera sideways a little between shots, keep the "
    "same subject in view) of a textured scene (avoid blank walls, glass and reflections), or send "
    "camera poses with a cameras file."
)


class PoseEstimationCancelled(Exception):
    """Raised when ``should_stop`` returned True; nothing usable was written."""


@dataclass(frozen=True)
class PoseOptions:
    """The settings :func:`~cmc.poses.estimate_poses` and :func:`~cmc.poses.poses_from_client` share.

    Attributes:
        long_side: long side of the working images in pixels (never enlarged).
        max_sift_size: long side of the images SIFT runs on (pixels); bounds time and memory.
        seed: seeds COLMAP's RANSAC and mapper, so reruns give the same result.
        work_dir: keep COLMAP's database, SfM images and sparse model here (default: a
            temporary folder, removed afterwards).
        keep_originals: copy the uploads, unchanged, into ``scene_dir/originals``.
        max_pixels: refuse photos with more pixels (decompression bombs).
        convention: camera axes written to cameras.json ('opengl' as nerfstudio/ARKit, or
            'opencv'); None: 'opengl' for SfM, the input file's for client poses.
        verbose: let COLMAP log to stderr.
        decode_memory: the budget the photo decodes share with the process's other decodes
            (:meth:`cmc.data.images.MemoryBudget.reserve`); None: they wait for none.
    """

    long_side: int = 504
    max_sift_size: int = 1600
    seed: int = 0
    work_dir: str | Path | None = None
    keep_originals: bool = True
    max_pixels: int = MAX_PIXELS
    convention: PoseConvention | None = None
    verbose: bool = False
    decode_memory: MemoryBudget | None = None

    def updated(self, **changes: Any) -> PoseOptions:
        """A copy with ``changes`` (field names only; a misspelt one raises TypeError)."""
        unknown = set(changes) - {f.name for f in fields(self)}
        if unknown:
            raise TypeError(f"unknown pose option(s): {', '.join(sorted(unknown))}")
        return replace(self, **changes)


@dataclass
class PoseResult:
    """What :func:`~cmc.poses.estimate_poses` and :func:`~cmc.poses.poses_from_client` produced.

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
