"""The compiled CPU renderer of baked MPIs (cmc.serving.texture_kernel) against the slow per-plane twin."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from cmc.geometry.cameras import look_at
from cmc.mpi._reference import render_texture_image_reference
from cmc.mpi.rendering import BICUBIC_MIN_WEIGHT, MPIFrame, blend, render_texture_image
from cmc.serving.baking import BakedScene
from cmc.serving.texture_kernel import (
    COLS,
    ROWS,
    TILE,
    MPIGeometry,
    PackedTextures,
    occupancy,
    occupied_tiles,
    reach,
    render,
)

W, H, D = 40, 30, 6
K = np.array([[36.0, 0, W / 2], [0, 36.0, H / 2], [0, 0, 1]])


def _textures(rng: np.random.Generator) -> np.ndarray:
    """[D, h, w, 4] uint8: random colours, alpha on a few blobs per plane (most tiles empty),
    some texels fully opaque, the back plane opaque."""
    h, w = int(H * 1.2), int(W * 1.2)
    tex = rng.integers(0, 256, size=(D, h, w, 4), dtype=np.uint8)
    alpha = np.zeros((D, h, w), dtype=np.uint8)
    for k in range(D - 1):
        for _ in range(2):
            y, x = rng.integers(0, h - 6), rng.integers(0, w - 6)
            alpha[k, y : y + 6, x : x + 6] = rng.integers(1, 256, size=(6, 6))
        alpha[k, 0, 0] = 255  # a lone texel in the corner tile
    alpha[-1] = 255
    tex[..., 3] = alpha
    return tex


def _premultiplied(tex: np.ndarray) -> torch.Tensor:
    rgba = torch.as_tensor(tex).permute(0, 3, 1, 2).float() / 255.0
    return torch.cat([rgba[:, :3] * rgba[:, 3:], rgba[:, 3:]], 1)


def _twin(textures: list[np.ndarray], frames: list[MPIFrame], weights: np.ndarray, P: np.ndarray, size=(W, H)):
    """The slow per-plane twin of every MPI, blended as cmc.mpi.rendering.render_image blends them."""
    Kt, Pt = torch.as_tensor(K, dtype=torch.float32), torch.as_tensor(P, dtype=torch.float32)
    outs = [
        render_texture_image_reference(_premultiplied(t), f, Kt, Pt, *size)
        for t, f in zip(textures, frames, strict=True)
    ]
    return blend(outs, torch.as_tensor(weights, dtype=torch.float32))


def _fast(textures, frames, weights, P, min_transmittance=0.0, threads=1, packed=None, size=(W, H)):
    packed = packed or PackedTextures.pack(textures)
    geometry = [MPIGeometry.from_frame(f) for f in frames]
    return render(packed, geometry, weights, range(len(textures)), K, P, *size, min_transmittance, threads)


def _assert_close(fast, slow):
    rgb, depth, acc = (torch.from_numpy(a) for a in fast)
    torch.testing.assert_close(rgb.reshape(-1, 3), slow.rgb, rtol=0, atol=2e-5)
    torch.testing.assert_close(acc.reshape(-1), slow.acc, rtol=0, atol=2e-5)
    torch.testing.assert_close(depth.reshape(-1), slow.depth, rtol=1e-4, atol=1e-4)


FRAME = MPIFrame.create(K, np.eye(4), 2.0, 8.0, D, W, H, 1.2, "cpu")
CAMERAS = {
    "reference": np.eye(4),
    "sideways": look_at(np.array([0.4, -0.2, 0.0]), np.array([0.0, 0.0, 4.0])),
    "outside the capture": look_at(np.array([0.0, 0.0, 0.0]), np.array([3.0, 0.5, 2.0])),
    "between the planes": look_at(np.array([0.1, 0.0, 3.0]), np.array([0.1, 0.0, 8.0])),
    "on a plane, looking along it": look_at(
        np.array([0.0, 0.0, float(FRAME.depths[2])]), np.array([1.0, 0.1, float(FRAME.depths[2]) + 0.3])
    ),
    "behind all planes, looking back": look_at(np.array([0.0, 0.0, 9.0]), np.array([0.0, 0.0, 0.0])),
}


@pytest.mark.parametrize("camera", list(CAMERAS))
def test_kernel_equals_the_slow_twin(camera):
    tex = _textures(np.random.default_rng(1))
    P = CAMERAS[camera]
    fast = _fast([tex], [FRAME], np.ones(1), P)
    slow = _twin([tex], [FRAME], np.ones(1), P)
    assert float(slow.acc.max()) > 0.5, "the camera must see some of the planes"
    if camera in ("outside the capture", "on a plane, looking along it"):
        assert float(slow.acc.min()) < 0.5, "and miss some"
    _assert_close(fast, slow)
    # Early termination changes a pixel by at most the transmittance left.
    rgb_t, _, acc_t = _fast([tex], [FRAME], np.ones(1), P, min_transmittance=1e-3)
    assert np.abs(rgb_t - fast[0]).max() <= 1e-3 and np.abs(acc_t - fast[2]).max() <= 1e-3


@pytest.mark.parametrize("camera", ["reference", "sideways", "between the planes"])
def test_kernel_blends_mpis_of_different_sizes_as_the_twin(camera):
    """Two MPIs (other camera, plane count and texture size) blended in the kernel, on 1 or 3
    threads (identical results), equal the blend of their slow twins."""
    rng = np.random.default_rng(2)
    other = MPIFrame.create(K, look_at(np.array([-0.3, 0.1, 0.0]), np.array([0.0, 0.0, 5.0])), 2.5, 9.0, 4, W, H, 1.0)
    tex2 = rng.integers(0, 256, size=(4, H, W, 4), dtype=np.uint8)
    tex2[-1, ..., 3] = 255
    textures, frames, weights = [_textures(rng), tex2], [FRAME, other], np.array([0.7, 0.3])
    P = CAMERAS[camera]
    one = _fast(textures, frames, weights, P, threads=1)
    three = _fast(textures, frames, weights, P, threads=3)
    assert all(np.array_equal(a, b) for a, b in zip(one, three, strict=True))
    _assert_close(one, _twin(textures, frames, weights, P))


@pytest.mark.parametrize("size", [(W - 3, H - 1), (COLS + 1, ROWS - 3), (3, 2)])
@pytest.mark.parametrize("camera", ["reference", "outside the capture", "behind all planes, looking back"])
def test_kernel_equals_the_slow_twin_at_sizes_that_leave_blocks_part_full(camera, size):
    """Images whose width is no multiple of the block's columns nor height of the band's rows
    (the last blocks of a row and the last band hold fewer rays) render as the twin."""
    tex = _textures(np.random.default_rng(5))
    P = CAMERAS[camera]
    _assert_close(_fast([tex], [FRAME], np.ones(1), P, size=size), _twin([tex], [FRAME], np.ones(1), P, size))


@pytest.mark.parametrize("camera", ["reference", "sideways", "outside the capture", "behind all planes, looking back"])
def test_bicubic_colour_in_the_kernel_is_the_torch_renderers(camera):
    """``colour_interpolation="bicubic"``: the kernel (alpha bilinear, straight colour over 4 x 4
    texels, edges repeated) against cmc.mpi.rendering's whole-image path given the straight colours,
    with every plane's colours noisy so that a wrong tap shows; on 1 and 3 threads, and with
    empty blocks and transparent samples skipped or not (skipping stays exact)."""
    tex = _textures(np.random.default_rng(8))
    P = CAMERAS[camera]
    packed = PackedTextures.pack([tex])
    geometry = [MPIGeometry.from_frame(FRAME)]
    everything = replace(
        packed, reach=np.full_like(packed.reach, 255), sat=occupied_tiles(np.ones_like(occupancy(tex))).reshape(-1)
    )
    runs = [
        render(p, geometry, np.ones(1), [0], K, P, W, H, 0.0, n, colour_interpolation="bicubic")
        for p, n in ((packed, 1), (packed, 3), (everything, 1))
    ]
    assert all(np.array_equal(a, b) for run in runs[1:] for a, b in zip(runs[0], run, strict=True))
    straight = torch.as_tensor(tex).permute(0, 3, 1, 2).float() / 255.0
    Kt, Pt = torch.as_tensor(K, dtype=torch.float32), torch.as_tensor(P, dtype=torch.float32)
    torch_out = render_texture_image(_premultiplied(tex), FRAME, Kt, Pt, W, H, straight_rgb=straight[:, :3])
    _assert_close(runs[0], blend([torch_out], torch.ones(1)))
    bilinear = _fast([tex], [FRAME], np.ones(1), P)
    # The reference camera's pixels fall on texel centres (this frame's texels are its pixels),
    # where both kernels return the texel; elsewhere the colours differ.
    differ = np.abs(bilinear[0] - runs[0][0]).max()
    assert differ < 1e-5 if camera == "reference" else differ > 0.05
    assert np.array_equal(bilinear[2], runs[0][2])  # the coverage does not: alpha stays bilinear


@pytest.mark.parametrize("camera", ["sideways", "between the planes"])
def test_faint_samples_take_bilinear_colour_in_every_renderer(camera):
    """Where colour is bicubic, a sample weighing less than ``bicubic_min_weight`` in its pixel
    takes its four texels' bilinear premultiplied colour: the kernel, the whole-image torch path
    and the slow twin agree at 0 (every sample bicubic), at the default and at 2 (every sample
    bilinear: the bilinear render to the bit). The default moves some pixels, none by more than
    the faint samples' summed weight (under D times the threshold)."""
    tex = _textures(np.random.default_rng(10))
    P = CAMERAS[camera]
    packed, geometry = PackedTextures.pack([tex]), [MPIGeometry.from_frame(FRAME)]
    straight = (torch.as_tensor(tex).permute(0, 3, 1, 2).float() / 255.0)[:, :3]
    Kt, Pt = torch.as_tensor(K, dtype=torch.float32), torch.as_tensor(P, dtype=torch.float32)
    runs = {}
    for t in (0.0, BICUBIC_MIN_WEIGHT, 2.0):
        runs[t] = render(
            packed, geometry, np.ones(1), [0], K, P, W, H, 0.0, 1, colour_interpolation="bicubic", bicubic_min_weight=t
        )
        for twin in (render_texture_image, render_texture_image_reference):
            out = twin(_premultiplied(tex), FRAME, Kt, Pt, W, H, straight_rgb=straight, bicubic_min_weight=t)
            _assert_close(runs[t], blend([out], torch.ones(1)))
    bilinear = _fast([tex], [FRAME], np.ones(1), P)
    assert all(np.array_equal(a, b) for a, b in zip(runs[2.0], bilinear, strict=True))
    moved = np.abs(runs[BICUBIC_MIN_WEIGHT][0] - runs[0.0][0]).max()
    assert 1e-3 < moved <= D * BICUBIC_MIN_WEIGHT


