"""End to end on an LLFF scene: train from the poses ``cmc poses`` estimates vs the dataset's poses.

Both runs train the same preset with the same seed on the same pixels (the dataset's ``images_8``
PNGs of the RegNeRF training views, e.g. fern's 1, 10, 19); only the cameras differ:

(a) dataset: ``poses_bounds.npy`` poses, intrinsics and scene-wide bounds, as ``load_llff`` gives them;
(b) estimated: :func:`cmc.poses.estimate_poses` on the photos of the same three views (intrinsics,
    poses and per-view near/far at the 504x378 working resolution, arbitrary frame): the
    full-resolution photos in ``images/`` where the scene has them (fern), else the ``images_8``
    PNGs themselves (room, trex: what a user uploading 504x378 photos gets; with ``--exif-focal``
    they carry the dataset's focal length as the EXIF tag a phone writes, as a phone's photos do).

The held-out views (0, 8, 16) have dataset poses only. Run (b) needs them in its own frame; two
ways of aligning the two reconstructions are scored, neither looks at a held-out image:

* ``structure`` (the target's number where the scene ships ``sparse/0``):
  through the 3D points. The dataset ships its sparse model
  (``sparse/0``: points and its SIMPLE_RADIAL camera). Our SfM points and the dataset's points that
  the three shared photos see at the same pixels are the same scene points
  (:func:`cmc.eval.alignment.corresponding_points`; dataset points projected with the dataset's poses and
  its distortion, ours where SfM observed them). A held-out view sees each dataset point where the
  dataset's pose and camera project it; its pose in frame (b) is the camera that sees the
  corresponding points of (b) at those pixels (:func:`cmc.eval.alignment.register_camera`, LO-RANSAC P3P +
  refinement), as SfM would register that photo into (b) with perfect matches. Control: the same
  procedure on the training views must give back (b)'s own SfM poses.
* ``points`` (the target's number where the scene has no sparse model): each held-out photo is
  registered into reconstruction (b) as it stands, by SIFT matches to the three training photos
  that land on (b)'s SfM points and P3P with (b)'s camera (:func:`register_into_reconstruction`),
  as SfM registers a further photo into a model. (Until 2026-12-06 it ran SfM on the three photos
  plus the held-out one and carried that camera over by the similarity of the three shared
  cameras: each such run found its own focal length, 342-460 px on room against (b)'s 397 px,
  and put the held-out camera a few pixels off; reports of then name this registration ``sfm``.)
* ``similarity``: one similarity from the three training cameras
  (:func:`cmc.eval.alignment.similarity_from_cameras`: rotation = chordal mean of ``R_gt_i R_est_i^T``,
  scale = ratio of the RMS centre spreads, translation from the centroids), applied as a pose
  transform (centre: scaled, rotated and shifted; orientation: rotated only).

Both runs render the test views at 504x378: run (a) and the ``structure`` and ``similarity``
registrations with the dataset's intrinsics, ``points`` with run (b)'s own (the photos share one
camera, and (b)'s model is consistent with its focal length, not the dataset's).

``--refine-test-poses`` adds a diagnostic: each registered test pose of each run is refined
photometrically against that run's frozen baked model (:func:`refine_test_pose`) and scored again,
which separates the test-view registration error from the quality of the reconstruction itself.
``--refine-test-poses model`` also registers each held-out photo to the model's own render by
SIFT matches and P3P (:func:`register_to_model`, which recovers offsets the local photometric
search cannot), and ``focal`` refines each test view's focal length with its pose.

Usage::

    nice -n 19 .venv/bin/python bench/poses_e2e.py --data ../shared/datasets/llff/fern --steps 400 \\
        --lpips-dir ../shared/weights --out bench/reports/current/poses_e2e.json \\
        [--refine-test-poses [pose|focal|model]]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import os
import platform
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import ExifTags, Image

from cmc.config import preset_config, with_settings
from cmc.data.datasets import LLFFSplit, Scene, load_image, load_llff, save_image
from cmc.data.images import FULL_FRAME_DIAGONAL_MM
from cmc.errors import PoseEstimationError
from cmc.eval.alignment import (
    apply_similarity_to_poses,
    corresponding_points,
    invert_similarity,
    mutual_matches,
    register_camera,
    register_photo,
    sift_features,
    similarity_from_cameras,
)
from cmc.eval.bench import git_commit
from cmc.eval.metrics import image_metrics
from cmc.geometry.cameras import Cameras
from cmc.geometry.planes import mean_baseline
from cmc.method.training import Trainer
from cmc.poses import PoseOptions, PoseResult, estimate_poses, read_colmap_cameras, read_colmap_points
from cmc.serving.baking import MANIFEST, BakedScene, bake

METRICS = ("psnr", "ssim", "lpips_alex", "lpips_vgg")


def rotation_angle_deg(A: np.ndarray, B: np.ndarray) -> float:
    """Angle of the rotation taking A to B (both [3, 3]), degrees."""
    return float(np.degrees(np.arccos(np.clip((np.trace(A.T @ B) - 1) / 2, -1, 1))))


def training_photos(data: Path, ids: list[int], num_views: int) -> list[Path]:
    """The photos of the views ``ids`` to estimate poses from: the originals (``images/``, sorted
    like ``images_8``) where the scene has them, else the ``images_8`` PNGs.

    The shared fern copy holds only the photos of the training views; then ``images/`` must hold
    exactly ``len(ids)`` photos, taken as those views in sorted order (checked against ``images_8``
    after pose estimation, see :func:`estimated_scene`).
    """
    folder = data / "images" if (data / "images").is_dir() else data / "images_8"
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    if len(files) == num_views:
        return [files[i] for i in ids]
    if len(files) == len(ids):
        return files
    raise SystemExit(f"{folder} holds {len(files)} photos: need all {num_views} or the {len(ids)} train views")


def estimated_scene(split: LLFFSplit, est: PoseResult) -> tuple[Scene, dict[str, Any]]:
    """Training scene (b): the dataset's pixels with the estimated cameras and near/far."""
    train = split.train
    cams = est.camera_file.cameras
    w, h = train.cameras.width, train.cameras.height
    working = [load_image(p).shape[:2] for p in est.image_paths]
    check = {
        "working_image_size": [working[0][1], working[0][0]],
        "estimated_intrinsics_size": [cams.width, cams.height],
        "dataset_image_size": [w, h],
        "intrinsics_rescaled": False,
    }
    if any(s != (h, w) for s in working):
        print(f"note: estimated working images are {working}, images_8 are {h}x{w}", file=sys.stderr)
    else:  # the photo of each view: its working image must be closest to that view's images_8 PNG
        diff = np.array([[np.abs(load_image(p) - im).mean() for im in train.images] for p in est.image_paths])
        check["working_vs_images_8_mean_abs_diff"] = np.diag(diff).tolist()
        if (diff.argmin(axis=1) != np.arange(len(diff))).any():
            raise SystemExit(f"the photos do not match the training views of images_8 (mean abs diff {diff.tolist()})")
    if (cams.width, cams.height) != (w, h):  # same aspect ratio assumed (SfM scales K uniformly)
        cams = cams.scaled(w, h)
        check["intrinsics_rescaled"] = True
    nf = np.asarray(est.camera_file.near_far, dtype=np.float64)
    return Scene(train.images.copy(), cams, nf, list(train.names)), check


