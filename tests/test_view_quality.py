"""The view-quality priors do what they claim, on scenes with known depth (not just that they run)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from cmc.config import preset_config, with_settings
from cmc.datasets import synthetic_scene
from cmc.losses import distortion
from cmc.rendering import RayOutput, pixel_centers, render_rays
from cmc.training import Trainer

W, H = 64, 48


def _out(weights: torch.Tensor) -> RayOutput:
    R = weights.shape[0]
    return RayOutput(torch.zeros(R, 3), torch.zeros(R), weights.sum(1), weights)


def test_distortion_known_values():
    """One plane: delta / 3. Two planes a distance s apart with weight 1/2 each:
    2 * (1/4) * s + (1/4 + 1/4) * delta / 3. Spreading weight over distant planes costs more."""
    D = 11
    delta = 1 / (D - 1)
    one = torch.zeros(1, D)
    one[0, 4] = 1
    assert distortion([_out(one)], D).item() == pytest.approx(delta / 3)
    two = torch.zeros(1, D)
    two[0, 2] = two[0, 7] = 0.5
    expected = 2 * 0.25 * (5 * delta) + 0.5 * delta / 3
    assert distortion([_out(two)], D).item() == pytest.approx(expected)
    near = torch.zeros(1, D)
    near[0, 4] = near[0, 5] = 0.5
    assert distortion([_out(near)], D) < distortion([_out(two)], D)


def test_distortion_matches_the_double_sum():
    g = torch.Generator().manual_seed(0)
    w = torch.rand(7, 9, generator=g)
    w = w / w.sum(1, keepdim=True) * 0.9  # covered rays (acc > 0.5)
    s = torch.arange(9) / 8
    pair = (w[:, :, None] * w[:, None, :] * (s[:, None] - s[None, :]).abs()).sum((1, 2))
    expected = (pair + (w**2).sum(1) / 8 / 3).mean()
    assert distortion([_out(w)], 9).item() == pytest.approx(expected.item(), rel=1e-5)


def _planes_for_90_percent(trainer: Trainer) -> float:
    """Mean over the input views' pixels (every MPI) of how many planes carry 90 % of the weight."""
    counts = []
    uv = pixel_centers(W, H)
    for f, fr in zip(trainer.model.fields, trainer.model.frames, strict=True):
        for j in range(len(trainer.scene)):
            with torch.no_grad():
                o = render_rays(f, fr, trainer.K[j], trainer.poses[j], uv)
            w = torch.sort(o.weights, 1, descending=True).values
            counts.append(((torch.cumsum(w, 1) < 0.9 * o.acc[:, None]).sum(1) + 1).float().mean())
    return float(torch.stack(counts).mean())


def test_distortion_prior_concentrates_opacity():
    """Trained with the prior, fewer planes carry 90 % of each ray's weight (from a foggy start:
    plane-sweep prior at a high temperature), and the depth is no worse."""
    scene = synthetic_scene(3, W, H)
    base = preset_config("fast", steps=60, rays_per_view=512, unseen_rays=256)
    base = with_settings(base, ["model.num_planes=16", "model.pyramid.stereo_temperature=0.05"])
    results = {}
    for lam in (0.0, 0.05):
        trainer = Trainer(scene, replace(base, loss=replace(base.loss, lambda_distortion=lam)))
        trainer.fit()
        out = trainer.model.render(scene.cameras.K[0], scene.cameras.world_from_cam[0], W, H)
        depth_err = float(np.median(np.abs(out.depth.numpy() - scene.depths[0]) / scene.depths[0]))
        results[lam] = (_planes_for_90_percent(trainer), depth_err)
    (planes0, err0), (planes1, err1) = results[0.0], results[0.05]
    assert planes1 < 0.7 * planes0, results
    assert err1 <= err0 + 0.01, results


def test_with_settings_parses_and_rejects():
    cfg = with_settings(
        preset_config("fast"), ["loss.lambda_ac=1", "model.num_planes=32", "model.pyramid.scales=[1,0.5]"]
    )
    assert cfg.loss.lambda_ac == 1.0 and isinstance(cfg.loss.lambda_ac, float)
    assert cfg.model.num_planes == 32 and cfg.model.pyramid.scales == (1, 0.5)
    with pytest.raises(ValueError, match="unknown setting"):
        with_settings(cfg, ["loss.lambda_nope=1"])
    with pytest.raises(ValueError, match="needs a int"):
        with_settings(cfg, ["model.num_planes=many"])
    with pytest.raises(ValueError, match="KEY=VALUE"):
        with_settings(cfg, ["steps"])


