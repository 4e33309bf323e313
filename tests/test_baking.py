"""Baking: the baked renderer reproduces the field render, the format is readable and checked."""

from __future__ import annotations

import copy
import json
from dataclasses import replace

import numpy as np
import pytest
import torch
from PIL import Image

from cmc.config import preset_config
from cmc.data.datasets import synthetic_scene
from cmc.eval.metrics import psnr
from cmc.geometry.cameras import pixel_rays
from cmc.geometry.planes import blend_weights, mean_baseline, sample_virtual_pose, texel_grid
from cmc.method.training import Trainer
from cmc.mpi._reference import render_texture_image_reference
from cmc.mpi.fields import MPIField, PyramidPlaneField
from cmc.mpi.rendering import blend
from cmc.serving.baking import BakedFormatError, BakedScene, bake, bake_textures, quantize_planes

W, H = 64, 48


@pytest.fixture(scope="module", params=["fast", "paper"])
def trained(request):
    scene = synthetic_scene(num_views=3, width=W, height=H)
    cfg = preset_config(request.param, steps=15, rays_per_view=256, unseen_rays=256)
    cfg = replace(cfg, model=replace(cfg.model, num_planes=10, mlp=replace(cfg.model.mlp, width=32, depth=2)))
    trainer = Trainer(scene, cfg)
    trainer.fit()
    return scene, trainer.model


def test_baked_render_matches_field_render_at_input_views(trained, tmp_path):
    """Baked with every alpha kept (alpha_floor 0): this short training leaves faint alpha (the
    plane-sweep start's 0.01) on many planes, which the default floor drops on purpose."""
    scene, model = trained
    baked = BakedScene.load(bake(model, tmp_path / "baked", alpha_floor=0))
    for i in range(len(scene)):
        K, pose = scene.cameras.K[i], scene.cameras.world_from_cam[i]
        a, b = model.render(K, pose, W, H), baked.render(K, pose)
        assert psnr(a.rgb.numpy(), b.rgb) >= 35
        # The field interpolates alpha logits then applies the sigmoid; the baked texture holds
        # sigmoid values and the renderer interpolates those (in 8 bits). With the sharp plane-sweep
        # start (logits +-4.6 one texel apart) the two differ along occlusion edges by part of a
        # plane step: the bulk must agree, the edge tail within one plane step (here 10 planes
        # from 1.6 to 6.6: one step is 10.5 % of depth at z = 2, the nearest layer, more behind).
        rel = (a.depth - torch.from_numpy(b.depth)).abs() / a.depth
        assert rel.median().item() < 0.005 and rel.quantile(0.95).item() < 0.02, rel.quantile(0.95)
        assert rel.quantile(0.99).item() < 0.1, rel.quantile(0.99)


def test_baked_render_matches_slow_twin(trained, tmp_path):
    """BakedScene.render (the fast whole-image path) equals the blend of the slow per-plane twin's
    renders of every baked MPI, at the input views and at unseen poses."""
    scene, model = trained
    baked = BakedScene.load(bake(model, tmp_path / "baked"))
    rng = np.random.default_rng(0)
    poses = [scene.cameras.world_from_cam[0]]
    poses += [sample_virtual_pose(scene.cameras.world_from_cam, rng, jitter=0.3) for _ in range(2)]
    centers = torch.stack([f.world_from_ref[:3, 3] for f in baked.frames])
    K = torch.as_tensor(scene.cameras.K[0], dtype=torch.float32)
    for pose in poses:
        P = torch.as_tensor(pose, dtype=torch.float32)
        fast = baked.render(K.numpy(), pose)
        cubic = baked.colour_interpolation == "bicubic"
        twins = [
            render_texture_image_reference(f.premultiplied, fr, K, P, W, H, f.rgba[:, :3] if cubic else None)
            for f, fr in zip(baked.fields, baked.frames, strict=True)
        ]
        slow = blend(twins, blend_weights(centers, P[:3, 3], mean_baseline(centers)))
        assert float(slow.acc.max()) > 0.99
        # The CPU kernel stops a ray at transmittance 1e-4 (cmc.serving.texture_kernel): colour and
        # coverage may differ by that much, depth by that share of the far plane's depth.
        rgb, acc, depth = (torch.from_numpy(x) for x in (fast.rgb, fast.acc, fast.depth))
        torch.testing.assert_close(rgb.reshape(-1, 3), slow.rgb, rtol=0, atol=1e-4)
        torch.testing.assert_close(acc.reshape(-1), slow.acc, rtol=0, atol=1e-4)
        torch.testing.assert_close(depth.reshape(-1), slow.depth, rtol=1e-4, atol=1e-4 * float(baked.far))


def test_manifest_describes_the_atlases(trained, tmp_path):
    _, model = trained
    reported = []
    out = bake(model, tmp_path / "b", on_progress=lambda done, total: reported.append((done, total)))
    assert reported == [(1, 3), (2, 3), (3, 3)]  # after each MPI is evaluated
    m = json.loads((out / "mpi.json").read_text())
    assert m["format"] == "cmc-mpi" and m["version"] == 2 and m["convention"] == "opencv"
    # How renders sample colour is the field's: `fast` samples its base colours bicubically,
    # `paper`'s MLP is baked to texels that renders sample bilinearly.
    expected = "bicubic" if isinstance(model.fields[0], PyramidPlaneField) else "bilinear"
    assert m["colour_interpolation"] == expected == BakedScene.load(out).colour_interpolation
    # A bake from before the key existed renders bilinearly; an unknown value is refused.
    del m["colour_interpolation"]
    (out / "mpi.json").write_text(json.dumps(m))
    assert BakedScene.load(out).colour_interpolation == "bilinear"
    (out / "mpi.json").write_text(json.dumps({**m, "colour_interpolation": "lanczos"}))
    with pytest.raises(BakedFormatError, match="colour_interpolation"):
        BakedScene.load(out)
    assert len(m["mpis"]) == 3
    for e in m["mpis"]:
        assert len(e["depths"]) == 10 and e["depths"] == sorted(e["depths"])
        atlas = Image.open(out / e["atlas"])  # complete when the bake returns
        assert atlas.size == (e["grid"][1] * e["tile"][1], e["grid"][0] * e["tile"][0])
        atlas.load()