def test_the_kernel_refuses_an_unknown_interpolation():
    with pytest.raises(ValueError, match="colour_interpolation"):
        render(PackedTextures.pack([_textures(np.random.default_rng(9))]), [MPIGeometry.from_frame(FRAME)],
               np.ones(1), [0], K, np.eye(4), W, H, colour_interpolation="nearest")  # fmt: skip


@pytest.mark.parametrize("camera", list(CAMERAS))
def test_skipping_empty_blocks_and_transparent_samples_is_exact(camera):
    """With every tile marked occupied and every texel reaching alpha (nothing skipped but opaque
    rays) the render is the same to the bit: on mostly empty planes, at cameras whose blocks
    straddle the planes' edges (outside the capture) or see the planes edge-on or from behind."""
    tex = _textures(np.random.default_rng(6))
    tex[2] = 0  # a plane with no alpha at all
    packed = PackedTextures.pack([tex])
    everything = replace(
        packed, reach=np.full_like(packed.reach, 255), sat=occupied_tiles(np.ones_like(occupancy(tex))).reshape(-1)
    )
    P = CAMERAS[camera]
    for min_transmittance in (0.0, 1e-4):
        a = _fast([tex], [FRAME], np.ones(1), P, min_transmittance, packed=packed)
        b = _fast([tex], [FRAME], np.ones(1), P, min_transmittance, packed=everything)
        assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))


