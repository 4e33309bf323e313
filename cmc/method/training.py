"""Training loop: losses per step, progress hooks, cooperative cancellation, exact resume.

Randomness of step ``s`` (ray choice, unseen pose) depends on ``(seed, s)`` alone (generators
seeded with them, or with the seed and the pixel order's number that step ``s`` reads), so a run
resumed from a checkpoint at step s makes exactly the draws an uninterrupted run makes: resuming
reproduces the uninterrupted result to float tolerance.

Unseen poses (for L_ac, L_dc): a random convex combination of the input camera centres plus
Gaussian jitter (``unseen_jitter`` mean baselines), with the same weighted mean of the input
rotations (:func:`cmc.geometry.planes.sample_virtual_pose`), intrinsics of input view 0; rays are
uniform random pixels of that camera.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from cmc.config import LossConfig, TrainConfig
from cmc.data.datasets import Scene, validate_scene
from cmc.errors import CheckpointError, ConfigError
from cmc.geometry.planes import sample_virtual_pose
from cmc.method.eta import TrainingETA, checkpoints_to_come
from cmc.method.losses import (
    alpha_entropy,
    appearance_consistency,
    depth_consistency,
    distortion,
    reconstruction_loss,
    robust_depth_consistency,
)
from cmc.method.model import CMCModel
from cmc.mpi.rendering import render_ray_groups

# 2: texture shapes follow the pixel-aligned plane extent (cmc.mpi.rendering.pixel_aligned_margin)
# 3: the pyramid field's colour and alpha levels are separate parameters (cmc.mpi.fields)
CHECKPOINT_VERSION = 3


class TrainingCancelled(Exception):
    """Raised by :meth:`Trainer.fit` when ``should_stop`` returned True (after checkpointing)."""


@dataclass
class Progress:
    """Reported to the progress hook after every step.

    Attributes: step (completed steps), total, losses (name -> value of the last step),
    elapsed_s (this process's training seconds), eta_s (estimated seconds left in training, each
    loss phase at its own step time: :class:`cmc.method.eta.TrainingETA`; once a checkpoint was
    written, with the writes to come at its time: :func:`cmc.method.eta.checkpoints_to_come`).
    """

    step: int
    total: int
    losses: dict[str, float]
    elapsed_s: float
    eta_s: float


@dataclass
class TrainResult:
    model: CMCModel
    steps: int
    seconds: float
    history: list[dict[str, float]] = field(default_factory=list)
    checkpoint_write_s: float | None = None  # the last checkpoint write's seconds (None: none written)
    # each loss phase's mean step time (reconstruction-only, full; TrainingETA.phase_means)
    phase_step_s: tuple[float | None, float | None] = (None, None)


def lr_at(cfg: TrainConfig, step: int) -> float:
    """Exponential decay from ``cfg.lr`` at step 0 to ``cfg.lr_final`` at the last step."""
    t = step / max(cfg.steps - 1, 1)
    return cfg.lr * (cfg.lr_final / cfg.lr) ** t


def alpha_entropy_weight(cfg: TrainConfig, step: int) -> float:
    """The alpha entropy prior's weight at ``step``: ``loss.lambda_alpha_entropy`` times the factor
    of ``loss.alpha_entropy_schedule`` for the share of the steps (equal shares, in order) that
    holds ``step``."""
    schedule = cfg.loss.alpha_entropy_schedule
    return cfg.loss.lambda_alpha_entropy * schedule[min(step * len(schedule) // cfg.steps, len(schedule) - 1)]


# Configuration fields that change when checkpoints are written, not what is trained.
_NOT_IN_RESUME_KEY = ("checkpoint_every",)


def _resume_key(config: dict[str, Any]) -> dict[str, Any]:
    """The part of a ``TrainConfig.to_dict()`` a checkpoint must match to be resumed."""
    return {k: v for k, v in config.items() if k not in _NOT_IN_RESUME_KEY}


@dataclass(frozen=True)
class LossTerms:
    """The loss terms of one training step, each an unweighted scalar tensor, and ``total``,
    their sum weighted by :class:`cmc.config.LossConfig` (a term whose weight is 0 is 0)."""

    mse: torch.Tensor  # reconstruction of every input by every MPI (paper Eq. 4.5)
    dc_input: torch.Tensor  # depth consistency between MPIs at the input views
    ac: torch.Tensor  # appearance consistency between MPIs at unseen poses (Eq. 4.6)
    dc: torch.Tensor  # depth consistency between MPIs at unseen poses (Eq. 4.7)
    distortion: torch.Tensor  # concentration of each ray's opacity
    alpha_entropy: torch.Tensor  # visible alpha pushed to 0 or 1
    total: torch.Tensor

    @staticmethod
    def weighted(
        lc: LossConfig,
        mse: torch.Tensor,
        dc_input: torch.Tensor,
        ac: torch.Tensor,
        dc: torch.Tensor,
        distortion: torch.Tensor,
        alpha_entropy: torch.Tensor,
    ) -> LossTerms:
        """The terms and their sum weighted by ``lc``."""
        total = (
            mse
            + lc.lambda_dc_input * dc_input
            + lc.lambda_ac * ac
            + lc.lambda_dc * dc
            + lc.lambda_distortion * distortion
            + lc.lambda_alpha_entropy * alpha_entropy
        )
        return LossTerms(mse, dc_input, ac, dc, distortion, alpha_entropy, total)

    def floats(self) -> dict[str, float]:
        """Every term as a float, by name (``total`` included)."""
        return {f.name: float(getattr(self, f.name).detach()) for f in fields(self)}


class Trainer:
    """Trains a :class:`CMCModel` on a scene's input views.

    Args:
        scene: the N >= 2 input views.
        cfg: training configuration.
        device: torch device ("cpu", "cuda").
    """

    def __init__(
        self,
        scene: Scene,
        cfg: TrainConfig,
        device: str | torch.device = "cpu",
        on_build_progress: Callable[[float], None] | None = None,
    ):
        """``on_build_progress``: the model build's share done as it goes (:class:`CMCModel`)."""
        validate_scene(scene, min_views=2)
        schedule = cfg.loss.alpha_entropy_schedule
        if not schedule or min(schedule) < 0:
            raise ConfigError(f"loss.alpha_entropy_schedule needs one or more factors >= 0, got {list(schedule)}")
        self.scene, self.cfg = scene, cfg
        self.device = torch.device(device)
        torch.manual_seed(cfg.seed)
        self.model = CMCModel(scene, cfg.model, self.device, on_build_progress)
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=cfg.lr, fused=True)
        self.images = torch.as_tensor(scene.images, device=self.device).reshape(len(scene), -1, 3)
        self.K = torch.as_tensor(scene.cameras.K, dtype=torch.float32, device=self.device)
        self.poses = torch.as_tensor(scene.cameras.world_from_cam, dtype=torch.float32, device=self.device)
        self.depth_scale = self.model.far - self.model.near
        self.step = 0
        self._orders: dict[tuple[int, int], torch.Tensor] = {}

    # -- one step ---------------------------------------------------------------------------

    def _random_pixels(self, gen: torch.Generator, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        """n random pixel indices, in row-major order, and their centre coordinates [n, 2].

        In order, neighbouring rays sample neighbouring texels: the textures' samples and their
        gradients stay in the CPU's caches (cmc.mpi.plane_sampling samples about twice as fast so,
        in a one-off timing on fern's finest level)."""
        w, h = self.scene.cameras.width, self.scene.cameras.height
        return self._in_row_major_order(torch.randint(0, w * h, (n,), generator=gen))

    def _in_row_major_order(self, idx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Pixel indices ``idx`` sorted (row-major order) on the device, and their centre coordinates."""
        w = self.scene.cameras.width
        idx = idx.sort().values.to(self.device)
        return idx, torch.stack([idx % w, idx // w], -1).float() + 0.5

    def _input_pixels(self, gen: torch.Generator, view: int, step: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The pixels input view ``view`` draws at step ``step`` (``cfg.ray_sampling``), as
        :meth:`_random_pixels` returns them."""
        n = self.cfg.rays_per_view
        if self.cfg.ray_sampling == "uniform":
            return self._random_pixels(gen, n)
        # Draws step * n ... step * n + n - 1 of the orders laid end to end (w * h draws each): the
        # part of each order the slice covers, crossing into the next at the end of one.
        size, start = self.scene.cameras.width * self.scene.cameras.height, step * n
        parts = [
            self._pixel_order(view, e)[max(start - e * size, 0) : min(start + n - e * size, size)]
            for e in range(start // size, (start + n - 1) // size + 1)
        ]
        return self._in_row_major_order(torch.cat(parts))

    def _pixel_order(self, view: int, epoch: int) -> torch.Tensor:
        """A random order of input view ``view``'s pixels, the ``epoch``-th (seeded by the run's
        seed, the view and the epoch alone)."""
        key = (view, epoch)
        if key not in self._orders:
            gen = torch.Generator().manual_seed((self.cfg.seed * 1_000_003 + view) * 1_000_003 + epoch)
            self._orders = {k: v for k, v in self._orders.items() if k[1] >= epoch - 1}
            self._orders[key] = torch.randperm(self.scene.cameras.width * self.scene.cameras.height, generator=gen)
        return self._orders[key]

    def _colour_grads(self, mpi: int) -> list[float]:
        """Factor on the colour gradients of MPI ``mpi`` from each input view's rays."""
        s = self.cfg.loss.cross_view_colour
        return [1.0 if j == mpi else s for j in range(len(self.scene))]

    def compute_losses(self, step: int) -> LossTerms:
        """All loss terms of step ``step`` (unweighted) and their weighted sum ``total``."""
        cfg, lc = self.cfg, self.cfg.loss
        gen = torch.Generator().manual_seed(cfg.seed * 1_000_003 + step)
        rng = np.random.default_rng([cfg.seed, step])
        fields, frames = list(self.model.fields), self.model.frames
        full = step >= lc.recon_only_fraction * cfg.steps
        # Target cameras of this step: every input view, then the unseen poses. MPI i renders
        # every ray drawn from its own photo and the share cfg.cross_view_rays of each other
        # photo's: shared[j] indexes that share of view j's rays, evenly spread over the batch.
        groups, targets, shared = [], [], []
        for j in range(len(self.scene)):
            idx, uv = self._input_pixels(gen, j, step)
            m = max(1, round(cfg.cross_view_rays * len(idx)))
            shared.append(torch.arange(m, device=self.device) * len(idx) // m)
            groups.append((self.K[j], self.poses[j], uv))
            targets.append(self.images[j][idx])
        n = len(self.scene)
        use_unseen = full and (lc.lambda_ac > 0 or lc.lambda_dc > 0)
        for _ in range(cfg.unseen_poses if use_unseen else 0):
            pose = sample_virtual_pose(self.scene.cameras.world_from_cam, rng, cfg.unseen_jitter)
            P = torch.as_tensor(pose, dtype=torch.float32, device=self.device)
            groups.append((self.K[0], P, self._random_pixels(gen, cfg.unseen_rays)[1]))

        def rays_of_mpi(i: int) -> list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
            return [(K, P, uv if t == i or t >= n else uv[shared[t]]) for t, (K, P, uv) in enumerate(groups)]

        # per_mpi[i][t]: MPI i's render of target t (one field query per MPI). The unseen poses'
        # colours serve L_ac alone: without it no gradient flows through them.
        unseen_grad = [1.0 if lc.lambda_ac > 0 else 0.0] * (len(groups) - n)
        per_mpi = [
            render_ray_groups(f, fr, rays_of_mpi(i), self._colour_grads(i) + unseen_grad, cfg.colour_grad_min_weight)
            for i, (f, fr) in enumerate(zip(fields, frames, strict=True))
        ]
        by_target = list(zip(*per_mpi, strict=True))
        zero = torch.zeros((), device=self.device)
        exposure = self.model.exposure
        if exposure is not None:
            # MPI i's colours in photo j's response before they meet photo j; at an unseen pose
            # every MPI's in the mean response, so that L_ac compares one response with itself.
            for t in range(len(by_target)):
                dst = t if t < n else None
                by_target[t] = [replace(o, rgb=exposure.convert(o.rgb, i, dst)) for i, o in enumerate(by_target[t])]
        # Every MPI against the pixels of photo j it rendered; the MPIs' depths compared on the
        # rays of photo j that all of them rendered.
        shared_targets = [targets[j][shared[j]] for j in range(n)]
        mse = torch.stack(
            [
                reconstruction_loss([o], targets[j] if i == j else shared_targets[j])
                for j in range(n)
                for i, o in enumerate(by_target[j])
            ]
        ).mean()
        at_shared = [[o.select(shared[j]) if i == j else o for i, o in enumerate(by_target[j])] for j in range(n)]
        if lc.depth_consistency == "cauchy":
            scale = 1.0 / (self.model.cfg.num_planes - 1)
            dc_loss = lambda o: robust_depth_consistency(o, self.model.near, self.model.far, scale)  # noqa: E731
        else:
            dc_loss = lambda o: depth_consistency(o, self.depth_scale)  # noqa: E731
        unseen = by_target[n:]
        every_out = [o for outs in by_target for o in outs]  # every MPI's render of every target
        entropy_weight = alpha_entropy_weight(cfg, step)
        return LossTerms.weighted(
            replace(lc, lambda_alpha_entropy=entropy_weight),
            mse=mse,
            dc_input=torch.stack([dc_loss(at_shared[j]) for j in range(n)]).mean()
            if full and lc.lambda_dc_input > 0
            else zero,
            ac=torch.stack([appearance_consistency(o) for o in unseen]).mean() if unseen and lc.lambda_ac > 0 else zero,
            dc=torch.stack([dc_loss(o) for o in unseen]).mean() if unseen else zero,
            distortion=distortion(every_out, self.model.cfg.num_planes) if lc.lambda_distortion > 0 else zero,
            alpha_entropy=alpha_entropy(every_out) if entropy_weight > 0 else zero,
        )

    def train_step(self) -> dict[str, float]:
        for g in self.optimizer.param_groups:
            g["lr"] = lr_at(self.cfg, self.step)
        self.optimizer.zero_grad(set_to_none=True)
        losses = self.compute_losses(self.step)
        if not torch.isfinite(losses.total):
            raise FloatingPointError(f"loss became {losses.total.item()} at step {self.step}")
        losses.total.backward()
        self.optimizer.step()
        self.step += 1
        return losses.floats()

    # -- checkpoints --------------------------------------------------------------------------
    # A checkpoint resumes under any configuration that trains the same run: how often it is
    # written (checkpoint_every) does not count.

    def state_dict(self) -> dict:
        return {
            "version": CHECKPOINT_VERSION,
            "step": self.step,
            "config": self.cfg.to_dict(),
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
        }

    def save_checkpoint(self, path: str | Path) -> None:
        """Write atomically (temporary file, then rename), so a crash never leaves a torn file."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(path.suffix + ".tmp")
        torch.save(self.state_dict(), tmp)
        os.replace(tmp, path)

    def load_checkpoint(self, path: str | Path) -> None:
        ckpt = torch.load(path, map_location=self.device, weights_only=False)
        if ckpt.get("version") != CHECKPOINT_VERSION:
            raise CheckpointError(f"checkpoint {path} has version {ckpt.get('version')}, expected {CHECKPOINT_VERSION}")
        if _resume_key(ckpt["config"]) != _resume_key(self.cfg.to_dict()):
            raise CheckpointError(f"checkpoint {path} was written with a different training configuration")
        self.model.load_state_dict(ckpt["model"])
        self.optimizer.load_state_dict(ckpt["optimizer"])
        self.step = int(ckpt["step"])

    # -- loop ---------------------------------------------------------------------------------

    def fit(
        self,
        on_progress: Callable[[Progress], None] | None = None,
        should_stop: Callable[[], bool] | None = None,
        checkpoint_path: str | Path | None = None,
        resume: bool = True,
        checkpoint_seconds: float | None = 60.0,
        on_checkpoint: Callable[[Path], None] | None = None,
        checkpoint_write_s: float | None = None,
        full_cost_ratio: float | None = None,
    ) -> TrainResult:
        """Train to ``cfg.steps``.

        With ``checkpoint_path``: resume from it when it exists (and ``resume``), write it every
        ``cfg.checkpoint_every`` steps and after the first step that ends ``checkpoint_seconds``
        or more after the last checkpoint (or the start), at the end, and before raising
        TrainingCancelled. The time bound is what a process killed without warning (a container
        stopped past its grace period, a lost machine) loses; it is not part of the
        configuration, so changing it keeps checkpoints usable. ``on_checkpoint(path)`` is
        called after each write (to copy it elsewhere; it may move the file away).
        ``Progress.eta_s`` counts the writes still to come at the last write's seconds, and before
        this run has written one at ``checkpoint_write_s`` (an earlier run's; None: not at all),
        and until a full-loss step has run, those steps at ``full_cost_ratio`` times the
        reconstruction-only ones (an earlier run's measured ratio; None: the cost model of
        :func:`cmc.method.eta.full_cost_ratio`).
        """
        if checkpoint_path is not None and resume and Path(checkpoint_path).exists():
            self.load_checkpoint(checkpoint_path)
        t0 = t_last = t_saved = time.perf_counter()
        eta = TrainingETA.for_config(self.cfg, len(self.scene), full_cost_ratio)
        history = []

        save_s = checkpoint_write_s  # a checkpoint write's seconds: those to come take as long
        written_s: float | None = None  # this run's last write's seconds

        def save() -> None:
            nonlocal save_s, written_s
            assert checkpoint_path is not None
            started = time.perf_counter()
            self.save_checkpoint(checkpoint_path)
            if on_checkpoint is not None:
                on_checkpoint(Path(checkpoint_path))
            save_s = written_s = time.perf_counter() - started

        while self.step < self.cfg.steps:
            if should_stop is not None and should_stop():
                if checkpoint_path is not None:
                    save()
                raise TrainingCancelled(f"cancelled at step {self.step}")
            losses = self.train_step()
            history.append(losses)
            now = time.perf_counter()
            due = checkpoint_seconds is not None and now - t_saved >= checkpoint_seconds
            if checkpoint_path is not None and (self.step % self.cfg.checkpoint_every == 0 or due):
                save()
                t_saved = now
            eta.record(self.step - 1, now - t_last)
            t_last = now
            if on_progress is not None:
                remaining = eta.remaining_s(self.step)
                assert remaining is not None  # a step was just measured
                if save_s is not None and checkpoint_path is not None:  # and the writes to come, each as long
                    steps_left = self.cfg.steps - self.step
                    writes = checkpoints_to_come(
                        self.step,
                        self.cfg.steps,
                        self.cfg.checkpoint_every,
                        remaining / steps_left if steps_left else 0.0,
                        checkpoint_seconds,
                        now - t_saved,
                    )
                    remaining += writes * save_s
                on_progress(Progress(self.step, self.cfg.steps, losses, now - t0, remaining))
                t_last = time.perf_counter()  # what the callback did (a preview bake) is no step's time
        if checkpoint_path is not None:
            save()
        seconds = time.perf_counter() - t0
        seconds = seconds if math.isfinite(seconds) else 0.0
        return TrainResult(self.model, self.step, seconds, history, written_s, eta.phase_means())


def load_model(checkpoint_path: str | Path, scene: Scene, device: str | torch.device = "cpu") -> CMCModel:
    """Rebuild a trained model from a checkpoint and the scene it was trained on."""
    ckpt = torch.load(checkpoint_path, map_location=device, weights_only=False)
    cfg = TrainConfig.from_dict(ckpt["config"])
    model = CMCModel(scene, cfg.model, device)
    model.load_state_dict(ckpt["model"])
    return model
