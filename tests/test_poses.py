"""Tests of cmc.poses: the COLMAP conversion (known answers against pycolmap's own projection),
triangulation and depth ranges, structure from motion on a rendered scene with known cameras (up to
a similarity), client poses, every bad input named in issue 3, cancellation, and the CLI.

The rendered scene: ``render_layers`` gives the exact geometry (depth of each pixel) of textured
layers seen from ``synthetic_cameras``; the test colours each layer with a dense random-shapes
texture (SIFT needs more than smooth stripes). The fern integration test reads the three
full-resolution JPEGs from the shared folder (``$CMC_SHARED_DIR`` or ``../shared``) and is skipped
without it.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from helpers import SHARED_DIR, rotation
from PIL import ExifTags, Image, ImageDraw, ImageFilter

from cmc.cli import main
from cmc.data.datasets import DEFAULT_LAYERS, SceneError, load_scene_folder, render_layers, synthetic_cameras
from cmc.eval.alignment import apply_similarity_to_poses, register_photo, similarity_from_cameras
from cmc.geometry.cameras import CameraError, CameraFile, Cameras, camera_file_to_dict, cameras_from_llff, look_at
from cmc.poses import (
    PoseEstimationCancelled,
    PoseEstimationError,
    cameras_from_colmap,
    depth_range,
    estimate_poses,
    intake,
    poses_from_client,
    triangulate_pair,
)
from cmc.poses.bounds import NEAR_FAR_MARGINS
from cmc.poses.intake import SIFT_FULL_SIZE, sift_first_octave, sift_options, sift_peak_threshold

pycolmap = pytest.importorskip("pycolmap")

FERN = SHARED_DIR / "datasets" / "llff" / "fern"
W, H = 320, 240
FOCAL_35MM = 37  # EXIF prior written into the rendered PNGs; synthetic_cameras' 50 degree FOV is ~37.1 mm


# --- helpers ---------------------------------------------------------------------------------


def relative_errors(truth: np.ndarray, est: np.ndarray) -> tuple[float, float]:
    """Largest relative-rotation and translation-direction errors (degrees) over all camera pairs,
    both invariant to a similarity transform of either set of camera-to-world poses [N, 4, 4]."""
    rot, tdir = 0.0, 0.0
    for i in range(len(truth)):
        for j in range(i + 1, len(truth)):
            a = np.linalg.inv(truth[i]) @ truth[j]
            b = np.linalg.inv(est[i]) @ est[j]
            R = a[:3, :3].T @ b[:3, :3]
            rot = max(rot, math.degrees(math.acos(np.clip((np.trace(R) - 1) / 2, -1, 1))))
            ta, tb = a[:3, 3] / np.linalg.norm(a[:3, 3]), b[:3, 3] / np.linalg.norm(b[:3, 3])
            tdir = max(tdir, math.degrees(math.acos(np.clip(ta @ tb, -1, 1))))
    return rot, tdir


def shapes_texture(seed: int, size: int = 512, count: int = 3000) -> np.ndarray:
    """[size, size, 3] float texture of many small random ellipses and triangles (SIFT-friendly)."""
    rng = np.random.default_rng(seed)
    im = Image.new("RGB", (size, size), tuple(int(c) for c in rng.integers(0, 256, 3)))
    draw = ImageDraw.Draw(im)
    for _ in range(count):
        x, y = rng.uniform(0, size, 2)
        r = rng.uniform(2, 9)
        colour = tuple(int(c) for c in rng.integers(0, 256, 3))
        if rng.random() < 0.5:
            draw.ellipse([x - r, y - r * rng.uniform(0.4, 1), x + r, y + r], fill=colour)
        else:
            draw.polygon(
                [(x + r * math.cos(a), y + r * math.sin(a)) for a in rng.uniform(0, 2 * math.pi, 3)], fill=colour
            )
    return np.asarray(im.filter(ImageFilter.GaussianBlur(1.0)), dtype=np.float64) / 255


def render_textured(cameras: Cameras, texture_seed: int = 0) -> np.ndarray:
    """[N, H, W, 3] uint8 views of DEFAULT_LAYERS: geometry from ``render_layers``, colour from a
    random-shapes texture per layer, sampled bilinearly at the world (x, y) of each pixel."""
    _, depths = render_layers(DEFAULT_LAYERS, cameras, supersample=1)
    zs = np.array([layer.z for layer in DEFAULT_LAYERS])
    textures = [shapes_texture(texture_seed * 10 + k) for k in range(len(zs))]
    v, u = np.meshgrid(np.arange(cameras.height) + 0.5, np.arange(cameras.width) + 0.5, indexing="ij")
    pix = np.stack([u, v, np.ones_like(u)], -1)
    views = []
    for K, pose, depth in zip(cameras.K, cameras.world_from_cam, depths, strict=True):
        X = (pix @ np.linalg.inv(K).T * depth[..., None]) @ pose[:3, :3].T + pose[:3, 3]
        layer = np.abs(X[..., 2:3] - zs).argmin(-1)
        colour = np.zeros(X.shape)
        for k, tex in enumerate(textures):
            m = layer == k
            texel = 0.004 * zs[k]  # world units per texel: about 1.4 pixels at any depth
            tu, tv = (X[..., 0][m] / texel) % 510, (X[..., 1][m] / texel) % 510
            i, j = np.floor(tv).astype(int), np.floor(tu).astype(int)
            fv, fu = (tv - i)[:, None], (tu - j)[:, None]
            colour[m] = (
                tex[i, j] * (1 - fu) * (1 - fv)
                + tex[i, j + 1] * fu * (1 - fv)
                + tex[i + 1, j] * (1 - fu) * fv
                + tex[i + 1, j + 1] * fu * fv
            )
        views.append(np.clip(colour * 255 + 0.5, 0, 255).astype(np.uint8))
    return np.stack(views)


def phone_exif(focal_35mm: int | None = FOCAL_35MM) -> Image.Exif:
    exif = Image.Exif()
    exif[ExifTags.Base.Make], exif[ExifTags.Base.Model] = "Acme", "Phone 1"
    if focal_35mm is not None:
        exif.get_ifd(ExifTags.IFD.Exif)[ExifTags.Base.FocalLengthIn35mmFilm] = focal_35mm
    return exif


def write_photos(folder: Path, views: np.ndarray, names: list[str] | None = None) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for k, view in enumerate(views):
        path = folder / (names[k] if names else f"IMG_{k:04d}.png")
        Image.fromarray(view).save(path, exif=phone_exif())
        paths.append(path)
    return paths


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> tuple[Cameras, list[Path], np.ndarray]:
    """Three rendered photos (PNG with EXIF focal), their true cameras, and a 4th unrelated view."""
    cams = synthetic_cameras(3, W, H, baseline=0.6, jitter_seed=1)
    views = render_textured(cams)
    folder = tmp_path_factory.mktemp("photos")
    paths = write_photos(folder, views)
    other = render_textured(synthetic_cameras(1, W, H), texture_seed=7)[0]
    return cams, paths, other


def client_dict(cams: Cameras, paths: list[Path], convention: str = "opengl") -> dict:
    return camera_file_to_dict(CameraFile(cams, [p.name for p in paths]), convention)  # type: ignore[arg-type]


# --- COLMAP conversion, triangulation, depth range ---------------------------------------------


@pytest.mark.parametrize(
    "model, params", [("SIMPLE_PINHOLE", [300.0, 160.0, 120.0]), ("PINHOLE", [310, 290, 150, 110])]
)
def test_cameras_from_colmap_matches_pycolmap_projection(model: str, params: list) -> None:
    rng = np.random.default_rng(0)
    rec = pycolmap.Reconstruction()
    camera = pycolmap.Camera.create_from_model_name(1, model, 300.0, W, H)
    camera.params = params
    rec.add_camera_with_trivial_rig(camera)
    names = []
    for k in range(3):
        cam_from_world = np.concatenate(
            [rotation(rng.normal(size=3), rng.uniform(0.1, 2.5)), rng.normal(size=(3, 1))], 1
        )
        image = pycolmap.Image(name=f"v{k}.png", camera_id=1, image_id=k + 1)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(cam_from_world))
        names.append(f"v{k}.png")
    cams = cameras_from_colmap(rec, names[::-1])
    assert (cams.width, cams.height) == (W, H)
    points = rng.normal(size=(50, 3)) * 3
    uv, depth = cams.project(points)
    for k, name in enumerate(names[::-1]):
        image = rec.find_image_with_name(name)
        np.testing.assert_allclose(cams.centers[k], np.ravel(image.projection_center()), atol=1e-9)
        for p in range(len(points)):
            expected = image.project_point(points[p])
            if depth[k, p] > 1e-3:
                np.testing.assert_allclose(uv[k, p], np.ravel(expected), rtol=1e-9, atol=1e-6)
            else:
                assert expected is None  # behind the camera for both


def test_cameras_from_colmap_refuses_distortion_and_unregistered() -> None:
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera.create_from_model_name(1, "SIMPLE_RADIAL", 300.0, W, H))
    rec.add_image_with_trivial_frame(pycolmap.Image(name="a.png", camera_id=1, image_id=1), pycolmap.Rigid3d())
    with pytest.raises(CameraError, match="distortion"):
        cameras_from_colmap(rec, ["a.png"])
    with pytest.raises(PoseEstimationError, match="not registered"):
        cameras_from_colmap(rec, ["b.png"])


def test_triangulate_pair_recovers_points() -> None:
    rng = np.random.default_rng(1)
    cams = synthetic_cameras(2, W, H, baseline=0.5)
    X = rng.uniform([-1, -1, 2], [1, 1, 6], size=(40, 3))
    uv, depth = cams.project(X)
    points, depths, err = triangulate_pair(cams, 0, 1, uv[0], uv[1])
    np.testing.assert_allclose(points, X, atol=1e-8)
    np.testing.assert_allclose(depths, depth.T, atol=1e-8)
    assert err.max() < 1e-6
    _, _, err = triangulate_pair(cams, 0, 1, uv[0], uv[1] + [0.0, 5.0])  # off the epipolar lines
    assert err.min() > 1.0


def test_depth_range() -> None:
    z = np.concatenate([np.linspace(2.0, 6.0, 1000), [0.01, 500.0, -3.0, np.nan]])  # outliers, behind, NaN
    near, far = depth_range(z)
    m_near, m_far = NEAR_FAR_MARGINS
    assert m_near * 1.9 < near < m_near * 2.1 and m_far * 5.9 < far < m_far * 6.1
    assert m_near <= 0.25 and m_far >= 4  # room's nearest surfaces lie 2.5x nearer than its SfM points
    with pytest.raises(PoseEstimationError, match="only 3 3D points are seen from IMG_1"):
        depth_range(np.array([1.0, 2.0, 3.0]), "IMG_1")


# --- Structure from motion on the rendered scene ---------------------------------------------


def test_sfm_recovers_known_cameras(scene, tmp_path: Path) -> None:
    cams, paths, _ = scene
    stages: list[str] = []
    result = estimate_poses(paths, tmp_path / "scene", on_stage=stages.append)
    assert stages == ["intake", "features", "matching", "mapping", "near_far", "write"]
    est = result.camera_file.cameras
    assert (est.width, est.height) == (W, H)
    rot, tdir = relative_errors(cams.world_from_cam, est.world_from_cam)
    assert rot < 1.0 and tdir < 2.0, (rot, tdir)
    assert est.K[0, 0, 0] == pytest.approx(cams.K[0, 0, 0], rel=0.01)  # the EXIF prior, kept
    # depths: scale the similarity away with the camera baseline, then compare with the layers' z
    scale = np.linalg.norm(np.diff(cams.centers[[0, 2]], axis=0)) / np.linalg.norm(np.diff(est.centers[[0, 2]], axis=0))
    nf = result.camera_file.near_far * scale / NEAR_FAR_MARGINS  # the points' own depth range
    assert (nf[:, 0] > 1.1).all() and (nf[:, 0] < 2.2).all(), nf  # the nearest layer: z = 2
    assert (nf[:, 1] > 5.5).all() and (nf[:, 1] < 8.2).all(), nf  # the farthest: z = 6
    assert {"intake", "features", "matching", "mapping", "near_far", "write", "total"} <= set(result.timings)
    assert result.stats["registered"] == 3 and result.stats["focal_prior"] == ["35mm-equivalent"] * 3
    # the sparse points: each lands where its photos observed it (working resolution), and mapped
    # into the true frame it lies on one of the layers (world z = the layer's depth)
    sparse = result.sparse
    assert sparse is not None and len(sparse.xyz) == result.stats["points3D"] > 100
    uv, _ = est.project(sparse.xyz)  # [N, P, 2]
    error = np.linalg.norm(uv.transpose(1, 0, 2) - sparse.pixels, axis=-1)[~np.isnan(sparse.pixels[..., 0])]
    assert np.median(error) < 0.3 and np.percentile(error, 95) < 1.5, np.percentile(error, [50, 95])
    assert all(sparse.seen_by(k).sum() > 50 for k in range(3))
    s, R, t = similarity_from_cameras(est.world_from_cam, cams.world_from_cam)
    z = (s * sparse.xyz @ R.T + t)[:, 2]
    layer_z = np.array([layer.z for layer in DEFAULT_LAYERS])
    # (1.5 %: these 320-pixel photos keep weaker, less precise features; cmc.poses.intake.sift_peak_threshold)
    assert np.median(np.abs(z[:, None] - layer_z).min(1) / z) < 0.015
    # the folder is a trainable scene: images at the working size + cameras.json with near/far
    loaded = load_scene_folder(result.scene_dir)
    assert loaded.images.shape == (3, H, W, 3)
    np.testing.assert_allclose(loaded.cameras.world_from_cam, est.world_from_cam, atol=1e-9)
    assert sorted(p.name for p in (result.scene_dir / "originals").iterdir()) == [p.name for p in paths]
    assert json.loads(result.cameras_path.read_text())["convention"] == "opengl"
    # the frame is upright: the mean camera looks down world -z, the photos' up is world +y
    # (the synthetic cameras' own frame is OpenCV's: their up is -y, so SfM's first photo is too)
    R = est.world_from_cam[:, :3, :3]
    assert np.allclose(-R[:, :, 1].mean(0), [0, 1, 0], atol=0.02), R[:, :, 1]
    assert np.allclose(R[:, :, 2].mean(0), [0, 0, -1], atol=0.02), R[:, :, 2]
    assert np.allclose(-cams.world_from_cam[:, :3, 1].mean(0), [0, -1, 0], atol=0.02)


def test_a_further_photo_registers_into_the_reconstruction(scene, tmp_path: Path) -> None:
    """register_photo (the estimated-pose benchmark's registration of held-out photos): a fourth
    photo from a known camera between and in front of the three lands at that camera once the
    reconstruction's frame is mapped onto the true one; each training photo gives back its own
    SfM pose; a photo of another scene and a photo of the wrong size are refused."""
    cams, paths, other = scene
    result = estimate_poses(paths, tmp_path / "scene", keep_originals=False)
    est = result.camera_file.cameras
    images = np.stack([np.asarray(Image.open(p).convert("RGB"), np.float32) / 255 for p in result.image_paths])
    fourth = Cameras(cams.K[:1], look_at(np.array([0.12, -0.05, 0.3]), np.array([0.1, 0.0, 4.0]))[None], W, H)
    photo = render_textured(fourth)[0].astype(np.float32) / 255
    pose, info = register_photo(photo, images, result.sparse, est.K[0])
    assert info["inliers"] > 50 and info["points"] <= info["matches"], info
    s, R, t = similarity_from_cameras(est.world_from_cam, cams.world_from_cam)
    mapped = apply_similarity_to_poses(pose[None], s, R, t)[0]
    rot, _ = relative_errors(np.stack([fourth.world_from_cam[0], np.eye(4)]), np.stack([mapped, np.eye(4)]))
    assert rot < 0.1, rot
    assert np.linalg.norm(mapped[:3, 3] - fourth.world_from_cam[0, :3, 3]) < 0.01 * 0.6  # 1 % of the baseline
    baseline = np.linalg.norm(est.centers[0] - est.centers[2])
    for k in range(3):
        own, _ = register_photo(images[k], images, result.sparse, est.K[k])
        rot, _ = relative_errors(np.stack([own, np.eye(4)]), np.stack([est.world_from_cam[k], np.eye(4)]))
        assert rot < 0.05 and np.linalg.norm(own[:3, 3] - est.centers[k]) < 0.002 * baseline, k
    with pytest.raises(PoseEstimationError):
        register_photo(other.astype(np.float32) / 255, images, result.sparse, est.K[0])
    with pytest.raises(ValueError, match="the size of images"):
        register_photo(photo[:-1], images, result.sparse, est.K[0])


def test_sift_threshold_follows_the_photo_size() -> None:
    """COLMAP's contrast threshold at SIFT_FULL_SIZE and above; lower in proportion on smaller
    photos (a 504-pixel photo of a plain room keeps about 500 features at the default)."""
    assert sift_peak_threshold(SIFT_FULL_SIZE, 0.006) == sift_peak_threshold(4032, 0.006) == 0.006
    assert sift_peak_threshold(504, 0.006) == pytest.approx(0.006 * 504 / SIFT_FULL_SIZE)


def test_sift_doubles_only_photos_below_full_size() -> None:
    """The first octave: COLMAP's -1 (the photo doubled) below SIFT_FULL_SIZE, the photo's own
    scale (0) at and above it, as pycolmap receives it."""
    assert sift_first_octave(504, -1) == sift_first_octave(SIFT_FULL_SIZE - 1, -1) == -1
    assert sift_first_octave(SIFT_FULL_SIZE, -1) == sift_first_octave(4032, -1) == 0
    assert sift_options(pycolmap, SIFT_FULL_SIZE, SIFT_FULL_SIZE).sift.first_octave == 0
    small = sift_options(pycolmap, SIFT_FULL_SIZE, 504)
    assert small.sift.first_octave == pycolmap.FeatureExtractionOptions().sift.first_octave == -1


def test_sfm_at_the_photos_own_scale_recovers_known_cameras(scene, tmp_path: Path, monkeypatch) -> None:
    """SfM with SIFT's first octave at the photo's own scale (what photos of SIFT_FULL_SIZE and
    more get; here the 320-pixel photos, with the full size lowered to theirs) registers the
    three photos about as well as with the doubled octave, from fewer points."""
    cams, paths, _ = scene
    doubled = estimate_poses(paths, tmp_path / "doubled", keep_originals=False)
    monkeypatch.setattr(intake, "SIFT_FULL_SIZE", W)
    own = estimate_poses(paths, tmp_path / "own", keep_originals=False)
    assert own.stats["points3D"] < 0.8 * doubled.stats["points3D"], (own.stats, doubled.stats)
    rot, tdir = relative_errors(cams.world_from_cam, own.camera_file.cameras.world_from_cam)
    assert rot < 1.0 and tdir < 2.0, (rot, tdir)


def test_sfm_is_deterministic_and_scales_to_the_working_size(scene, tmp_path: Path) -> None:
    cams, paths, _ = scene
    a = estimate_poses(paths, tmp_path / "a", long_side=160, keep_originals=False)
    b = estimate_poses(paths, tmp_path / "b", long_side=160, keep_originals=False, convention="opencv")
    assert (a.camera_file.cameras.width, a.camera_file.cameras.height) == (160, 120)
    assert Image.open(a.image_paths[0]).size == (160, 120)
    np.testing.assert_allclose(a.camera_file.cameras.K[:, :2], cams.scaled(160, 120).K[:, :2], rtol=0.01)
    np.testing.assert_allclose(a.camera_file.cameras.world_from_cam, b.camera_file.cameras.world_from_cam, atol=1e-6)
    np.testing.assert_allclose(a.camera_file.near_far, b.camera_file.near_far, rtol=1e-6)
    assert not (a.scene_dir / "originals").exists()


def test_sfm_without_exif_refines_the_focal(scene, tmp_path: Path) -> None:
    cams, paths, _ = scene
    bare = []
    for p in paths:
        bare.append(tmp_path / p.name)
        Image.open(p).save(bare[-1])  # no EXIF: COLMAP starts from 1.2 * long side and refines
    result = estimate_poses(bare, tmp_path / "scene")
    assert result.stats["focal_prior"] == [None] * 3
    rot, _ = relative_errors(cams.world_from_cam, result.camera_file.cameras.world_from_cam)
    assert rot < 3.0


# --- Bad inputs ------------------------------------------------------------------------------


def test_blank_photo_is_named(scene, tmp_path: Path) -> None:
    _, paths, _ = scene
    blank = tmp_path / "blank.png"
    Image.new("RGB", (W, H), (128, 128, 128)).save(blank, exif=phone_exif())
    with pytest.raises(
        PoseEstimationError, match=r"could not register 1 of 3 photos \(blank.png: only 0 image features"
    ):
        estimate_poses([paths[0], blank, paths[1]], tmp_path / "scene")
    assert not (tmp_path / "scene" / "cameras.json").exists()


def test_identical_photos_are_refused(scene, tmp_path: Path) -> None:
    _, paths, _ = scene
    copy = tmp_path / "copy.png"
    copy.write_bytes(paths[0].read_bytes())
    with pytest.raises(PoseEstimationError, match="IMG_0000.png and copy.png are identical"):
        estimate_poses([paths[0], copy, paths[1]], tmp_path / "scene")
    with pytest.raises(SceneError, match="more than once"):
        estimate_poses([paths[0], paths[0]], tmp_path / "scene")


def test_photos_from_the_same_spot_are_diagnosed(scene, tmp_path: Path) -> None:
    cams, paths, _ = scene
    view = np.asarray(Image.open(paths[0]), dtype=np.int16)
    noisy = np.clip(view + np.random.default_rng(0).integers(-2, 3, view.shape), 0, 255).astype(np.uint8)
    again = write_photos(tmp_path / "again", noisy[None], ["again.png"])[0]
    with pytest.raises(PoseEstimationError, match="could not register") as e:
        estimate_poses([paths[0], again], tmp_path / "scene")
    assert "same spot" in str(e.value) and "send camera poses" in str(e.value)


def test_unrelated_photo_is_named(scene, tmp_path: Path) -> None:
    _, paths, other = scene
    unrelated = write_photos(tmp_path / "other", other[None], ["holiday.png"])[0]
    with pytest.raises(PoseEstimationError, match=r"could not register 1 of 3 photos \(holiday.png: .*too few") as e:
        estimate_poses([paths[0], paths[1], unrelated], tmp_path / "scene")
    assert "registered: IMG_0000.png, IMG_0001.png" in str(e.value)


def test_truncated_jpeg_and_non_image_are_named(scene, tmp_path: Path) -> None:
    _, paths, _ = scene
    jpeg = tmp_path / "IMG_9.jpg"
    Image.open(paths[2]).save(jpeg, quality=90)
    jpeg.write_bytes(jpeg.read_bytes()[:-2000])
    with pytest.raises(SceneError, match="IMG_9.jpg .*truncated"):
        estimate_poses([paths[0], paths[1], jpeg], tmp_path / "scene")
    text = tmp_path / "notes.jpg"
    text.write_text("not a photo")
    with pytest.raises(SceneError, match="notes.jpg is not a supported image"):
        estimate_poses([paths[0], text], tmp_path / "scene")


def test_mixed_orientation_and_too_few_photos(scene, tmp_path: Path) -> None:
    _, paths, _ = scene
    portrait = tmp_path / "portrait.png"
    Image.open(paths[1]).transpose(Image.Transpose.ROTATE_90).save(portrait)
    with pytest.raises(SceneError, match="one size and orientation"):
        estimate_poses([paths[0], portrait], tmp_path / "scene")
    with pytest.raises(PoseEstimationError, match="at least 2 photos"):
        estimate_poses(paths[:1], tmp_path / "scene")


def test_cancellation(scene, tmp_path: Path) -> None:
    _, paths, _ = scene
    with pytest.raises(PoseEstimationCancelled):
        estimate_poses(paths, tmp_path / "a", should_stop=lambda: True)
    # True once COLMAP's database exists, i.e. while feature extraction runs: the polling thread
    # cancels the running pycolmap stage
    work = tmp_path / "work"
    with pytest.raises(PoseEstimationCancelled):
        estimate_poses(paths, tmp_path / "b", work_dir=work, should_stop=lambda: (work / "database.db").exists())
    assert not (tmp_path / "b" / "cameras.json").exists()
    with pytest.raises(PoseEstimationCancelled):  # client poses without near/far run pycolmap too
        poses_from_client(paths, client_dict(*scene[:2]), tmp_path / "c", should_stop=lambda: True)


# --- Client poses ----------------------------------------------------------------------------


def test_client_poses_triangulate_near_far_and_round_trip(scene, tmp_path: Path) -> None:
    cams, paths, _ = scene
    stages: list[str] = []
    cameras = client_dict(cams, paths)
    result = poses_from_client(paths, cameras, tmp_path / "scene", long_side=160, on_stage=stages.append)
    assert stages == ["intake", "features", "matching", "triangulation", "write"]
    assert set(result.timings) == set(stages) | {"total"}
    out = result.camera_file
    np.testing.assert_allclose(out.cameras.world_from_cam, cams.world_from_cam, atol=1e-12)
    np.testing.assert_allclose(out.cameras.K, cams.scaled(160, 120).K, atol=1e-9)
    points_range = out.near_far / NEAR_FAR_MARGINS  # the layers lie at z = 2, 3.2 and 6
    assert (points_range[:, 0] > 1.1).all() and (points_range[:, 0] < 2.2).all(), out.near_far
    assert (points_range[:, 1] > 5.5).all() and (points_range[:, 1] < 8.2).all(), out.near_far
    assert result.stats["consistent_matches"] > 0.9 * result.stats["matches"]
    assert "triangulation" in result.timings
    # what we return can be sent back: same photos + our cameras.json -> same cameras, near/far kept
    again = poses_from_client(paths, result.cameras_path, tmp_path / "again", long_side=160)
    np.testing.assert_allclose(again.camera_file.cameras.K, out.cameras.K, atol=1e-9)
    np.testing.assert_allclose(again.camera_file.near_far, out.near_far, rtol=1e-12)
    assert "features" not in again.timings  # near/far given: no feature matching
    assert json.loads(again.cameras_path.read_text())["convention"] == "opengl"


def test_client_poses_in_opencv_convention_and_other_resolution(scene, tmp_path: Path) -> None:
    cams, paths, _ = scene
    data = client_dict(cams.scaled(640, 480), paths, "opencv")  # intrinsics for a larger capture size
    for fr, nf in zip(data["frames"], [(1.5, 7.0)] * 3, strict=True):
        fr["near"], fr["far"] = nf
        fr["file_path"] = "images/" + Path(fr["file_path"]).stem + ".jpg"  # matched by name without extension
    result = poses_from_client(paths[::-1], data, tmp_path / "scene")
    np.testing.assert_allclose(result.camera_file.cameras.world_from_cam, cams.world_from_cam[::-1], atol=1e-12)
    np.testing.assert_allclose(result.camera_file.cameras.K, cams.K[::-1], atol=1e-9)
    assert json.loads(result.cameras_path.read_text())["convention"] == "opencv"


def test_client_poses_in_the_wrong_convention_are_detected(scene, tmp_path: Path) -> None:
    cams, paths, _ = scene
    data = client_dict(cams, paths, "opengl")
    data["convention"] = "opencv"  # ARKit poses labelled as OpenCV: cameras look backwards
    with pytest.raises(CameraError, match="do not fit the photos.*convention"):
        poses_from_client(paths, data, tmp_path / "scene")


def test_client_poses_with_phone_noise(scene, tmp_path: Path) -> None:
    cams, paths, _ = scene
    rng = np.random.default_rng(3)
    noisy = cams.world_from_cam.copy()
    for pose in noisy:  # ARKit-like drift: 0.3 degree rotations, 1% of the baseline in position
        pose[:3, :3] = pose[:3, :3] @ rotation(rng.normal(size=3), math.radians(0.3))
        pose[:3, 3] += rng.normal(scale=0.006, size=3)
    noisy_cams = Cameras(cams.K, noisy, W, H)
    result = poses_from_client(paths, client_dict(noisy_cams, paths), tmp_path / "noisy")
    nf = result.camera_file.near_far / NEAR_FAR_MARGINS  # the matches' own depth range: layers at z = 2 .. 6
    assert (nf[:, 0] > 1.1).all() and (nf[:, 0] < 2.2).all() and (nf[:, 1] > 5.5).all() and (nf[:, 1] < 8.2).all()


def _edit(data: dict, how: str) -> dict:
    data = json.loads(json.dumps(data))
    fr = data["frames"]
    if how == "rotation":
        fr[1]["transform_matrix"][0][0] = 2.0
    elif how == "focal":
        fr[0]["fl_x"] = -10.0
    elif how == "names":
        fr[2]["file_path"] = "IMG_9999.png"
    elif how == "count":
        del fr[2]
    elif how == "size":
        for f in fr:
            f["cx"], f["cy"] = 120.0, 160.0
        data["w"], data["h"] = 240, 320
    elif how == "principal":
        fr[0]["cx"] = 400.0
    elif how == "matrix":
        fr[0]["transform_matrix"] = [[1, 0, 0], [0, 1, 0]]
    elif how == "convention":
        data["convention"] = "arkit"
    elif how == "duplicate":
        fr[2]["file_path"] = fr[0]["file_path"]
    return data


@pytest.mark.parametrize(
    "how, error, message",
    [
        ("rotation", CameraError, "not a proper rotation"),
        ("focal", CameraError, "focal lengths .* must be"),
        ("names", CameraError, "no frame in the cameras file is for photo IMG_0002.png"),
        ("count", CameraError, "2 frames for 3 photos"),
        ("size", CameraError, r"for 240x320 images but the photos are 320x240 \(rotated"),
        ("principal", CameraError, "principal point"),
        ("matrix", CameraError, "4x4"),
        ("convention", CameraError, "unknown pose convention"),
        ("duplicate", CameraError, "2 frames in the cameras file name photo IMG_0000.png"),
    ],
)
def test_bad_client_cameras_are_clear_errors(scene, tmp_path: Path, how: str, error: type, message: str) -> None:
    cams, paths, _ = scene
    data = client_dict(cams, paths)
    for fr in data["frames"]:
        fr["near"], fr["far"] = 1.0, 8.0  # keep these tests free of feature matching
    with pytest.raises(error, match=message):
        poses_from_client(paths, _edit(data, how), tmp_path / "scene")


def test_bad_client_file(scene, tmp_path: Path) -> None:
    _, paths, _ = scene
    bad = tmp_path / "cams.json"
    bad.write_text("{not json")
    with pytest.raises(CameraError, match="not valid JSON"):
        poses_from_client(paths, bad, tmp_path / "scene")
    with pytest.raises(CameraError, match="not found"):
        poses_from_client(paths, tmp_path / "missing.json", tmp_path / "scene")


# --- CLI -------------------------------------------------------------------------------------


def test_cli_poses(scene, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    cams, paths, _ = scene
    out = tmp_path / "scene" / "cameras.json"
    assert main(["poses", *map(str, paths), "--out", str(out), "--long-side", "160"]) == 0
    printed = capsys.readouterr().out
    assert "features" in printed and "mapping" in printed and "cmc train" in printed
    assert load_scene_folder(out.parent).images.shape == (3, 120, 160, 3)
    client = tmp_path / "client.json"
    client.write_text(json.dumps(client_dict(cams, paths)))
    assert main(["poses", *map(str, paths), "--cameras", str(client), "--out", str(tmp_path / "c")]) == 0
    assert (tmp_path / "c" / "cameras.json").exists()
    blank = tmp_path / "blank.png"
    Image.new("RGB", (W, H)).save(blank)
    assert main(["poses", str(paths[0]), str(blank), "--out", str(tmp_path / "bad")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("cmc poses: error: could not register") and "\n" not in err


# --- Fern (shared data) ----------------------------------------------------------------------


@pytest.mark.skipif(not (FERN / "images").is_dir(), reason=f"shared dataset absent: {FERN / 'images'}")
def test_fern_full_resolution_jpegs(tmp_path: Path) -> None:
    """Issue 3's benchmark: views 1, 10, 19 against the dataset's own poses (up to similarity)."""
    photos = [FERN / "images" / f"IMG_{n}.JPG" for n in (4027, 4036, 4045)]
    pb = np.load(FERN / "poses_bounds.npy")[[1, 10, 19]]
    truth, bounds = cameras_from_llff(pb, 504, 378)
    result = estimate_poses(photos, tmp_path / "fern", keep_originals=False)
    assert result.stats["registered"] == 3
    rot, tdir = relative_errors(truth.world_from_cam, result.camera_file.cameras.world_from_cam)
    assert rot <= 0.5 and tdir <= 1.0, (rot, tdir)
    assert result.camera_file.cameras.K[0, 0, 0] == pytest.approx(truth.K[0, 0, 0], rel=0.01)
    # client path with the dataset's poses: triangulated near/far in the dataset's units
    data = camera_file_to_dict(CameraFile(truth, [p.name for p in photos]))
    client = poses_from_client(photos, data, tmp_path / "client", max_sift_size=800, keep_originals=False)
    # (the points' own depth range against LLFF's, both from COLMAP points' depth percentiles)
    np.testing.assert_allclose(client.camera_file.near_far / NEAR_FAR_MARGINS, bounds, rtol=0.15)