def alignment(gt: Cameras, est: Cameras) -> dict[str, Any]:
    """Similarity est -> gt from the training cameras, with its residuals per view."""
    scale, R, t = similarity_from_cameras(est.world_from_cam, gt.world_from_cam)
    aligned = apply_similarity_to_poses(est.world_from_cam, scale, R, t)
    centre_err = np.linalg.norm(aligned[:, :3, 3] - gt.centers, axis=1)
    rot_err = [rotation_angle_deg(a[:3, :3], g[:3, :3]) for a, g in zip(aligned, gt.world_from_cam, strict=True)]
    baseline = mean_baseline(gt.centers)
    return {
        "scale_est_to_gt": scale,
        "R_est_to_gt": R.tolist(),
        "t_est_to_gt": t.tolist(),
        "gt_mean_baseline": baseline,
        "centre_error_gt_units": centre_err.tolist(),
        "centre_error_fraction_of_baseline": (centre_err / baseline).tolist(),
        "rotation_error_deg": rot_err,
        "focal_px_dataset": gt.K[:, 0, 0].tolist(),
        "focal_px_estimated": est.K[:, 0, 0].tolist(),
        "principal_point_estimated": est.K[:, :2, 2].tolist(),
    }


def register_through_structure(data: Path, split: LLFFSplit, est: PoseResult) -> tuple[np.ndarray, dict[str, Any]]:
    """Held-out poses in the estimated frame, registered through the 3D points (module docstring).

    Returns: world_from_cam [T, 4, 4] of the test views in frame (b), and a report (correspondence
    and inlier counts, and the control: training views registered the same way vs their SfM poses).
    """
    assert est.sparse is not None, "SfM result without its sparse points"
    xyz_gt = read_colmap_points(data / "sparse" / "0" / "points3D.bin")
    (camera,) = read_colmap_cameras(data / "sparse" / "0" / "cameras.bin")  # LLFF: one shared camera
    w, h = split.train.cameras.width, split.train.cameras.height
    camera.rescale(w, h)

    def seen_by_dataset(world_from_cam: np.ndarray, X: np.ndarray) -> np.ndarray:
        """[P, 2] pixels where a dataset camera sees X (the dataset's distortion); NaN when unseen."""
        cam = (X - world_from_cam[:3, 3]) @ world_from_cam[:3, :3]  # camera coordinates
        uv = np.asarray(camera.img_from_cam(cam), dtype=np.float64).reshape(-1, 2)
        inside = (cam[:, 2] > 0) & (uv[:, 0] > 0) & (uv[:, 0] < w) & (uv[:, 1] > 0) & (uv[:, 1] < h)
        uv[~inside] = np.nan
        return uv

    shared = np.stack([seen_by_dataset(p, xyz_gt) for p in split.train.cameras.world_from_cam], axis=1)
    ia, ib = corresponding_points(est.sparse.pixels, shared)
    X_est, X_gt = est.sparse.xyz[ia], xyz_gt[ib]

    def register(cams: Cameras, k: int) -> tuple[np.ndarray, dict[str, Any]]:
        uv = seen_by_dataset(cams.world_from_cam[k], X_gt)
        ok = ~np.isnan(uv[:, 0])
        pose, inliers = register_camera(cams.K[k], w, h, X_est[ok], uv[ok], seed=0)
        return pose, {"points": int(ok.sum()), "inliers": int(inliers.sum())}

    sfm = est.camera_file.cameras.world_from_cam
    baseline = mean_baseline(sfm[:, :3, 3])
    control = []
    for k, view in enumerate(split.train_ids):
        pose, info = register(split.train.cameras, k)
        control.append(
            {
                "view": view,
                **info,
                "rotation_vs_sfm_deg": rotation_angle_deg(sfm[k, :3, :3], pose[:3, :3]),
                "centre_vs_sfm_fraction_of_baseline": float(np.linalg.norm(pose[:3, 3] - sfm[k, :3, 3]) / baseline),
            }
        )
    poses, test = [], []
    for k, view in enumerate(split.test_ids):
        pose, info = register(split.test.cameras, k)
        poses.append(pose)
        test.append({"view": view, **info})
    report = {
        "dataset_points": len(xyz_gt),
        "sfm_points": len(est.sparse.xyz),
        "corresponding_points": len(ia),
        "dataset_camera": {"model": camera.model_name, "params": [float(x) for x in camera.params], "size": [w, h]},
        "control_train_views": control,
        "test_views": test,
    }
    return np.stack(poses), report


