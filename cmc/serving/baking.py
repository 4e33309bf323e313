"""Baked MPIs: explicit RGBA planes on disk, and a renderer that needs only those files.

On-disk format ``cmc-mpi`` version 2 (a folder; every file is browser-loadable):

* ``mpi.json``::

    {"format": "cmc-mpi", "version": 2,
     "convention": "opencv",          # camera axes x right, y down, z forward; see cmc.geometry.cameras
     "width": W, "height": H,         # size of the input images (pixels)
     "near": n, "far": f,             # plane range, scene units
     "blend": {"weights": "inverse_square_distance", "eps_baseline_fraction": 0.1,
               "baseline": b},        # see cmc.geometry.planes.blend_weights
     "colour_interpolation": "bicubic",  # or "bilinear" (the default where absent): how a
                                      # render samples colour between texels (cmc.serving.texture_kernel.render)
     "mpis": [{"K": 3x3,              # reference intrinsics, pixels, corner-origin
               "world_from_cam": 4x4, # reference camera-to-world
               "depths": [D floats],  # plane depths (reference camera z), nearest first
               "margin": [mx, my],    # planes cover the image's width enlarged mx times and its
                                      # height my times about its centre (version 1: one number)
               "tile": [h, w],        # texels per plane
               "grid": [rows, cols],  # tiles in the atlas, row-major, plane k at (k // cols, k % cols)
               "atlas": "mpi_00.png"}, ...]}

* ``mpi_XX.png``: 8-bit RGBA atlas of the D planes, straight (not premultiplied) alpha, alpha
  of :data:`ALPHA_FLOOR` (2) or less stored as 0 (:func:`quantize_planes`). Texel
  (r, c) of a tile covers reference pixel coordinates
  ``x = ((c + 0.5) / w * 2 - 1) * mx`` -> ``u = (x + 1) / 2 * W`` (the same for v with r, h, my,
  H), i.e. the tile spans the image's extent enlarged ``mx`` and ``my`` times about the image
  centre. Version 1 (one margin m for both axes) is read as ``[m, m]``.

Rendering composites each MPI front to back and blends them as
:func:`cmc.mpi.rendering.render_image` does: on the CPU with the compiled kernel of
:mod:`cmc.serving.texture_kernel` straight from the 8-bit textures, elsewhere with that function over
:class:`cmc.mpi.fields.TextureField` fields.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from PIL import Image

from cmc.data.images import to_uint8
from cmc.geometry.cameras import Cameras, pixel_rays
from cmc.geometry.planes import blend_weights, mean_baseline, texel_grid
from cmc.method.model import CMCModel
from cmc.mpi.fields import MPIField, TextureField
from cmc.mpi.plane_sampling import INTERPOLATIONS
from cmc.mpi.rendering import MPIFrame, render_image, select_mpis

if TYPE_CHECKING:
    from cmc.serving.texture_kernel import MPIGeometry, PackedTextures
from cmc.errors import BakedFormatError

# Baked alpha at or below this 8-bit count (under 1 % opacity) is stored as 0. Training leaves
# such faint alpha on a fifth of fern's texels (where the alpha entropy prior does not reach:
# behind surfaces, outside every view); it barely shows (colour PSNR 52-57 dB against keeping
# it, at fern's test views) but every such texel makes the renderer take a sample: without it a
# fern render takes 22 % less time (bench/reports/history/RESULTS-until-2026-11-27.md, serving cost).
ALPHA_FLOOR = 2
# A preview bake's texel resolution against the final bake's (``bake(scale=...)``): a quarter of
# the texels bake in about a quarter of the time (fern: 1.9 s instead of 7.3 s) at 0.2 dB less
# (bench/preview_quality.md).
PREVIEW_TEXEL_SCALE = 0.5

FORMAT = "cmc-mpi"
VERSION = 2
READABLE_VERSIONS = (1, 2)
MANIFEST = "mpi.json"


def entry_margin(entry: dict) -> tuple[float, float]:
    """(x, y) margin of a manifest's MPI entry: version 2 stores both, version 1 one for both."""
    m = entry["margin"]
    return (float(m), float(m)) if isinstance(m, int | float) else (float(m[0]), float(m[1]))


