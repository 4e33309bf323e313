"""The compiled CPU renderer of baked MPIs (cmc.texture_kernel) against the slow per-plane twin."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from cmc.baking import BakedScene
from cmc.cameras import look_at
from cmc.rendering import MPIFrame, render_texture_image_reference
from cmc.texture_kernel import TILE, occupancy, render_baked_mpi

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


def _twin(tex: np.ndarray, frame: MPIFrame, P: np.ndarray):
    rgba = torch.as_tensor(tex).permute(0, 3, 1, 2).float() / 255.0
    premult = torch.cat([rgba[:, :3] * rgba[:, 3:], rgba[:, 3:]], 1)
    Kt, Pt = torch.as_tensor(K, dtype=torch.float32), torch.as_tensor(P, dtype=torch.float32)
    return render_texture_image_reference(premult, frame, Kt, Pt, W, H)


CAMERAS = {
    "reference": np.eye(4),
    "sideways": look_at(np.array([0.4, -0.2, 0.0]), np.array([0.0, 0.0, 4.0])),
    "outside the capture": look_at(np.array([0.0, 0.0, 0.0]), np.array([3.0, 0.5, 2.0])),
    "between the planes": look_at(np.array([0.1, 0.0, 3.0]), np.array([0.1, 0.0, 8.0])),
    "behind all planes, looking back": look_at(np.array([0.0, 0.0, 9.0]), np.array([0.0, 0.0, 0.0])),
}


@pytest.mark.parametrize("camera", list(CAMERAS))
def test_kernel_equals_the_slow_twin(camera):
    rng = np.random.default_rng(1)
    tex = _textures(rng)
    frame = MPIFrame.create(K, np.eye(4), 2.0, 8.0, D, W, H, 1.2, "cpu")
    P = CAMERAS[camera]
    rgb, depth, acc = render_baked_mpi(tex, occupancy(tex), frame, K, P, W, H, min_transmittance=0.0)
    slow = _twin(tex, frame, P)
    assert float(slow.acc.max()) > 0.5, "the camera must see some of the planes"
    torch.testing.assert_close(torch.from_numpy(rgb).reshape(-1, 3), slow.rgb, rtol=0, atol=2e-5)
    torch.testing.assert_close(torch.from_numpy(acc).reshape(-1), slow.acc, rtol=0, atol=2e-5)
    torch.testing.assert_close(torch.from_numpy(depth).reshape(-1), slow.depth, rtol=1e-4, atol=1e-4)
    # Early termination changes a pixel by at most the transmittance left.
    rgb_t, _, acc_t = render_baked_mpi(tex, occupancy(tex), frame, K, P, W, H, min_transmittance=1e-3)
    assert np.abs(rgb_t - rgb).max() <= 1e-3 and np.abs(acc_t - acc).max() <= 1e-3


def test_occupancy_marks_tiles_a_bilinear_tap_can_reach():
    tex = np.zeros((2, 3 * TILE, 3 * TILE, 4), dtype=np.uint8)  # the second plane is empty
    tex[0, TILE, TILE] = 200, 100, 50, 9  # the first texel of the middle tile
    occ = occupancy(tex)
    assert occ.shape == (2, 3, 3) and not occ[1].any()
    # A sample whose top-left tap is one texel up or left of it (in the tiles before) reaches it.
    assert occ[0].tolist() == [[True, True, False], [True, True, False], [False, False, False]]
    # Skipping empty tiles is exact: the kernel with the real map equals it with every tile marked.
    frame = MPIFrame.create(K, np.eye(4), 2.0, 8.0, 2, 3 * TILE, 3 * TILE, 1.0, "cpu")
    P = look_at(np.array([0.05, 0.03, 0.0]), np.array([0.0, 0.0, 4.0]))
    a = render_baked_mpi(tex, occ, frame, K, P, W, H, 0.0)
    b = render_baked_mpi(tex, np.ones_like(occ), frame, K, P, W, H, 0.0)
    assert a[2].max() > 0 and all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))


def test_baked_scene_keeps_only_the_8_bit_textures(tmp_path):
    from cmc.baking import bake
    from cmc.config import preset_config
    from cmc.datasets import synthetic_scene
    from cmc.training import Trainer

    scene = synthetic_scene(num_views=2, width=32, height=24)
    trainer = Trainer(scene, preset_config("fast", steps=2, rays_per_view=64, unseen_rays=64))
    baked = BakedScene.load(bake(trainer.model, tmp_path / "b"))
    assert all(t.dtype == np.uint8 and t.shape[-1] == 4 for t in baked.textures)
    assert all((t[-1, ..., 3] == 255).all() for t in baked.textures)  # the back plane is opaque
    assert baked.nbytes == sum(t.nbytes for t in baked.textures) + sum(o.nbytes for o in baked.occupancy)
    assert baked._fields is None  # no float copy until a non-CPU path asks for one


def test_render_cache_is_bounded_by_bytes(tmp_path):
    """The service's cache of loaded scenes drops the least recently used beyond its byte budget,
    but never the scene it just loaded."""
    from cmc.baking import bake
    from cmc.config import preset_config
    from cmc.datasets import synthetic_scene
    from cmc.training import Trainer
    from service.renders import BakedCache
    from service.storage import LocalStorage

    scene = synthetic_scene(num_views=2, width=32, height=24)
    model = Trainer(scene, preset_config("fast", steps=1, rays_per_view=64, unseen_rays=64)).model
    a, b, c = (f"{n:032x}" for n in (10, 11, 12))  # scene ids as the service makes them
    for name in (a, b, c):
        bake(model, tmp_path / name / "baked")
    size = BakedScene.load(tmp_path / a / "baked").nbytes
    cache = BakedCache(LocalStorage(tmp_path), capacity_bytes=2 * size)
    for name in (a, b, a, c):  # b is now the least recently used
        cache.get(name)
    assert list(cache._scenes) == [a, c] and cache.nbytes == 2 * size
    small = BakedCache(LocalStorage(tmp_path), capacity_bytes=size // 2)
    small.get(a)
    assert list(small._scenes) == [a]
    out = small.render(a, scene.cameras.K[0], scene.cameras.world_from_cam[0], 32, 24)
    assert out.rgb.shape == (24, 32, 3) and out.rgb.mean() > 0.05