def test_reach_bits_mark_samples_that_can_have_alpha():
    alpha = np.zeros((1, 4, 5), np.uint8)
    alpha[0, 2, 3] = 1
    # A sample reaches texel (2, 3) from its top-left tap at (1..2, 2..3).
    assert np.argwhere(reach(alpha)[0]).tolist() == [[1, 2], [1, 3], [2, 2], [2, 3]]
    rng = np.random.default_rng(7)
    textures = [_textures(rng), rng.integers(0, 256, size=(3, 5, 7, 4), dtype=np.uint8)]
    packed = PackedTextures.pack(textures)
    bits = np.unpackbits(packed.reach, bitorder="little").astype(bool)
    for i, tex in enumerate(textures):
        D, h, w = tex.shape[:3]
        framed = np.zeros((D, h + 2, w + 2), np.uint8)
        framed[:, 1:-1, 1:-1] = tex[..., 3]
        start = int(packed.base[i, 0])
        assert start % 8 == 0  # each MPI's bits start a byte
        assert np.array_equal(bits[start : start + framed.size], reach(framed).reshape(-1))
    # The summed-area table counts the occupied tiles of any rectangle.
    sat = occupied_tiles(occupancy(textures[0]))
    occ = occupancy(textures[0])
    assert sat[1, 3, 4] == occ[1, :3, :4].sum() and sat[0, -1, -1] == occ[0].sum()


