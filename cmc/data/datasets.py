"""Scenes: posed images with depth bounds. Scene folders, LLFF, and a synthetic layered scene.

A *scene folder* holds the images and ``cameras.json`` (the transforms.json shape read by
:func:`cmc.geometry.cameras.load_camera_file`, with ``near``/``far``). Everything returned here uses the
conventions of :mod:`cmc.geometry.cameras`; images are float32 [H, W, 3] in [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from cmc.data.images import to_uint8
from cmc.errors import SceneError
from cmc.geometry.cameras import (
    CameraError,
    CameraFile,
    Cameras,
    cameras_from_llff,
    intrinsics,
    look_at,
    pixel_rays,
    save_camera_file,
)

CAMERAS_FILE = "cameras.json"


@dataclass
class Scene:
    """N posed views.

    Attributes:
        images: [N, H, W, 3] float32 in [0, 1].
        cameras: N cameras of size W x H.
        near_far: [N, 2] depth bounds (camera z, scene units) per view.
        names: N image names.
        depths: optional [N, H, W] ground-truth depth (synthetic scenes).
    """

    images: np.ndarray
    cameras: Cameras
    near_far: np.ndarray
    names: list[str] = field(default_factory=list)
    depths: np.ndarray | None = None

    def __post_init__(self) -> None:
        validate_scene(self)

    def __len__(self) -> int:
        return len(self.images)

    def subset(self, idx: list[int]) -> Scene:
        depths = None if self.depths is None else self.depths[idx]
        return Scene(self.images[idx], self.cameras[idx], self.near_far[idx], [self.names[i] for i in idx], depths)

    def with_gains(self, gains: list[float]) -> Scene:
        """The same views with view k's colours times ``gains[k]``, clipped to [0, 1] (photos of
        differing exposure)."""
        if len(gains) != len(self):
            raise SceneError(f"{len(gains)} gains for {len(self)} views")
        factor = np.asarray(gains, dtype=np.float32)[:, None, None, None]
        images = np.clip(self.images * factor, 0, 1).astype(np.float32)
        return Scene(images, self.cameras, self.near_far, self.names, self.depths)

    def with_near_scaled(self, factor: float) -> Scene:
        """The same views with every near bound times ``factor`` (< 1: looser bounds, as a stray
        point near a camera gives them)."""
        near_far = self.near_far * np.array([factor, 1.0])
        return Scene(self.images, self.cameras, near_far, self.names, self.depths)

    @property
    def near(self) -> float:
        return float(self.near_far[:, 0].min())

    @property
    def far(self) -> float:
        return float(self.near_far[:, 1].max())


def validate_scene(scene: Scene, min_views: int = 1) -> None:
    """Raise SceneError naming the first problem found."""
    imgs = scene.images
    if imgs.ndim != 4 or imgs.shape[-1] != 3:
        raise SceneError(f"images must be [N, H, W, 3], got {list(imgs.shape)}")
    n, h, w, _ = imgs.shape
    if n < min_views:
        raise SceneError(f"need at least {min_views} views, got {n}")
    if len(scene.cameras) != n:
        raise SceneError(f"{n} images but {len(scene.cameras)} cameras")
    if (scene.cameras.width, scene.cameras.height) != (w, h):
        raise SceneError(f"cameras are for {scene.cameras.width}x{scene.cameras.height} images, images are {w}x{h}")
    nf = np.asarray(scene.near_far, dtype=np.float64)
    if nf.shape != (n, 2):
        raise SceneError(f"near_far must be [N, 2], got {list(nf.shape)}")
    if not np.isfinite(nf).all() or (nf[:, 0] <= 0).any() or (nf[:, 0] >= nf[:, 1]).any():
        raise SceneError(f"need finite 0 < near < far for every view, got {nf.tolist()}")
    if not scene.names:
        scene.names = [f"view{i:03d}" for i in range(n)]


def load_image(path: Path) -> np.ndarray:
    """[H, W, 3] float32 in [0, 1]; raises SceneError for unreadable files."""
    try:
        with Image.open(path) as im:
            return np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0
    except FileNotFoundError:
        raise SceneError(f"image not found: {path}") from None
    except (UnidentifiedImageError, OSError) as e:
        raise SceneError(f"cannot read image {path}: {e}") from None


def save_image(path: Path, image: np.ndarray) -> None:
    """Write an [H, W, 3] or [H, W] float image in [0, 1] as 8-bit PNG/JPEG by extension."""
    Image.fromarray(to_uint8(image)).save(path)


def load_scene_folder(folder: str | Path) -> Scene:
    """Load a scene folder (images + ``cameras.json`` with near/far)."""
    folder = Path(folder)
    from cmc.geometry.cameras import load_camera_file

    try:
        cf = load_camera_file(folder / CAMERAS_FILE)
    except CameraError as e:
        raise SceneError(str(e)) from None
    if cf.near_far is None:
        raise SceneError(f"{folder / CAMERAS_FILE} gives no near/far depth bounds")
    images = []
    for name in cf.file_paths:
        p = (folder / name).resolve()
        if folder.resolve() not in p.parents:
            raise SceneError(f"image path {name!r} points outside the scene folder")
        images.append(load_image(p))
    sizes = {im.shape[:2] for im in images}
    if len(sizes) > 1:
        raise SceneError(f"images have different sizes: {sorted(sizes)}")
    h, w = images[0].shape[:2]
    cams = cf.cameras
    if (cams.width, cams.height) != (w, h):
        raise SceneError(f"cameras.json says {cams.width}x{cams.height} but the images are {w}x{h}")
    return Scene(np.stack(images), cams, cf.near_far, [Path(n).name for n in cf.file_paths])


def save_scene_folder(scene: Scene, folder: str | Path) -> Path:
    """Write ``scene`` as a scene folder (PNG images + cameras.json, OpenGL convention)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    names = [n if n.endswith(".png") else f"{n}.png" for n in scene.names]
    for name, img in zip(names, scene.images, strict=True):
        save_image(folder / name, img)
    save_camera_file(CameraFile(scene.cameras, names, scene.near_far), folder / CAMERAS_FILE)
    return folder


