"""Training on a tiny synthetic scene: it learns, resumes exactly, cancels cleanly, rejects bad input."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from cmc.config import TrainConfig, preset_config
from cmc.data.datasets import DEFAULT_LAYERS, SceneError, render_layers, synthetic_cameras, synthetic_scene
from cmc.errors import ConfigError
from cmc.eval.metrics import psnr
from cmc.method import training
from cmc.method.training import Trainer, TrainingCancelled, load_model, lr_at

W, H = 64, 48


@pytest.fixture(scope="module")
def scene():
    return synthetic_scene(num_views=3, width=W, height=H)


def tiny(preset: str = "fast", **kw) -> TrainConfig:
    base = dict(steps=8, rays_per_view=256, unseen_rays=256, checkpoint_every=3)
    base.update(kw)
    cfg = preset_config(preset, **base)
    if preset == "paper":
        cfg = replace(cfg, model=replace(cfg.model, num_planes=8, mlp=replace(cfg.model.mlp, width=32, depth=2)))
    else:
        cfg = replace(cfg, model=replace(cfg.model, num_planes=12))
    return cfg


def test_fast_preset_learns_geometry_and_beats_nearest_view(scene):
    """After a short run, a held-out view between inputs 0 and 1 is closer to the ground truth
    than the nearest input photo, and the rendered depth is near the true depth."""
    cfg = tiny(steps=120, rays_per_view=1024, unseen_rays=1024)
    trainer = Trainer(scene, cfg)
    trainer.fit()
    novel = synthetic_cameras(5, W, H)[1:2]
    gt, gt_depth = render_layers(DEFAULT_LAYERS, novel)
    out = trainer.model.render(novel.K[0], novel.world_from_cam[0], W, H)
    ours = psnr(out.rgb.numpy(), gt[0])
    nearest = max(psnr(scene.images[i], gt[0]) for i in range(2))
    assert ours > nearest + 3, (ours, nearest)
    rel = np.abs(out.depth.numpy() - gt_depth[0]) / gt_depth[0]
    assert np.median(rel) < 0.15, np.median(rel)


def test_losses_fall(scene):
    trainer = Trainer(scene, tiny(steps=30, rays_per_view=512))
    hist = trainer.fit().history
    assert np.mean([h["mse"] for h in hist[-5:]]) < 0.7 * np.mean([h["mse"] for h in hist[:5]])


@pytest.mark.parametrize("preset", ["fast", "paper"])
def test_resume_from_checkpoint_is_exact(scene, tmp_path, preset):
    """Stopping at step 5 and resuming in a fresh trainer gives the same weights as 8 straight steps."""
    cfg = tiny(preset)
    straight = Trainer(scene, cfg)
    straight.fit()
    ckpt = tmp_path / "ckpt.pt"
    first = Trainer(scene, cfg)
    with pytest.raises(TrainingCancelled):
        first.fit(should_stop=lambda: first.step >= 5, checkpoint_path=ckpt)
    assert ckpt.exists()
    second = Trainer(scene, cfg)
    second.fit(checkpoint_path=ckpt)
    assert second.step == cfg.steps
    for a, b in zip(straight.model.state_dict().values(), second.model.state_dict().values(), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    reloaded = load_model(ckpt, scene)
    for a, b in zip(second.model.state_dict().values(), reloaded.state_dict().values(), strict=True):
        torch.testing.assert_close(a, b)


@pytest.mark.parametrize("seconds, saved_at", [(0.0, [1, 2, 3, 4, 5, 6]), (3600.0, [])])
def test_checkpoints_on_time_as_well_as_on_steps(scene, tmp_path, seconds, saved_at):
    """A checkpoint is also written after the first step that ends ``checkpoint_seconds`` after
    the last one, however far the step period (a process killed without warning loses at most
    that much training); the time bound does not change the configuration the checkpoint holds."""
    ckpt = tmp_path / "ckpt.pt"
    seen = []

    def on_progress(p):
        if ckpt.exists():
            seen.append(torch.load(ckpt, weights_only=False)["step"])
            ckpt.unlink()

    cfg = tiny(steps=6, checkpoint_every=1000)
    Trainer(scene, cfg).fit(on_progress=on_progress, checkpoint_path=ckpt, checkpoint_seconds=seconds)
    assert seen == saved_at
    assert torch.load(ckpt, weights_only=False)["step"] == 6  # and at the end
    Trainer(scene, cfg).load_checkpoint(ckpt)


def test_same_seed_same_result_other_seed_differs(scene):
    a, b, c = (Trainer(scene, tiny(steps=3, seed=s)) for s in (1, 1, 2))
    for t in (a, b, c):
        t.fit()
    pa, pb, pc = (next(t.model.fields[0].parameters()) for t in (a, b, c))
    torch.testing.assert_close(pa, pb)
    assert not torch.allclose(pa, pc)


def test_model_build_reports_its_progress(scene):
    """The build's share done: after the sweeps placing the planes, then after each MPI's."""
    from cmc.method.model import PLACING_SHARE

    shares = []
    Trainer(scene, tiny(steps=4), on_build_progress=shares.append)
    rest = 1 - PLACING_SHARE
    assert shares == pytest.approx([PLACING_SHARE, PLACING_SHARE + rest / 3, PLACING_SHARE + 2 * rest / 3, 1.0])


def test_progress_reports_every_step_with_eta(scene):
    seen = []
    Trainer(scene, tiny(steps=4)).fit(on_progress=seen.append)
    assert [p.step for p in seen] == [1, 2, 3, 4]
    assert all(p.total == 4 and p.eta_s >= 0 and "mse" in p.losses for p in seen)
    assert seen[-1].eta_s == 0


def test_consistency_terms_only_after_warmup(scene):
    cfg = tiny(steps=10)  # recon_only_fraction 0.3 -> steps 0..2 use L_MSE only
    cfg = replace(cfg, loss=replace(cfg.loss, lambda_ac=0.5))
    t = Trainer(scene, cfg)
    assert t.compute_losses(2).ac.item() == 0.0
    late = t.compute_losses(3)
    assert late.ac.item() > 0 and late.dc.item() > 0 and late.dc_input.item() > 0


def test_without_appearance_consistency_no_gradient_flows_through_the_unseen_colours(scene):
    """With lambda_ac = 0 (``fast``) the unseen poses' colours serve nothing: L_ac is 0 and not
    computed, and every other term and every gradient is what it is with L_ac computed and
    weighted by almost 0."""
    cfg = tiny(steps=10)
    assert cfg.loss.lambda_ac == 0 and cfg.unseen_poses == 1
    t = Trainer(scene, cfg)

    def losses_and_grads(lambda_ac: float):
        t.cfg = replace(cfg, loss=replace(cfg.loss, lambda_ac=lambda_ac))
        t.optimizer.zero_grad(set_to_none=True)
        losses = t.compute_losses(5)
        losses.total.backward()
        return losses, [p.grad.clone() for p in t.model.parameters()]

    fast, fast_grads = losses_and_grads(0.0)
    slow, slow_grads = losses_and_grads(1e-30)
    assert fast.ac.item() == 0.0 and slow.ac.item() > 0
    for name in ("mse", "dc_input", "dc", "distortion", "alpha_entropy"):
        assert getattr(fast, name).item() == pytest.approx(getattr(slow, name).item(), rel=1e-6), name
    for a, b in zip(fast_grads, slow_grads, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-9)


def test_checkpoint_from_other_config_is_refused(scene, tmp_path):
    ckpt = tmp_path / "c.pt"
    Trainer(scene, tiny(steps=2)).fit(checkpoint_path=ckpt)
    with pytest.raises(ValueError, match="different training configuration"):
        Trainer(scene, tiny(steps=3)).fit(checkpoint_path=ckpt)


def test_lr_schedule_endpoints():
    cfg = preset_config("paper", steps=100)
    assert lr_at(cfg, 0) == pytest.approx(5e-3)
    assert lr_at(cfg, 99) == pytest.approx(1e-4)


def test_alpha_entropy_weight_follows_its_schedule(scene):
    """The prior's weight is the schedule's factor for the share of the steps a step lies in, and
    the step's total loss weighs the prior by it; a schedule without factors is refused."""
    cfg = tiny(steps=8)
    cfg = replace(cfg, loss=replace(cfg.loss, lambda_alpha_entropy=0.004, alpha_entropy_schedule=(0.5, 1.5)))
    assert [training.alpha_entropy_weight(cfg, s) for s in (0, 3, 4, 7)] == pytest.approx([0.002, 0.002, 0.006, 0.006])
    three = replace(cfg, steps=300, loss=replace(cfg.loss, alpha_entropy_schedule=(0.0, 1.0, 2.0)))
    assert [training.alpha_entropy_weight(three, s) for s in (99, 100, 199, 200, 299)] == pytest.approx(
        [0.0, 0.004, 0.004, 0.008, 0.008]
    )
    trainer = Trainer(scene, cfg)
    lc = cfg.loss
    for step, weight in ((0, 0.002), (7, 0.006)):
        t = trainer.compute_losses(step)
        assert t.alpha_entropy.item() > 0
        rest = t.mse + lc.lambda_dc_input * t.dc_input + lc.lambda_ac * t.ac + lc.lambda_dc * t.dc
        rest = rest + lc.lambda_distortion * t.distortion
        assert t.total.item() == pytest.approx((rest + weight * t.alpha_entropy).item(), rel=1e-6)
    with pytest.raises(ConfigError, match="alpha_entropy_schedule"):
        Trainer(scene, replace(cfg, loss=replace(cfg.loss, alpha_entropy_schedule=())))


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda s: s.subset([0]), "at least 2 views"),
        (lambda s: setattr(s, "near_far", np.tile([5.0, 2.0], (3, 1))) or s, "near < far"),
    ],
)
def test_bad_scenes_are_refused(scene, mutate, message):
    s = synthetic_scene(num_views=3, width=16, height=12)
    with pytest.raises(SceneError, match=message):
        Trainer(mutate(s), tiny())