def test_texel_grid_evaluation_matches_its_slow_twin(trained):
    """What a bake evaluates (``on_texel_grid``: for ``fast``'s textures every texel at once in
    the samplers' layout, the colours taken into the mean response in place) equals the generic
    evaluation, a few texels at a time through ``forward``, at the plane extent and at the half
    resolution of a preview bake; the photos' responses made to differ so that the conversion shows."""
    _, model = trained
    model = copy.deepcopy(model)
    if model.exposure is not None:
        with torch.no_grad():
            model.exposure.log_gain.copy_(torch.tensor([[0.1, -0.2, 0.0], [0.3, 0.0, -0.1], [0.0, 0.2, 0.1]]))
            model.exposure.offset.copy_(torch.tensor([[0.02, 0.0, -0.03], [0.0, 0.01, 0.0], [-0.02, 0.0, 0.04]]))
    for field, frame in zip(model.display_fields(), model.frames, strict=True):
        for tile in (frame.extent, tuple(s // 2 for s in frame.extent)):
            fast = bake_textures(field, frame, tile)
            g = texel_grid(*tile)
            dirs = pixel_rays(frame.K, frame.pixels_from_grid(g.reshape(-1, 2)))
            slow = MPIField.on_texel_grid(field, g, frame.plane_z, dirs / dirs.norm(dim=-1, keepdim=True), chunk=500)
            assert fast.shape == (10, 4, *tile)
            torch.testing.assert_close(fast, slow, rtol=0, atol=1e-6)
            assert (fast[-1, 3] == 1).all() and fast.min() >= 0 and fast.max() <= 1


def test_version_1_folders_read_one_margin_for_both_axes(trained, tmp_path):
    """A folder baked before the margins were per axis (``cmc-mpi`` v1: one number) still loads:
    that margin on both axes, the geometry it was baked with."""
    _, model = trained
    out = bake(model, tmp_path / "b")
    m = json.loads((out / "mpi.json").read_text())
    assert [e["margin"] for e in m["mpis"]] == [list(f.margin) for f in model.frames]
    assert model.frames[0].margin[0] != model.frames[0].margin[1]  # 64 x 48 plus 6 and 5 pixels a side
    m["version"] = 1
    for e in m["mpis"]:
        e["margin"] = 1.2
    (out / "mpi.json").write_text(json.dumps(m))
    assert [f.margin for f in BakedScene.load(out).frames] == [(1.2, 1.2)] * 3


def test_missing_or_foreign_folders_are_refused(tmp_path):
    with pytest.raises(BakedFormatError, match="not a baked MPI folder"):
        BakedScene.load(tmp_path)
    (tmp_path / "mpi.json").write_text(json.dumps({"format": "other", "version": 7}))
    with pytest.raises(BakedFormatError, match="expected cmc-mpi v2"):
        BakedScene.load(tmp_path)


def test_an_atlas_of_the_wrong_size_is_refused(trained, tmp_path):
    """The atlases decode in threads: an error in one reaches the caller, naming the atlas."""
    _, model = trained
    out = bake(model, tmp_path / "b")
    name = json.loads((out / "mpi.json").read_text())["mpis"][1]["atlas"]
    Image.new("RGBA", (8, 8)).save(out / name)
    with pytest.raises(BakedFormatError, match=f"{name} is 8x8, expected"):
        BakedScene.load(out)


def test_merged_planes_are_exact_at_the_reference_view(trained, tmp_path):
    """Merging adjacent planes composites them in the reference camera: its render is unchanged
    (up to 8-bit storage), there are half as many planes, and depths stay in range."""
    scene, model = trained
    full = BakedScene.load(bake(model, tmp_path / "full"))
    merged = BakedScene.load(bake(model, tmp_path / "merged", merge=2))
    assert len(merged.frames[0].depths) == 5
    assert merged.frames[0].depths[0] >= full.frames[0].depths[0]
    assert merged.frames[0].depths[-1] <= full.frames[0].depths[-1]
    K, pose = scene.cameras.K[0], scene.cameras.world_from_cam[0]
    a = full.render(K, pose, min_weight=0.99)  # the reference MPI alone
    b = merged.render(K, pose, min_weight=0.99)
    assert psnr(a.rgb, b.rgb) >= 40


def test_faint_alpha_is_stored_as_zero():
    """Alpha at or below ALPHA_FLOOR counts (under 1 % opacity) is stored as 0, colours kept;
    alpha above it and the opaque back plane are stored as rounded."""
    rgba = torch.zeros(2, 4, 1, 4)
    rgba[:, :3] = 0.5
    rgba[0, 3, 0] = torch.tensor([0.003, 0.0078, 0.0118, 0.5])  # 8-bit 1, 2, 3, 128
    rgba[1, 3] = 1.0
    tiles = quantize_planes(rgba)
    assert tiles.dtype == np.uint8 and tiles.shape == (2, 1, 4, 4)
    assert tiles[0, 0, :, 3].tolist() == [0, 0, 3, 128]
    assert (tiles[..., :3] == 128).all() and (tiles[1, ..., 3] == 255).all()