def test_occupancy_marks_tiles_a_bilinear_tap_can_reach():
    tex = np.zeros((2, 3 * TILE - 2, 3 * TILE - 2, 4), dtype=np.uint8)  # framed: 3 x 3 tiles
    tex[0, TILE - 1, TILE - 1] = 200, 100, 50, 9  # framed texel (TILE, TILE): the middle tile's first
    occ = occupancy(tex)
    assert occ.shape == (2, 3, 3) and not occ[1].any()  # the second plane is empty
    # A sample whose top-left tap is one texel up or left of it (in the tiles before) reaches it.
    assert occ[0].tolist() == [[1, 1, 0], [1, 1, 0], [0, 0, 0]]
    # Skipping empty tiles and texels is exact: the kernel with the real maps equals it with every
    # tile and texel marked.
    frame = MPIFrame.create(K, np.eye(4), 2.0, 8.0, 2, 3 * TILE - 2, 3 * TILE - 2, 1.0, "cpu")
    P = look_at(np.array([0.05, 0.03, 0.0]), np.array([0.0, 0.0, 4.0]))
    packed = PackedTextures.pack([tex])
    full = occupied_tiles(np.ones_like(occ)).reshape(-1)
    every = replace(packed, reach=np.full_like(packed.reach, 255), sat=full)
    a = _fast([tex], [frame], np.ones(1), P, packed=packed)
    b = _fast([tex], [frame], np.ones(1), P, packed=every)
    assert a[2].max() > 0 and all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))


def test_packed_textures_keep_the_texels():
    rng = np.random.default_rng(3)
    textures = [_textures(rng), rng.integers(0, 256, size=(3, 5, 7, 4), dtype=np.uint8)]
    packed = PackedTextures.pack(textures)
    assert all(np.array_equal(packed.texture(i), t) for i, t in enumerate(textures))
    assert packed.texels.dtype == np.dtype("<u4")
    first = int(packed.texels[packed.base[1, 0] + (7 + 2) + 1])  # MPI 1, plane 0, texel (0, 0) (framed)
    assert first == int.from_bytes(textures[1][0, 0, 0].tobytes(), "little")  # R in the low byte