def test_tilted_layer_depth_is_the_ray_plane_intersection():
    """A wall z = 5 + 0.5 x seen by a camera at the origin looking along +z: the centre pixel's
    depth is 5, and a pixel whose ray has x/z = r meets it at z = 5 / (1 - 0.5 r)."""
    from cmc.cameras import Cameras, intrinsics
    from cmc.datasets import Layer, render_layers

    K = intrinsics(100.0, 100.0, 50.0, 40.0)
    cams = Cameras(K[None], np.eye(4)[None], 100, 80)
    _, depth = render_layers((Layer(5.0, (-1e3, 1e3, -1e3, 1e3), 1, (0.5, 0.0)),), cams, supersample=1)
    assert depth[0, 40, 50] == pytest.approx(5.0 / (1 - 0.5 * 0.5 / 100), rel=1e-5)  # pixel centre u = 50.5
    r = (90.5 - 50) / 100
    assert depth[0, 40, 90] == pytest.approx(5.0 / (1 - 0.5 * r), rel=1e-5)


def test_wide_baseline_split_cameras():
    """Halfway views sit at the midpoints of input pairs, near views 5 % of the baseline from an
    input; every camera looks at (0, 0, 4); the exact depth matches the images' cameras."""
    from cmc.datasets import WIDE_SCENES, wide_baseline_split

    split = wide_baseline_split("cards", width=64, height=48)
    assert set(WIDE_SCENES) >= {"cards", "posts", "slanted"}
    c_in, c_test = split.train.cameras.centers, split.test.cameras.centers
    for k, (i, j) in enumerate(((0, 1), (1, 2), (2, 0))):
        np.testing.assert_allclose(c_test[k], (c_in[i] + c_in[j]) / 2, atol=1e-12)
    for k in range(3):
        assert np.linalg.norm(c_test[3 + k] - c_in[k]) == pytest.approx(0.05 * 0.6)
    for cams in (split.train.cameras, split.test.cameras):
        uv, _ = cams.project(np.array([[0.0, 0.0, 4.0]]))
        np.testing.assert_allclose(uv[:, 0], np.tile([32.0, 24.0], (len(cams), 1)), atol=1e-9)
    assert split.test_kinds == ["halfway"] * 3 + ["near"] * 3
    assert split.train.near < split.train.depths.min() and split.train.far > split.train.depths.max()


def test_robust_depth_consistency_corrects_small_and_tolerates_large_disagreements():
    """On normalised disparity, log(1 + (ds / scale)^2): zero for agreeing MPIs, log 2 at one
    scale apart; its pull (gradient) on a depth peaks near one scale and falls for a disagreement
    as large as an occluder in front of a wall, where the squared loss pulls hardest."""
    from cmc.losses import depth_consistency, robust_depth_consistency

    near, far, scale = 1.0, 10.0, 0.05

    def depth_at(s: float) -> float:  # normalised disparity -> depth
        return 1.0 / (s * (1 / near - 1 / far) + 1 / far)

    def pull(loss, s_b: float) -> float:
        a = torch.tensor([depth_at(0.5)], requires_grad=True)
        b = torch.tensor([depth_at(s_b)])
        out = lambda z: RayOutput(torch.zeros(1, 3), z, torch.ones(1))  # noqa: E731
        value = loss([out(a), out(b)])
        value.backward()
        return abs(a.grad.item()), value.item()

    robust = lambda o: robust_depth_consistency(o, near, far, scale)  # noqa: E731
    squared = lambda o: depth_consistency(o, far - near)  # noqa: E731
    assert pull(robust, 0.5)[1] == pytest.approx(0.0, abs=1e-6)
    assert pull(robust, 0.5 + scale)[1] == pytest.approx(np.log(2), rel=1e-3)
    small, large = pull(robust, 0.5 + scale)[0], pull(robust, 0.5 + 8 * scale)[0]
    assert large < 0.5 * small, (small, large)
    assert pull(squared, 0.5 + 8 * scale)[0] > pull(squared, 0.5 + scale)[0]