def with_exif_focal(paths: list[Path], focal_px: float, folder: Path) -> list[Path]:
    """Copies in ``folder`` of the PNGs among ``paths`` carrying the EXIF tag a phone writes,
    ``FocalLengthIn35mmFilm`` (whole millimetres, so about 1 % off), for the focal length
    ``focal_px`` at their own size; other photos (JPEGs with their own EXIF) as they are."""
    out = []
    for path in paths:
        if path.suffix.lower() != ".png":
            out.append(path)
            continue
        with Image.open(path) as im:
            exif = Image.Exif()
            f35 = focal_px * FULL_FRAME_DIAGONAL_MM / math.hypot(*im.size)  # as cmc.data.images.exif_focal_px reads it
            exif[ExifTags.Base.FocalLengthIn35mmFilm] = round(f35)
            folder.mkdir(parents=True, exist_ok=True)
            im.save(folder / path.name, exif=exif)
        out.append(folder / path.name)
    return out


def register_into_reconstruction(
    data: Path, split: LLFFSplit, est: PoseResult, images: np.ndarray
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Each held-out photo's camera in frame (b), registered into reconstruction (b) as it stands.

    Where the scene has no sparse model to register through: SIFT matches between the held-out
    photo (the ``images_8`` PNG) and the three working images of (b) give it the pixels of (b)'s
    SfM points, and LO-RANSAC P3P with (b)'s intrinsics (the photos share one camera) its pose
    (:func:`cmc.eval.alignment.register_photo`), as SfM registers a further photo into a model.
    ``images`` [3, H, W, 3] are (b)'s working images (``est.image_paths``), where its points were seen.
    Control: the training photos registered the same way must give back their own SfM poses.
    Returns K [T, 3, 3], poses [T, 4, 4] and a report (counts per view, the control).
    """
    assert est.sparse is not None, "SfM result without its sparse points"
    files = sorted(p for p in (data / "images_8").iterdir() if p.suffix.lower() == ".png")
    cams_b = est.camera_file.cameras
    baseline = mean_baseline(cams_b.centers)
    features = [sift_features(image) for image in images]  # each photo registered matches against these
    control = []
    for k, view in enumerate(split.train_ids):
        pose, info = register_photo(images[k], images, est.sparse, cams_b.K[k], image_features=features)
        control.append(
            {
                "view": view,
                **info,
                "rotation_vs_sfm_deg": rotation_angle_deg(cams_b.world_from_cam[k, :3, :3], pose[:3, :3]),
                "centre_vs_sfm_fraction_of_baseline": float(
                    np.linalg.norm(pose[:3, 3] - cams_b.world_from_cam[k, :3, 3]) / baseline
                ),
            }
        )
    poses, records = [], []
    for view in split.test_ids:
        pose, info = register_photo(load_image(files[view]), images, est.sparse, cams_b.K[0], image_features=features)
        poses.append(pose)
        records.append({"view": view, **info})
        print(f"view {view}: {records[-1]}", file=sys.stderr, flush=True)
    Ks = np.repeat(cams_b.K[:1], len(poses), axis=0)
    report = {"sfm_points": len(est.sparse.xyz), "control_train_views": control, "test_views": records}
    return Ks, np.stack(poses), report


def _rodrigues(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of the axis-angle vector ``w`` (radians)."""
    a = float(np.linalg.norm(w))
    if a < 1e-15:
        return np.eye(3)
    k = w / a
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(a) * Kx + (1 - np.cos(a)) * Kx @ Kx


def _blur(img: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur of an [H, W, C] image (reflect padding); identity for sigma 0."""
    if sigma <= 0:
        return img
    r = int(3 * sigma + 0.5)
    x = torch.arange(-r, r + 1, dtype=img.dtype)
    g = torch.exp(-0.5 * (x / sigma) ** 2)
    g = g / g.sum()
    t = img.permute(2, 0, 1)[:, None]  # [C, 1, H, W]
    t = torch.nn.functional.conv2d(torch.nn.functional.pad(t, (r, r, 0, 0), mode="reflect"), g.view(1, 1, 1, -1))
    t = torch.nn.functional.conv2d(torch.nn.functional.pad(t, (0, 0, r, r), mode="reflect"), g.view(1, 1, -1, 1))
    return t[:, 0].permute(1, 2, 0)


def refine_test_pose(
    baked: BakedScene,
    K: np.ndarray,
    pose: np.ndarray,
    target: np.ndarray,
    depth: float,
    stages: tuple[tuple[int, float], ...] = ((2, 2.0), (2, 0.0), (1, 0.0)),
    iters: int = 6,
    focal: bool = False,
) -> tuple[np.ndarray, np.ndarray, dict[str, float]]:
    """Photometric 6-DoF refinement of one test pose against a frozen baked model (diagnostic).

    Gauss-Newton / Levenberg-Marquardt on the RGB residual with a forward-difference Jacobian,
    coarse to fine over ``stages`` of (downsampling factor, Gaussian blur sigma in pixels of that
    resolution); the coarse stages render at reduced size (same camera, K scaled) against the
    area-downsampled target. The update is applied in the camera frame, ``pose @ [exp(w) | v]``,
    with parameters scaled to about one full-resolution pixel of image motion each (rotation:
    1 / f radians; translation: ``depth`` / f scene units, one pixel at depth ``depth``). With
    ``focal`` a seventh parameter scales the focal length (one unit: one pixel at the image's
    left and right edges). Returns the refined pose, the intrinsics and the size of the correction.
    """
    f = float(K[0, 0])
    gt_full = torch.as_tensor(target, dtype=torch.float32)
    H, W = gt_full.shape[:2]
    unit = np.array([1 / f] * 3 + [depth / f] * 3 + ([2 / W] if focal else []))

    def pose_of(p: np.ndarray) -> np.ndarray:
        d = np.eye(4)
        d[:3, :3], d[:3, 3] = _rodrigues(p[:3] * unit[:3]), p[3:6] * unit[3:6]
        return pose @ d

    def K_of(p: np.ndarray) -> np.ndarray:
        scale = 1 + p[6] * unit[6] if focal else 1.0
        out = np.array(K, dtype=np.float64)
        out[0, 0] *= scale
        out[1, 1] *= scale
        return out

    p = np.zeros(len(unit))
    for down, sigma in stages:
        w, h = W // down, H // down
        gt = gt_full.permute(2, 0, 1)[None]
        gt = torch.nn.functional.adaptive_avg_pool2d(gt, (h, w))[0].permute(1, 2, 0) if down > 1 else gt_full
        gt_b = _blur(gt, sigma)

        def residual(q: np.ndarray, w=w, h=h, sigma=sigma, gt_b=gt_b) -> np.ndarray:
            K_s = np.diag([w / W, h / H, 1.0]) @ K_of(q)
            rgb = torch.from_numpy(baked.render(K_s, pose_of(q), w, h).rgb)
            return (_blur(rgb, sigma) - gt_b).reshape(-1).numpy().astype(np.float64)

        r = residual(p)
        lam = 1e-3
        for _ in range(iters):
            J = np.stack([(residual(p + 0.5 * e) - r) / 0.5 for e in np.eye(len(p))], 1)
            JtJ, g = J.T @ J, J.T @ r
            improved = False
            for _ in range(4):
                step = -np.linalg.solve(JtJ + lam * np.diag(np.diag(JtJ) + 1e-9), g)
                r_new = residual(p + step)
                if r_new @ r_new < r @ r:
                    p, r, lam, improved = p + step, r_new, lam * 0.3, True
                    break
                lam *= 10
            if not improved or np.abs(step).max() < 0.05:
                break
    refined = pose_of(p)
    rel = np.linalg.inv(pose) @ refined
    return (
        refined,
        K_of(p),
        {
            "rotation_deg": rotation_angle_deg(np.eye(3), rel[:3, :3]),
            "focal_scale": float(K_of(p)[0, 0] / K[0, 0]),
            "translation_scene_units": float(np.linalg.norm(rel[:3, 3])),
            "params_px": p.tolist(),
        },
    )


def register_to_model(
    baked: BakedScene, K: np.ndarray, pose: np.ndarray, target: np.ndarray, rounds: int = 3
) -> tuple[np.ndarray, dict[str, Any]]:
    """Pose of the photo ``target`` in the frame of the model ``baked``, as a photo is registered
    into a reconstruction: SIFT matches between the photo and the model's own render at ``pose``,
    the render's keypoints lifted to 3D by its depth (where its coverage is full and the depth
    smooth), and LO-RANSAC P3P on those (:func:`cmc.eval.alignment.register_camera`); repeated from the
    new pose ``rounds`` times. Unlike :func:`refine_test_pose`'s local search it recovers offsets of
    many pixels. Uses the held-out image: a diagnostic of the reconstruction, not of the protocol."""
    kp_t, d_t = sift_features(target)
    H, W = target.shape[:2]
    Kinv = np.linalg.inv(K)
    history = []
    for _ in range(rounds):
        out = baked.render(K, pose)
        rgb, depth, acc = out.rgb, out.depth, out.acc
        kp_r, d_r = sift_features(rgb)
        m = mutual_matches(d_r, d_t)
        uv = kp_r[m[:, 0]]
        col = np.clip(uv[:, 0].astype(int), 1, W - 2)
        row = np.clip(uv[:, 1].astype(int), 1, H - 2)
        z = depth[row, col]
        win = np.stack([depth[row + a, col + b] for a in (-1, 0, 1) for b in (-1, 0, 1)])
        smooth = (win.max(0) - win.min(0)) < 0.02 * z
        ok = (acc[row, col] > 0.98) & smooth & (z > 0)
        X_cam = (np.c_[uv[ok], np.ones(int(ok.sum()))] @ Kinv.T) * z[ok, None]
        X = X_cam @ pose[:3, :3].T + pose[:3, 3]
        try:
            new_pose, inliers = register_camera(K, W, H, X, kp_t[m[ok, 1]], max_error_px=2.0)
        except PoseEstimationError as e:
            history.append({"matches": int(len(m)), "lifted": int(ok.sum()), "error": str(e)})
            break
        rel = np.linalg.inv(pose) @ new_pose
        history.append(
            {
                "matches": int(len(m)),
                "lifted": int(ok.sum()),
                "inliers": int(inliers.sum()),
                "rotation_deg": rotation_angle_deg(np.eye(3), rel[:3, :3]),
            }
        )
        pose = new_pose
    return pose, {"rounds": history}


def train_and_score(
    name: str,
    scene: Scene,
    steps: int,
    seed: int,
    test_images: np.ndarray,
    test_cameras: dict[str, tuple[np.ndarray, np.ndarray]],
    test_ids: list[int],
    device: torch.device,
    lpips_dir: str | None,
    save_dir: Path | None,
    refine: str | None = None,
    settings: tuple[str, ...] = (),
) -> dict[str, Any]:
    """Train the fast preset (with ``settings``, ``--set`` style) on ``scene``, bake, render each
    test camera set and score it.

    With ``refine``: also score the first camera set after :func:`refine_test_pose` (label
    ``<label>_refined``; with ``refine="focal"`` also ``<label>_refined_focal``, each test view's
    focal length refined with its pose), a diagnostic separating registration error from
    reconstruction quality.
    """
    cfg = with_settings(preset_config("fast", steps=steps, seed=seed), list(settings))
    record: dict[str, Any] = {"near": scene.near, "far": scene.far, "config": cfg.to_dict()}
    with tempfile.TemporaryDirectory() as tmp:
        baked_dir = (save_dir / f"{name}_baked") if save_dir else Path(tmp) / "baked"
        if (baked_dir / MANIFEST).exists():  # training is deterministic: a saved bake is this run's
            print(f"[{name}] the bake in {baked_dir} (saved by an earlier run)", file=sys.stderr, flush=True)
            record["train_seconds"] = None
        else:
            print(
                f"[{name}] training {steps} steps, near/far {scene.near:.3f}/{scene.far:.3f}",
                file=sys.stderr,
                flush=True,
            )
            trainer = Trainer(scene, cfg, device)
            t0 = time.perf_counter()
            trainer.fit()
            record["train_seconds"] = time.perf_counter() - t0
            bake(trainer.model, baked_dir)
        baked = BakedScene.load(baked_dir, device)
        score_cameras(name, baked, test_cameras, test_images, test_ids, lpips_dir, save_dir, record, refine)
    return record


def score_cameras(
    name: str,
    baked: BakedScene,
    test_cameras: dict[str, tuple[np.ndarray, np.ndarray]],
    test_images: np.ndarray,
    test_ids: list[int],
    lpips_dir: str | None,
    save_dir: Path | None,
    record: dict[str, Any],
    refine: str | None = None,
) -> None:
    """Render and score every camera set of ``test_cameras`` into ``record[label]``."""
    cams = dict(test_cameras)
    if refine:
        label, (Ks, poses) = next(iter(test_cameras.items()))
        variants = {"pose": ["refined"], "focal": ["refined", "refined_focal"], "model": ["refined", "model"]}
        for suffix in variants[refine]:
            refined, refined_K, corrections = [], [], []
            for k in range(len(test_ids)):
                t0 = time.perf_counter()
                start, info = poses[k], {}
                if suffix == "model":
                    start, info = register_to_model(baked, Ks[k], poses[k], test_images[k])
                pose_k, K_k, polish = refine_test_pose(
                    baked, Ks[k], start, test_images[k], baked.near, focal=suffix == "refined_focal"
                )
                info = {**polish, **info}
                refined.append(pose_k)
                refined_K.append(K_k)
                corrections.append({"view": test_ids[k], **info, "seconds": time.perf_counter() - t0})
            cams[f"{label}_{suffix}"] = (np.stack(refined_K), np.stack(refined))
            record["refinement" if suffix == "refined" else f"refinement_{suffix}"] = corrections
    for label, (Ks, poses) in cams.items():
        views = []
        for k, view in enumerate(test_ids):
            pred = baked.render(Ks[k], poses[k]).rgb
            views.append({"view": view, **image_metrics(pred, test_images[k], lpips_dir)})
            if save_dir is not None:
                save_image(save_dir / f"{name}_{label}_test_{view:03d}.png", pred)
        record[label] = {"views": views, "mean": {m: float(np.mean([v[m] for v in views])) for m in METRICS}}
        print(f"[{name}] {label}: {record[label]['mean']}", file=sys.stderr, flush=True)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=Path("../shared/datasets/llff/fern"), help="LLFF scene folder")
    ap.add_argument("--steps", type=int, default=600, help="training steps of the fast preset (both runs)")
    ap.add_argument("--seed", type=int, default=0, help="training and SfM seed (both runs)")
    ap.add_argument("--lpips-dir", default=os.environ.get("CMC_LPIPS_DIR"), help="folder with lpips_alex.pth")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", type=Path, default=Path("bench/reports/current/poses_e2e.json"), help="JSON report")
    ap.add_argument("--save-dir", type=Path, help="also write the rendered test views and baked models here")
    ap.add_argument(
        "--exif-focal",
        action="store_true",
        help="PNG photos carry the dataset's focal length as a phone's EXIF tag (35 mm equivalent), "
        "as photos uploaded from a phone do; without it SfM has to find the focal length itself",
    )
    ap.add_argument(
        "--refine-test-poses",
        nargs="?",
        const="pose",
        choices=("pose", "focal", "model"),
        help="diagnostic: also score both runs after photometric refinement of the registered test poses "
        "('focal': and once more refining each test view's focal length with its pose; 'model': and once "
        "more after registering each test photo to the model's render by SIFT and P3P, register_to_model)",
    )
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a training setting (both runs)")
    ap.add_argument(
        "--max-sift-size", type=int, default=PoseOptions.max_sift_size, help="long side SIFT runs at, pixels"
    )
    args = ap.parse_args(argv)
    device = torch.device(args.device)
    if args.save_dir:
        args.save_dir.mkdir(parents=True, exist_ok=True)

    split = load_llff(args.data)
    num_views = len(split.train_ids) + len(split.test_ids) + len(split.val_ids)
    photos = training_photos(args.data, split.train_ids, num_views)
    exif_dir = Path(tempfile.mkdtemp(prefix="poses-e2e-exif-"))
    focal = float(split.train.cameras.K[0, 0, 0])
    if args.exif_focal:
        photos = with_exif_focal(photos, focal, exif_dir)

    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        est = estimate_poses(
            photos, Path(tmp) / "scene", seed=args.seed, keep_originals=False, max_sift_size=args.max_sift_size
        )
        pose_wall_s = time.perf_counter() - t0
        scene_b, size_check = estimated_scene(split, est)
        working_images = np.stack([load_image(p) for p in est.image_paths])
    scene_a = split.train

    align = alignment(scene_a.cameras, scene_b.cameras)
    scale, R, t = align["scale_est_to_gt"], np.array(align["R_est_to_gt"]), np.array(align["t_est_to_gt"])
    test = split.test
    test_pose_similarity = apply_similarity_to_poses(test.cameras.world_from_cam, *invert_similarity(scale, R, t))
    cams_b = {"similarity": (test.cameras.K, test_pose_similarity)}
    structure: dict[str, Any] | None = None
    points: dict[str, Any] | None = None
    if (args.data / "sparse" / "0" / "points3D.bin").exists():
        test_pose_structure, structure = register_through_structure(args.data, split, est)
        for k, view in enumerate(split.test_ids):  # how far apart the two registrations put each view
            rel = np.linalg.inv(test_pose_similarity[k]) @ test_pose_structure[k]
            structure["test_views"][k]["rotation_vs_similarity_deg"] = rotation_angle_deg(np.eye(3), rel[:3, :3])
            structure["test_views"][k]["centre_vs_similarity_fraction_of_baseline"] = float(
                np.linalg.norm(rel[:3, 3]) / mean_baseline(scene_b.cameras.centers)
            )
            print(f"view {view}: {structure['test_views'][k]}", file=sys.stderr)
        cams_b = {"structure": (test.cameras.K, test_pose_structure), **cams_b}
    else:
        K_points, test_pose_points, points = register_into_reconstruction(args.data, split, est, working_images)
        cams_b = {"points": (K_points, test_pose_points), **cams_b}
    primary = next(iter(cams_b))  # the registration the target is judged on (refined when asked)

    cams_a = {"dataset": (test.cameras.K, test.cameras.world_from_cam)}
    common = dict(
        steps=args.steps,
        seed=args.seed,
        test_images=test.images,
        test_ids=split.test_ids,
        device=device,
        lpips_dir=args.lpips_dir,
        save_dir=args.save_dir,
        refine=args.refine_test_poses,
        settings=tuple(args.set),
    )
    run_a = train_and_score("dataset_poses", scene_a, test_cameras=cams_a, **common)
    run_b = train_and_score("estimated_poses", scene_b, test_cameras=cams_b, **common)
    ma, mb = run_a["dataset"]["mean"], run_b[primary]["mean"]
    diff = {m: mb[m] - ma[m] for m in METRICS}
    diff_similarity = {m: run_b["similarity"]["mean"][m] - ma[m] for m in METRICS}
    report = {
        "task": f"end to end: {args.data.name} from estimated vs dataset poses, held-out views registered into the "
        "estimated frame through the two reconstructions' 3D points where the scene ships them, "
        "and by a similarity of the training cameras",
        "registration": primary,
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "data": str(args.data),
        "train_views": split.train_ids,
        "test_views": split.test_ids,
        "photos": [p.name for p in photos],
        "exif_focal": args.exif_focal,
        "steps": args.steps,
        "settings": args.set,
        "seed": args.seed,
        "pose_estimation": {
            "wall_seconds": pose_wall_s,
            "timings": est.timings,
            "stats": est.stats,
            "near_far_estimated": np.asarray(est.camera_file.near_far).tolist(),
            **size_check,
        },
        "bounds": {
            "dataset_scene_near_far": [scene_a.near, scene_a.far],
            "estimated_scene_near_far": [scene_b.near, scene_b.far],
            "estimated_scene_near_far_in_gt_units": [scene_b.near * scale, scene_b.far * scale],
        },
        "alignment": align,
        "structure_registration": structure,
        "points_registration": points,
        "test_poses_in_estimated_frame": {label: poses.tolist() for label, (_, poses) in cams_b.items()},
        "runs": {"dataset_poses": run_a, "estimated_poses": run_b},
        "difference_estimated_minus_dataset": diff,
        "difference_with_similarity_registration": diff_similarity,
        "difference_after_test_pose_refinement": {
            m: run_b[f"{primary}_refined"]["mean"][m] - run_a["dataset_refined"]["mean"][m] for m in METRICS
        }
        if args.refine_test_poses
        else None,
        "difference_after_registration_to_the_model": {
            m: run_b[f"{primary}_model"]["mean"][m] - run_a["dataset_model"]["mean"][m] for m in METRICS
        }
        if args.refine_test_poses == "model"
        else None,
        "difference_after_test_pose_and_focal_refinement": {
            m: run_b[f"{primary}_refined_focal"]["mean"][m] - run_a["dataset_refined_focal"]["mean"][m] for m in METRICS
        }
        if args.refine_test_poses == "focal"
        else None,
        "target_psnr_gap_db": 0.5,
        "target_met": bool(ma["psnr"] - mb["psnr"] <= 0.5),
        "device": torch.cuda.get_device_name(device)
        if device.type == "cuda"
        else f"cpu ({platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"{torch.get_num_threads()} torch threads)",
        "git_commit": git_commit(),
        "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d"),
        "versions": {"python": platform.python_version(), "torch": torch.__version__, "numpy": np.__version__},
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=1))
    print(
        f"PSNR dataset {ma['psnr']:.3f} dB, estimated {mb['psnr']:.3f} dB, difference {diff['psnr']:+.3f} dB "
        f"registered by {primary} (target: within 0.5 dB -> {'met' if report['target_met'] else 'NOT met'}); "
        f"with the camera similarity: {diff_similarity['psnr']:+.3f} dB"
    )
    return report


if __name__ == "__main__":
    main()