def test_baked_scene_keeps_only_the_8_bit_textures(tmp_path):
    from cmc.config import preset_config
    from cmc.data.datasets import synthetic_scene
    from cmc.method.training import Trainer
    from cmc.serving.baking import bake

    scene = synthetic_scene(num_views=2, width=32, height=24)
    trainer = Trainer(scene, preset_config("fast", steps=2, rays_per_view=64, unseen_rays=64))
    baked = BakedScene.load(bake(trainer.model, tmp_path / "b"))
    assert all(t.dtype == np.uint8 and t.shape[-1] == 4 for t in baked.textures)
    assert all((t[-1, ..., 3] == 255).all() for t in baked.textures)  # the back plane is opaque
    texels = sum(t.nbytes for t in baked.textures)
    assert baked.nbytes == baked.packed.nbytes and texels < baked.nbytes < 1.25 * texels  # frames, tile map
    assert baked._fields is None  # no float copy until a non-CPU path asks for one


def test_render_cache_is_bounded_by_bytes(tmp_path):
    """The service's cache of loaded scenes (keyed by storage folder) drops the least recently used
    beyond its byte budget, but never the scene it just loaded; loading a scene's final bake drops
    its preview; a folder with nothing stored is FileNotFoundError."""
    from cmc.config import preset_config
    from cmc.data.datasets import synthetic_scene
    from cmc.method.training import Trainer
    from cmc.serving.baking import bake
    from service.renders import BakedCache
    from service.storage import LocalStorage

    scene = synthetic_scene(num_views=2, width=32, height=24)
    model = Trainer(scene, preset_config("fast", steps=1, rays_per_view=64, unseen_rays=64)).model
    a, b, c = (f"{n:032x}/baked" for n in (10, 11, 12))  # scene ids as the service makes them
    for folder in (a, b, c, f"{12:032x}/preview"):
        bake(model, tmp_path / folder)
    size = BakedScene.load(tmp_path / a).nbytes
    cache = BakedCache(LocalStorage(tmp_path), capacity_bytes=2 * size)
    for folder in (a, b, a, c):  # b is now the least recently used
        cache.get(folder)
    assert list(cache._scenes) == [a, c] and cache.nbytes == 2 * size
    cache.evict(f"{12:032x}")
    cache.get(f"{12:032x}/preview")
    assert list(cache._scenes) == [a, f"{12:032x}/preview"]
    cache.get(c)  # the final bake replaces the preview of the same scene
    assert list(cache._scenes) == [a, c]
    with pytest.raises(FileNotFoundError):
        cache.get(f"{13:032x}/preview")
    small = BakedCache(LocalStorage(tmp_path), capacity_bytes=size // 2)
    small.get(a)
    assert list(small._scenes) == [a]
    out = small.render(a, scene.cameras.K[0], scene.cameras.world_from_cam[0], 32, 24)
    assert out.rgb.shape == (24, 32, 3) and out.rgb.mean() > 0.05


def test_renders_on_several_threads_at_once_are_those_made_one_by_one():
    """The service computes several renders at once (CMC_RENDER_CONCURRENCY), each on
    CMC_RENDER_THREADS threads: the kernel shares nothing between calls."""
    from concurrent.futures import ThreadPoolExecutor

    tex = _textures(np.random.default_rng(4))
    packed = PackedTextures.pack([tex])
    cameras = list(CAMERAS.values()) * 2
    alone = [_fast([tex], [FRAME], np.ones(1), P, 1e-4, 1, packed) for P in cameras]
    with ThreadPoolExecutor(4) as pool:
        together = list(pool.map(lambda P: _fast([tex], [FRAME], np.ones(1), P, 1e-4, 2, packed), cameras))
    for a, b in zip(alone, together, strict=True):
        assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