def test_unknown_preset():
    with pytest.raises(ValueError, match="unknown preset"):
        preset_config("turbo")


def test_config_round_trip():
    for name in ("fast", "paper"):
        cfg = preset_config(name)
        assert TrainConfig.from_dict(cfg.to_dict()) == cfg


def test_checkpoint_cadence_is_not_part_of_the_resume_check(scene, tmp_path):
    """Changing only checkpoint_every resumes the checkpoint instead of starting over from step 0."""
    ckpt = tmp_path / "c.pt"
    cfg = tiny(steps=6)
    first = Trainer(scene, cfg)
    with pytest.raises(TrainingCancelled):
        first.fit(should_stop=lambda: first.step >= 3, checkpoint_path=ckpt)
    second = Trainer(scene, replace(cfg, checkpoint_every=cfg.checkpoint_every + 7))
    second.load_checkpoint(ckpt)
    assert second.step == 3
    with pytest.raises(ValueError, match="different training configuration"):
        Trainer(scene, replace(cfg, lr=cfg.lr * 2)).load_checkpoint(ckpt)


def test_faint_samples_pass_no_gradient_to_their_colours(scene):
    """colour_grad_min_weight reaches the renders of a training step: with it above every
    sample's weight, one step leaves every colour texel (base and colour levels) as it was and
    still moves alpha; at 0 the colours move too."""

    def changed(cfg: TrainConfig) -> tuple[bool, bool]:
        torch.manual_seed(0)
        trainer = Trainer(scene, cfg)
        field = trainer.model.fields[0]
        colours, alphas = [field.base, *field.colour_levels], list(field.alpha_levels)
        before = [[p.detach().clone() for p in ps] for ps in (colours, alphas)]
        trainer.train_step()
        return tuple(  # type: ignore[return-value]
            any(not torch.equal(p, b) for p, b in zip(ps, bs, strict=True))
            for ps, bs in zip((colours, alphas), before, strict=True)
        )

    assert changed(tiny(colour_grad_min_weight=1.5)) == (False, True)
    assert changed(tiny(colour_grad_min_weight=0.0)) == (True, True)