@torch.no_grad()
def bake_textures(field: MPIField, frame: MPIFrame, tile: tuple[int, int] | None = None) -> torch.Tensor:
    """Evaluate a field on a texel grid: [D, 4, h, w] straight RGBA in [0, 1].

    Each texel is seen along the reference camera's ray through it (view-dependent fields are
    baked as the reference camera sees them). ``tile`` defaults to the plane extent.
    """
    h, w = tile or frame.extent
    g = texel_grid(h, w, frame.K.device)
    dirs = pixel_rays(frame.K, frame.pixels_from_grid(g.reshape(-1, 2)))
    return field.on_texel_grid(g, frame.plane_z, dirs / dirs.norm(dim=-1, keepdim=True))


def _atlas_grid(num_planes: int) -> tuple[int, int]:
    cols = math.ceil(math.sqrt(num_planes))
    return math.ceil(num_planes / cols), cols


def merge_planes(rgba: torch.Tensor, depths: torch.Tensor, group: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite each run of ``group`` adjacent planes into one (fewer planes, faster renders).

    Exact at the reference view; elsewhere the merged content moves with one depth, the
    disparity mean of its group. Shape: rgba [D, 4, h, w] straight alpha, depths [D] ->
    ([ceil(D / group), 4, h, w], [ceil(D / group)]).
    """
    if group <= 1:
        return rgba, depths
    planes, new_depths = [], []
    for s in range(0, len(depths), group):
        color, alpha = torch.zeros_like(rgba[0, :3]), torch.zeros_like(rgba[0, 3:])
        for k in range(s, min(s + group, len(depths))):  # front to back, premultiplied "over"
            a = rgba[k, 3:]
            color = color + (1 - alpha) * a * rgba[k, :3]
            alpha = alpha + (1 - alpha) * a
        planes.append(torch.cat([color / alpha.clamp_min(1e-6), alpha], 0))
        new_depths.append(1.0 / (1.0 / depths[s : s + group]).mean())
    return torch.stack(planes), torch.stack(new_depths)


def quantize_planes(rgba: torch.Tensor, alpha_floor: int = ALPHA_FLOOR) -> np.ndarray:
    """[D, 4, h, w] straight-alpha planes in [0, 1] -> [D, h, w, 4] uint8 as stored, alpha at or
    below ``alpha_floor`` set to 0 (colours kept)."""
    tiles = to_uint8(rgba).permute(0, 2, 3, 1).cpu().numpy()
    alpha = tiles[..., 3]
    alpha[alpha <= alpha_floor] = 0
    return tiles


def _bake_mpi(
    field: MPIField, frame: MPIFrame, scale: float, merge: int, alpha_floor: int, name: str
) -> tuple[dict[str, Any], np.ndarray]:
    """One MPI of :func:`bake`: its manifest entry and its planes tiled into an atlas
    [rows * h, cols * w, 4] uint8, to be written as ``name``."""
    h, w = (max(2, round(s * scale)) for s in frame.extent)
    rgba, depths = merge_planes(bake_textures(field, frame, (h, w)), frame.depths, merge)
    D = rgba.shape[0]
    rows, cols = _atlas_grid(D)
    atlas = np.zeros((rows * h, cols * w, 4), dtype=np.uint8)
    tiles = quantize_planes(rgba, alpha_floor)
    for k in range(D):
        r, c = divmod(k, cols)
        atlas[r * h : (r + 1) * h, c * w : (c + 1) * w] = tiles[k]
    entry = {
        "K": frame.K.cpu().tolist(),
        "world_from_cam": frame.world_from_ref.cpu().tolist(),
        "depths": depths.cpu().tolist(),
        "margin": list(frame.margin),
        "tile": [h, w],
        "grid": [rows, cols],
        "atlas": name,
    }
    return entry, atlas


def bake(
    model: CMCModel,
    out_dir: str | Path,
    scale: float = 1.0,
    merge: int = 1,
    alpha_floor: int = ALPHA_FLOOR,
    on_progress: Callable[[int, int], None] | None = None,
) -> Path:
    """Write ``model`` in the ``cmc-mpi`` format, each MPI as :meth:`CMCModel.display_fields`
    shows it (in the mean of the photos' colour responses where those were learnt).

    ``scale`` multiplies the texel resolution; ``merge`` > 1 composites that many adjacent
    planes into one (:func:`merge_planes`) for faster rendering; alpha at or below
    ``alpha_floor`` (8-bit counts) is stored as 0 (:func:`quantize_planes`; 0 keeps every alpha).
    ``on_progress(done, total)`` is called after each MPI is evaluated and tiled (at an even
    pace: its PNG is encoded in the background while the next MPI is evaluated, the last one's
    after the call); the manifest is written last, when every atlas is complete.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    mpis = []
    total = len(model.frames)
    with ThreadPoolExecutor(1) as writer:  # encodes MPI i's PNG while MPI i + 1 is evaluated
        written: list[Future] = []
        for i, (mpi_field, frame) in enumerate(zip(model.display_fields(), model.frames, strict=True)):
            entry, atlas = _bake_mpi(mpi_field, frame, scale, merge, alpha_floor, f"mpi_{i:02d}.png")
            mpis.append(entry)
            written.append(writer.submit(Image.fromarray(atlas, "RGBA").save, out / entry["atlas"], compress_level=1))
            if on_progress is not None:
                on_progress(i + 1, total)
        for w in written:
            w.result()  # raises what the writer raised
    centers = torch.stack([f.world_from_ref[:3, 3] for f in model.frames]).cpu()
    manifest = {
        "format": FORMAT,
        "version": VERSION,
        "convention": "opencv",
        "width": model.width,
        "height": model.height,
        "near": model.near,
        "far": model.far,
        "blend": {
            "weights": "inverse_square_distance",
            "eps_baseline_fraction": 0.1,
            "baseline": mean_baseline(centers),
        },
        "colour_interpolation": model.fields[0].colour_interpolation,
        "mpis": mpis,
    }
    tmp = out / (MANIFEST + ".tmp")
    tmp.write_text(json.dumps(manifest, indent=1))
    tmp.replace(out / MANIFEST)  # the manifest appears last: a folder with it is complete
    return out


@dataclass
class BakedRender:
    """A render of a baked scene, NumPy arrays: rgb [H, W, 3] float32 in [0, 1]; depth [H, W]
    target-camera z (scene units, 0 where no plane is hit); acc [H, W] coverage in [0, 1]."""

    rgb: np.ndarray
    depth: np.ndarray
    acc: np.ndarray


@dataclass
class BakedScene:
    """A loaded baked folder: the 8-bit textures of its MPIs plus their frames.

    Attributes:
        packed: every MPI's [D, h, w, 4] uint8 straight-alpha planes (nearest first, the back
            plane opaque, alpha 255, as rendered) and their occupancy, as the compiled kernel
            samples them (:class:`cmc.serving.texture_kernel.PackedTextures`); the only copy of the
            texels kept in memory.
        device: where :meth:`render` runs: the compiled kernel on the CPU
            (:mod:`cmc.serving.texture_kernel`), else :func:`cmc.mpi.rendering.render_image` over
            :attr:`fields` (built on first use).
    """

    packed: PackedTextures
    frames: list[MPIFrame]
    width: int
    height: int
    near: float
    far: float
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    colour_interpolation: str = (
        "bilinear"  # how renders sample colour between texels (cmc.serving.texture_kernel.render)
    )
    _fields: list[TextureField] | None = field(default=None, repr=False)
    _geometry: list[MPIGeometry] | None = field(default=None, repr=False)
    # The reference camera centres [N, 3] and their mean baseline, for the CPU path's blend weights.
    _centers: np.ndarray | None = field(default=None, repr=False)
    _baseline: float = field(default=1.0, repr=False)

    @staticmethod
    def load(folder: str | Path, device: str | torch.device = "cpu") -> BakedScene:
        from cmc.serving.texture_kernel import PackedTextures, default_threads  # numba, imported when a scene is loaded

        folder = Path(folder)
        try:
            m = json.loads((folder / MANIFEST).read_text())
        except FileNotFoundError:
            raise BakedFormatError(f"no {MANIFEST} in {folder}: not a baked MPI folder") from None
        except json.JSONDecodeError as e:
            raise BakedFormatError(f"{folder / MANIFEST} is not valid JSON: {e}") from None
        if m.get("format") != FORMAT or m.get("version") not in READABLE_VERSIONS:
            raise BakedFormatError(
                f"{folder} holds {m.get('format')} v{m.get('version')}, expected {FORMAT} v{VERSION}"
            )
        packed = PackedTextures.allocate([(len(e["depths"]), *e["tile"]) for e in m["mpis"]])

        def read_atlas(i: int) -> None:
            """Decode MPI i's atlas into ``packed`` (each MPI fills its own part of it)."""
            e = m["mpis"][i]
            (h, w), (rows, cols) = e["tile"], e["grid"]
            name = Path(e["atlas"]).name  # never follow paths out of the folder
            with Image.open(folder / name) as im:
                atlas = np.asarray(im.convert("RGBA"))
            D = len(e["depths"])
            if atlas.shape[:2] != (rows * h, cols * w) or rows * cols < D:
                raise BakedFormatError(f"{name} is {atlas.shape[1]}x{atlas.shape[0]}, expected {cols * w}x{rows * h}")
            tex = atlas.reshape(rows, h, cols, w, 4).transpose(0, 2, 1, 3, 4).reshape(rows * cols, h, w, 4)[:D].copy()
            del atlas
            tex[-1, ..., 3] = 255  # the back plane is opaque (cmc.mpi.fields)
            packed.fill(i, tex)

        # The atlases decode in threads (Pillow's PNG decoder releases the GIL).
        with ThreadPoolExecutor(min(len(m["mpis"]), default_threads())) as pool:
            list(pool.map(read_atlas, range(len(m["mpis"]))))
        t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32, device=device)  # noqa: E731
        frames = [
            MPIFrame(t(e["K"]), t(e["world_from_cam"]), t(e["depths"]), m["width"], m["height"], entry_margin(e))
            for e in m["mpis"]
        ]
        interpolation = m.get("colour_interpolation", "bilinear")  # absent from bakes before it existed
        if interpolation not in INTERPOLATIONS:
            raise BakedFormatError(f"{folder / MANIFEST}: unknown colour_interpolation {interpolation!r}")
        return BakedScene(
            packed,
            frames,
            int(m["width"]),
            int(m["height"]),
            float(m["near"]),
            float(m["far"]),
            torch.device(device),
            interpolation,
        )

    @property
    def textures(self) -> list[np.ndarray]:
        """Per MPI, [D, h, w, 4] uint8 straight-alpha planes: views of :attr:`packed`, no copy."""
        return [self.packed.texture(i) for i in range(len(self.frames))]

    @property
    def nbytes(self) -> int:
        """Bytes held by the textures and occupancy maps (what a loaded scene costs in memory)."""
        return self.packed.nbytes

    @property
    def fields(self) -> list[TextureField]:
        """The textures as :class:`TextureField` (float32 on :attr:`device`), built on first use."""
        if self._fields is None:
            self._fields = [
                TextureField(
                    torch.as_tensor(t, device=self.device).permute(0, 3, 1, 2).float() / 255.0,
                    self.colour_interpolation,
                )
                for t in self.textures
            ]
        return self._fields

    def coverage(self, K: np.ndarray, world_from_cam: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """[H, W] bool: the pixels of a render (its ``depth`` [H, W], target-camera z, 0 = no
        surface) whose point an input photo saw (:meth:`cmc.geometry.cameras.Cameras.coverage`; each MPI's
        reference camera is an input photo's). The rest a view shows only by extrapolation."""
        inputs = Cameras(
            np.stack([f.K.cpu().numpy() for f in self.frames]).astype(np.float64),
            np.stack([f.world_from_ref.cpu().numpy() for f in self.frames]).astype(np.float64),
            self.width,
            self.height,
        )
        return inputs.coverage(K, world_from_cam, depth)

    def render(
        self,
        K: np.ndarray,
        world_from_cam: np.ndarray,
        width: int | None = None,
        height: int | None = None,
        min_weight: float = 0.0,
        mpi_index: int | None = None,
        threads: int | None = None,
    ) -> BakedRender:
        """Colour and depth for any camera (OpenCV convention), default size the input size;
        the blend of all MPIs (:func:`cmc.mpi.rendering.render_image`), or MPI ``mpi_index`` alone.
        On the CPU NumPy end to end; ``threads``: CPU threads for this render (default one per core)."""
        width, height = width or self.width, height or self.height
        if self.device.type != "cpu":
            out = render_image(
                self.fields, self.frames, K, world_from_cam, width, height, mpi_index, min_weight=min_weight
            )
            return BakedRender(*(a.float().cpu().numpy() for a in (out.rgb, out.depth, out.acc)))
        from cmc.serving.texture_kernel import MPIGeometry
        from cmc.serving.texture_kernel import render as render_packed

        if self._geometry is None or self._centers is None:
            self._geometry = [MPIGeometry.from_frame(f) for f in self.frames]
            self._centers = np.stack([f.world_from_ref[:3, 3].cpu().numpy() for f in self.frames]).astype(np.float64)
            self._baseline = mean_baseline(self._centers)
        target = np.asarray(world_from_cam, dtype=np.float64)[:3, 3]
        weights, use = select_mpis(blend_weights(self._centers, target, self._baseline), mpi_index, min_weight)
        rgb, depth, acc = render_packed(
            self.packed,
            self._geometry,
            weights,
            use,
            K,
            world_from_cam,
            width,
            height,
            threads=threads,
            colour_interpolation=self.colour_interpolation,
        )
        return BakedRender(rgb, depth, acc)