# --- LLFF -----------------------------------------------------------------------------------


@dataclass
class LLFFSplit:
    """The RegNeRF few-shot protocol: ``train`` (evenly chosen) and ``test`` (index % 8 == 0), and
    ``val``, the images that are neither (views that may choose settings; the test views may not;
    None when no image is left)."""

    train: Scene
    test: Scene
    train_ids: list[int]
    test_ids: list[int]
    val: Scene | None
    val_ids: list[int]


def regnerf_split(num_images: int, num_train: int = 3) -> tuple[list[int], list[int]]:
    """Indices (train, test): test = every 8th image, train = ``num_train`` evenly from the rest."""
    test = [i for i in range(num_images) if i % 8 == 0]
    rest = [i for i in range(num_images) if i % 8 != 0]
    pick = np.round(np.linspace(0, len(rest) - 1, num_train)).astype(int)
    return [rest[i] for i in pick], test


def load_llff(scene_dir: str | Path, images_subdir: str = "images_8", num_train: int = 3) -> LLFFSplit:
    """Load an LLFF scene (``poses_bounds.npy`` + ``images_8``) split by :func:`regnerf_split`.

    Every view gets the scene-wide bounds [0.9 * min near, max far] (LLFF's per-view bounds are
    sparse-point percentiles; the MPIs must cover the whole scene from every camera).
    """
    scene_dir = Path(scene_dir)
    pb_path = scene_dir / "poses_bounds.npy"
    if not pb_path.exists():
        raise SceneError(f"not an LLFF scene (no poses_bounds.npy): {scene_dir}")
    files = sorted(p for p in (scene_dir / images_subdir).iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    pb = np.load(pb_path)
    if len(files) != len(pb):
        raise SceneError(f"{len(files)} images in {images_subdir} but {len(pb)} poses")
    images = np.stack([load_image(p) for p in files])
    h, w = images.shape[1:3]
    cams, bounds = cameras_from_llff(pb, w, h)
    nf = np.tile([bounds[:, 0].min() * 0.9, bounds[:, 1].max()], (len(pb), 1))
    full = Scene(images, cams, nf, [p.name for p in files])
    train, test = regnerf_split(len(pb), num_train)
    val = [i for i in range(len(pb)) if i not in train and i not in test]
    return LLFFSplit(full.subset(train), full.subset(test), train, test, full.subset(val) if val else None, val)


# --- Synthetic layered scene ----------------------------------------------------------------


@dataclass(frozen=True)
class Layer:
    """A textured rectangle (world z is the viewing direction of the synthetic cameras).

    The surface is ``z = z0 + tilt[0] * x + tilt[1] * y`` (a fronto-parallel plane when ``tilt``
    is zero) over ``bounds`` = (x0, x1, y0, y1) in world x, y; ``seed`` picks the procedural
    texture.
    """

    z: float
    bounds: tuple[float, float, float, float]
    seed: int
    tilt: tuple[float, float] = (0.0, 0.0)


DEFAULT_LAYERS = (
    Layer(2.0, (-0.55, -0.05, -0.45, 0.15), 1),
    Layer(3.2, (0.0, 0.75, -0.3, 0.5), 2),
    Layer(6.0, (-1e3, 1e3, -1e3, 1e3), 3),
)


def _texture(seed: int, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Deterministic procedural colour [.., 3] in [0, 1] at world (x, y): sinusoids + checks."""
    rng = np.random.default_rng(seed)
    base = rng.uniform(0.2, 0.8, 3)
    freqs = rng.uniform(4, 14, (3, 2))
    phase = rng.uniform(0, 2 * np.pi, 3)
    col = base + 0.25 * np.stack([np.sin(freqs[c, 0] * x + freqs[c, 1] * y + phase[c]) for c in range(3)], axis=-1)
    check = ((np.floor(x * 5) + np.floor(y * 5)) % 2)[..., None]
    return np.clip(col * (0.75 + 0.25 * check), 0, 1)


def render_layers(layers: tuple[Layer, ...], cameras: Cameras, supersample: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Ray-trace the layers: images [N, H, W, 3] and depth (camera z) [N, H, W], exact geometry."""
    w, h, s = cameras.width, cameras.height, supersample
    v, u = np.meshgrid((np.arange(h * s) + 0.5) / s, (np.arange(w * s) + 0.5) / s, indexing="ij")
    uv = np.stack([u, v], -1)
    images, depths = [], []
    for K, pose in zip(cameras.K, cameras.world_from_cam, strict=True):
        d_cam = pixel_rays(K, uv)  # camera z = 1
        d = d_cam @ pose[:3, :3].T
        o = pose[:3, 3]
        best_t = np.full(d.shape[:2], np.inf)
        col = np.zeros(d.shape[:2] + (3,))
        for L in layers:
            tx, ty = L.tilt  # o + t d meets z = z0 + tx x + ty y at:
            t = (L.z + tx * o[0] + ty * o[1] - o[2]) / (d[..., 2] - tx * d[..., 0] - ty * d[..., 1])
            x, y = o[0] + t * d[..., 0], o[1] + t * d[..., 1]
            x0, x1, y0, y1 = L.bounds
            hit = (t > 0) & (t < best_t) & (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
            best_t = np.where(hit, t, best_t)
            col = np.where(hit[..., None], _texture(L.seed, x, y), col)
        images.append(col.reshape(h, s, w, s, 3).mean((1, 3)))
        depths.append(best_t.reshape(h, s, w, s).mean((1, 3)))  # t is camera z since d_cam.z = 1
    return np.stack(images).astype(np.float32), np.stack(depths).astype(np.float32)


def synthetic_cameras(
    num_views: int,
    width: int = 96,
    height: int = 72,
    baseline: float = 0.3,
    fov_deg: float = 50.0,
    jitter_seed: int | None = None,
) -> Cameras:
    """Forward-facing cameras on a horizontal arc of width ``baseline`` at z = 0, all looking
    roughly at the point (0, 0, 4) (so each is slightly rotated), with a small vertical zig-zag."""
    f = 0.5 * width / np.tan(np.radians(fov_deg) / 2)
    K = intrinsics(f, f, width / 2, height / 2)
    xs = np.linspace(-baseline / 2, baseline / 2, num_views)
    rng = np.random.default_rng(jitter_seed) if jitter_seed is not None else None
    poses = []
    for i, x in enumerate(xs):
        c = np.array([x, 0.04 * (-1) ** i, 0.0])
        if rng is not None:
            c = c + rng.normal(scale=0.02, size=3)
        poses.append(look_at(c, (0.0, 0.0, 4.0)))
    return Cameras(np.tile(K, (num_views, 1, 1)), np.stack(poses), width, height)


def synthetic_scene(
    num_views: int = 3,
    width: int = 96,
    height: int = 72,
    layers: tuple[Layer, ...] = DEFAULT_LAYERS,
    baseline: float = 0.3,
) -> Scene:
    """A forward-facing scene of textured layers with known poses and exact depth maps."""
    cams = synthetic_cameras(num_views, width, height, baseline)
    images, depths = render_layers(layers, cams)
    zs = [L.z for L in layers]
    nf = np.tile([0.8 * min(zs), 1.1 * max(zs)], (num_views, 1))
    return Scene(images, cams, nf, [f"view{i:03d}" for i in range(num_views)], depths)


# --- Wide-baseline synthetic set (the view-quality benchmark) ---------------------------------

# Scenes with occlusions and slanted surfaces, seen by three cameras much farther apart than
# LLFF's (see wide_baseline_split). World units; the cameras sit near z = 0 looking along +z.
WIDE_SCENES: dict[str, tuple[Layer, ...]] = {
    # Two overlapping cards in front of a wall: occlusion edges at two depths.
    "cards": (
        Layer(1.8, (-0.5, 0.0, -0.35, 0.2), 11),
        Layer(2.8, (-0.1, 0.7, -0.5, 0.35), 12),
        Layer(5.5, (-1e3, 1e3, -1e3, 1e3), 13),
    ),
    # Thin posts in front of a card and a wall: many narrow disocclusions (a fence, plant stems).
    "posts": (
        *(Layer(2.0, (x, x + 0.07, -1.0, 1.0), 21 + k) for k, x in enumerate((-0.75, -0.4, -0.05, 0.3, 0.65))),
        Layer(3.4, (-0.6, 0.5, -0.3, 0.4), 27),
        Layer(6.5, (-1e3, 1e3, -1e3, 1e3), 28),
    ),
    # Slanted surfaces: a wall receding to the right, a floor, a tilted card in front.
    "slanted": (
        Layer(2.3, (-0.3, 0.25, -0.3, 0.15), 31, (0.8, 0.0)),
        Layer(4.0, (-1e3, 1e3, 0.35, 1e3), 32, (0.0, -2.5)),
        Layer(4.5, (-1e3, 1e3, -1e3, 1e3), 33, (1.2, 0.0)),
    ),
}


@dataclass
class SyntheticSplit:
    """A synthetic scene's input views and test views with exact images and depth.

    ``test_kinds[k]`` says where test view k is: ``"halfway"`` (midpoint of two input cameras),
    ``"near"`` (beside one input camera) or ``"beyond"`` (outside the triangle of the inputs).
    """

    name: str
    train: Scene
    test: Scene
    test_kinds: list[str]


def wide_baseline_split(
    name: str, width: int = 252, height: int = 189, baseline: float = 0.6, fov_deg: float = 55.0
) -> SyntheticSplit:
    """Scene ``name`` of :data:`WIDE_SCENES` from three input cameras in a triangle.

    The inputs sit at the corners of a triangle ``baseline`` wide (left, right, top), all looking
    at (0, 0, 4). Test views: the three midpoints of input pairs ("halfway", where a user
    navigating between the photos is), each input camera moved by 5 % of the baseline towards
    the others ("near"), and each input camera moved by half the baseline away from the others
    ("beyond": extrapolation, as LLFF test views often are). Every camera looks at (0, 0, 4);
    images are rendered exactly with depth.
    """
    if name not in WIDE_SCENES:
        raise SceneError(f"unknown synthetic scene {name!r}; choose one of {', '.join(WIDE_SCENES)}")
    layers = WIDE_SCENES[name]
    b = baseline
    inputs = np.array([[-b / 2, 0.1 * b, 0.0], [b / 2, 0.15 * b, 0.0], [0.05 * b, -0.35 * b, 0.0]])
    halfway = [(inputs[i] + inputs[j]) / 2 for i, j in ((0, 1), (1, 2), (2, 0))]
    centroid = inputs.mean(0)
    near = [c + 0.05 * b * (centroid - c) / np.linalg.norm(centroid - c) for c in inputs]
    beyond = [c - 0.5 * b * (centroid - c) / np.linalg.norm(centroid - c) for c in inputs]
    f = 0.5 * width / np.tan(np.radians(fov_deg) / 2)
    K = intrinsics(f, f, width / 2, height / 2)

    def cams(centers: list[np.ndarray] | np.ndarray) -> Cameras:
        poses = np.stack([look_at(c, (0.0, 0.0, 4.0)) for c in centers])
        return Cameras(np.tile(K, (len(poses), 1, 1)), poses, width, height)

    train_cams, test_cams = cams(inputs), cams([*halfway, *near, *beyond])
    images, depths = render_layers(layers, train_cams)
    nf = [0.9 * float(depths.min()), 1.1 * float(depths.max())]  # as SfM bounds would give
    t_images, t_depths = render_layers(layers, test_cams)
    train = Scene(images, train_cams, np.tile(nf, (3, 1)), [f"{name}_in{i}" for i in range(3)], depths)
    test_names = [f"{name}_{kind}{i}" for kind in ("near", "beyond") for i in range(3)]
    test_names = [f"{name}_half{i}{(i + 1) % 3}" for i in range(3)] + test_names
    test = Scene(t_images, test_cams, np.tile(nf, (9, 1)), test_names, t_depths)
    return SyntheticSplit(name, train, test, ["halfway"] * 3 + ["near"] * 3 + ["beyond"] * 3)