@pytest.mark.parametrize("rays", [256, 1000])
def test_permutation_sampling_draws_every_pixel_once_before_any_twice(scene, rays):
    """``ray_sampling="permutation"``: the draws of successive steps are slices of a random order
    of a photo's W * H pixels, then of the next order (256 rays: 12 steps per order; 1000 rays: a
    step's slice crosses from one order into the next); each view has its own orders, and a fresh
    trainer draws the same pixels at the same step (an exact resume)."""
    cfg = tiny(rays_per_view=rays)
    assert cfg.ray_sampling == "permutation"  # the fast preset's
    trainer, fresh = Trainer(scene, cfg), Trainer(scene, cfg)
    gen = torch.Generator()
    steps = 2 * W * H // rays
    draws = [trainer._input_pixels(gen, 0, s)[0] for s in range(steps)]
    counts = torch.bincount(torch.cat(draws), minlength=W * H)
    first_order = torch.bincount(torch.cat(draws[: W * H // rays]), minlength=W * H)
    assert first_order.max() == 1 and counts.min() >= 1 and counts.max() <= 2
    assert all(bool((d.diff() >= 0).all()) and len(d) == rays for d in draws)  # row-major order
    assert torch.equal(fresh._input_pixels(gen, 0, steps - 1)[0], draws[-1])
    assert not torch.equal(trainer._input_pixels(gen, 1, 0)[0], draws[0])
    idx, uv = draws[0], trainer._input_pixels(gen, 0, 0)[1]
    assert torch.equal(uv, torch.stack([idx % W, idx // W], -1).float() + 0.5)


@pytest.mark.parametrize("share", [1.0, 0.5])
def test_the_other_views_mpis_render_a_share_of_each_views_rays(scene, monkeypatch, share):
    """``cross_view_rays``: MPI i renders every ray drawn from its own photo and, of each other
    photo's rays, the share asked for, evenly spread over the batch (every other ray at 0.5) and
    the same rays in every other MPI; the losses stay finite and the consistency terms run."""
    calls = []
    real = training.render_ray_groups
    monkeypatch.setattr(
        training,
        "render_ray_groups",
        lambda f, fr, groups, *a: calls.append([g[2] for g in groups]) or real(f, fr, groups, *a),
    )
    trainer = Trainer(scene, tiny(rays_per_view=256, cross_view_rays=share))
    losses = trainer.compute_losses(trainer.cfg.steps - 1)
    assert len(calls) == 3 and all(len(uvs) == 4 for uvs in calls)  # three input views, one unseen pose
    for i, uvs in enumerate(calls):
        for j in range(3):
            own = calls[j][j]
            assert len(own) == 256
            assert torch.equal(uvs[j], own if i == j else own[:: round(1 / share)])
        assert torch.equal(uvs[3], calls[0][3])
    assert all(np.isfinite(v) for v in losses.floats().values()) and losses.dc_input > 0
