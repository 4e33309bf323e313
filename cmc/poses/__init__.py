"""Cameras for a few uploaded photos: structure from motion with pycolmap, or poses from the client.

Both entry points write a *scene folder* that ``cmc train`` reads directly: ``images/NAME.png``
(upright, long side ``long_side``), ``cameras.json`` (transforms.json shape with per-view
``near``/``far``) and, by default, the untouched uploads in ``originals/``.

* :func:`estimate_poses` (:mod:`cmc.poses.sfm`) runs SIFT (at most ``max_sift_size`` pixels),
  exhaustive matching and incremental mapping tuned for 2-5 photos, keeps the model that registers
  the most photos and fails naming the photos it could not register.
* :func:`poses_from_client` (:mod:`cmc.poses.client`) takes intrinsics and poses from a
  transforms.json-shaped file (ARKit / ARCore) and triangulates the depth range when the file
  has none.
* Both take one :class:`PoseOptions`; :mod:`cmc.poses.intake` reads and matches the photos and
  diagnoses failures, :mod:`cmc.poses.bounds` derives near/far, :mod:`cmc.poses.colmap` is the
  only module that knows COLMAP's conventions and files.

Conventions are :mod:`cmc.geometry.cameras`' (OpenCV axes, camera-to-world, pixel corner at 0); depth
bounds are camera z in scene units. Aligning two reconstructions (benchmarks) is
:mod:`cmc.eval.alignment`; the ``cmc poses`` command is in :mod:`cmc.cli`.
"""

from cmc.errors import PoseEstimationError
from cmc.poses.bounds import depth_range, triangulate_pair
from cmc.poses.client import poses_from_client
from cmc.poses.colmap import cameras_from_colmap, read_colmap_cameras, read_colmap_points, sparse_points_from_colmap
from cmc.poses.intake import IMAGES_DIR, ORIGINALS_DIR
from cmc.poses.options import PoseEstimationCancelled, PoseOptions, PoseResult, SparsePoints
from cmc.poses.sfm import estimate_poses

__all__ = [
    "IMAGES_DIR",
    "ORIGINALS_DIR",
    "PoseEstimationCancelled",
    "PoseEstimationError",
    "PoseOptions",
    "PoseResult",
    "SparsePoints",
    "cameras_from_colmap",
    "depth_range",
    "estimate_poses",
    "poses_from_client",
    "read_colmap_cameras",
    "read_colmap_points",
    "sparse_points_from_colmap",
    "triangulate_pair",
]
