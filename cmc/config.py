"""Configuration dataclasses and the named presets ``paper`` and ``fast``.

``TrainConfig.steps`` scales every schedule (the reconstruction-only warm-up and the learning
rate decay are fractions of it), so a preset can be run short for tests without other edits.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, fields, is_dataclass, replace
from typing import Any, Literal, get_type_hints

from cmc.errors import ConfigError

Preset = Literal["fast", "paper"]
PRESETS: tuple[Preset, ...] = ("fast", "paper")


@dataclass
class MLPFieldConfig:
    """The paper's MLP (Sec. 5.1)."""

    width: int = 256  # hidden units per layer
    depth: int = 6  # hidden layers
    pe_freqs: int = 10  # positional-encoding frequencies L for the point
    leaky_slope: float = 0.01


@dataclass
class PyramidFieldConfig:
    """Explicit multi-resolution plane textures and how the plane sweep starts them (defaults:
    the ``fast`` preset's)."""

    scales: tuple[float, ...] = (0.5, 0.25, 0.125, 0.0625)  # per-plane alpha levels
    # Per-plane colour residual levels, added to the base colour of the plane's group.
    colour_scales: tuple[float, ...] = (0.25, 0.125, 0.0625)
    base_groups: int = 8  # base colours: one per group of adjacent planes (CMCModel: at most one per plane)
    # How rays sample the base colours: "bilinear", or "bicubic" (a sharper reconstruction: a
    # texture seen at another sub-texel phase than it was fitted at keeps its detail; the bake
    # records it and the renderers sample the baked colour the same way, see cmc.serving.baking).
    base_interpolation: Literal["bilinear", "bicubic"] = "bicubic"
    init_from_sweep: bool = True  # start alpha from the plane sweep (cmc.method.planesweep, ModelConfig.sweep)
    # True: the base colours of the groups behind each texel's visible surface (the sweep's most
    # probable plane) start as the background continued from nearby (cmc.method.model.hidden_layer_colours);
    # False: every group starts as the reference photo.
    hidden_colour_everywhere: bool = True
    # > 0: while training, each group's colour also changes with the angle between a ray and the
    # reference camera's ray through the same point, by a texture at this scale of the plane
    # extent, held off where the photo is textured (cmc.mpi.fields.ViewColour: the other photos'
    # reflections on smooth surfaces do not bend the geometry); bakes hold the reference
    # camera's colours. 0: colour is the same from every direction.
    view_colour_scale: float = 0.125


@dataclass
class SweepConfig:
    """How the plane sweep (:func:`cmc.method.planesweep.plane_sweep_weights`) scores the planes
    (defaults: the ``fast`` preset's)."""

    # Softmin temperature on the cost, in its units (lower: more confident).
    temperature: float = 0.3
    window: int = 5  # side of the texel window the cost is averaged over
    # The photo-consistency measure: "ad" (mean absolute colour difference) or "ad_census"
    # (that plus a census term, both saturated).
    cost: Literal["ad", "ad_census"] = "ad_census"
    edge_sigma: float = 0.1  # > 0: edge-aware window weights, in colour units; 0: uniform window
    occlusion_aware: bool = True  # the best-matching other view's cost, not the mean over views
    extend_border: bool = True  # the margin takes the geometry of the image's border
    # (P1, P2) of semi-global aggregation of the cost (cmc.method.planesweep.semi_global), in cost
    # units; P2 = 0: off.
    smoothness: tuple[float, float] = (0.2, 2.0)
    # The sweep runs on a grid this many times finer than alpha's finest level, while that grid
    # holds at most max_texels texels (cmc.method.planesweep.affordable_supersample).
    supersample: int = 2
    max_texels: int = 2**19


@dataclass
class ModelConfig:
    """The per-view MPIs (defaults: the ``fast`` preset's)."""

    field_type: Literal["mlp", "pyramid"] = "pyramid"
    num_planes: int = 56  # D planes per MPI
    # Spacing of the planes in disparity: 1 = uniform between near and far; below 1, this share
    # of the planes is spread uniformly and the rest follows where a plane sweep finds the scene's
    # surfaces (cmc.method.model.sweep_statistics, cmc.geometry.planes.content_plane_depths), so that a surface
    # lies nearer a plane and a view far from the inputs sees it less displaced.
    plane_density_floor: float = 0.05
    # With plane_density_floor below 1: the planes span only the depths where the first plane sweep
    # finds the scene's surfaces (cmc.geometry.planes.occupied_depth_range), not all of the scene's
    # near/far bounds, so the views do not depend on how tight those bounds are.
    fit_depth_range: bool = True
    margin: float = 1.2  # plane extent relative to the reference image (see MPIFrame)
    # Learn each input photo's colour response (gain and offset per channel, cmc.method.model.ExposureResponse),
    # so that an MPI is compared with another input photo in that photo's exposure and white balance.
    exposure_compensation: bool = True
    # The plane sweep that places the planes (with plane_density_floor below 1) and starts the
    # pyramid field's alpha (PyramidFieldConfig.init_from_sweep).
    sweep: SweepConfig = field(default_factory=SweepConfig)
    mlp: MLPFieldConfig = field(default_factory=MLPFieldConfig)
    pyramid: PyramidFieldConfig = field(default_factory=PyramidFieldConfig)


@dataclass
class LossConfig:
    """Loss weights (paper Eq. 4.5-4.8 and our priors; defaults: the ``fast`` preset's). A weight
    of 0 switches a term off."""

    lambda_dc_input: float = 0.01  # depth consistency between MPIs at the input views (L_dc^I)
    lambda_ac: float = 0.0  # appearance consistency between MPIs at unseen poses (Eq. 4.6)
    lambda_dc: float = 0.01  # depth consistency between MPIs at unseen poses (Eq. 4.7)
    lambda_distortion: float = 0.01  # concentration of each ray's opacity (cmc.method.losses.distortion)
    # Form of both depth-consistency terms: "squared" (the paper's, on depth / (far - near)) or
    # "cauchy" (occlusion-tolerant, on disparity; cmc.method.losses.robust_depth_consistency).
    depth_consistency: Literal["squared", "cauchy"] = "cauchy"
    lambda_alpha_entropy: float = 0.003  # visible alpha pushed to 0 or 1 (cmc.method.losses.alpha_entropy)
    # Factors on lambda_alpha_entropy over equal shares of the steps, in order ((1.0,): constant):
    # weaker while the geometry settles, stronger once it has (cmc.method.training.alpha_entropy_weight).
    alpha_entropy_schedule: tuple[float, ...] = (0.5, 1.5)
    # first fraction of steps without the depth-consistency terms (paper: 15/50 epochs, L_MSE only)
    recon_only_fraction: float = 0.3
    cross_view_colour: float = 0.1  # factor on the colour gradients of MPI i from input view j != i


@dataclass
class TrainConfig:
    """Everything that determines a training run (with the scene and the seed); defaults: the
    ``fast`` preset."""

    preset: Preset = "fast"
    steps: int = 300
    rays_per_view: int = 6144  # rays drawn from every input view per step
    # How a step draws an input view's rays: "uniform" (independent random pixels) or
    # "permutation" (successive slices of a random order of all the photo's pixels: every pixel is
    # drawn once before any is drawn again, so every texel of the photo's own plane textures gets
    # its share of updates).
    ray_sampling: Literal["uniform", "permutation"] = "permutation"
    # The share of each input view's rays that the other views' MPIs render too, evenly spread
    # over the batch (its own MPI renders them all): the other views' rays mostly shape an MPI's
    # alpha, whose textures are coarser than the colours its own photo's rays fit.
    cross_view_rays: float = 0.5
    unseen_rays: int = 1024  # rays drawn at each unseen pose per step
    unseen_poses: int = 1  # unseen poses per step
    unseen_jitter: float = 0.1  # std of the unseen-pose centre jitter, in mean baselines
    lr: float = 0.04  # Adam learning rate at step 0 ...
    lr_final: float = 0.005  # ... decaying exponentially to this at the last step
    # A plane sample weighing less than this in its ray's colour passes no gradient to its colour
    # (cmc.mpi.rendering.composite), and training does not sample its colour at all (it reads
    # 0.5: cmc.mpi.rendering.render_ray_groups): both passes skip those texels, most of a step's.
    colour_grad_min_weight: float = 1e-3
    seed: int = 0
    checkpoint_every: int = 250  # steps between checkpoints (when a checkpoint path is given)
    model: ModelConfig = field(default_factory=ModelConfig)
    loss: LossConfig = field(default_factory=LossConfig)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict[str, Any]) -> TrainConfig:
        """The inverse of :meth:`to_dict` (lists back to tuples, nested groups to dataclasses).
        A setting missing from ``d`` (a configuration saved before it existed) raises ConfigError."""
        return _dataclass_from_dict(TrainConfig, d)


def _dataclass_from_dict(cls: type, d: dict[str, Any], prefix: str = "") -> Any:
    hints = get_type_hints(cls)
    values = {}
    for f in fields(cls):
        if f.name not in d:
            raise ConfigError(
                f"the configuration has no setting {prefix + f.name!r}: it was saved by an older version of cmc"
            )
        v = d[f.name]
        if is_dataclass(hints[f.name]):
            v = _dataclass_from_dict(hints[f.name], v, f"{prefix}{f.name}.")
        elif isinstance(v, list):
            v = tuple(v)
        values[f.name] = v
    return cls(**values)


def preset_config(name: str, **overrides: Any) -> TrainConfig:
    """The named preset with top-level fields overridden (e.g. ``steps=20``).

    * ``paper``: the paper's Sec. 5.1 -- per-view MLP (PE L=10 on the point, raw direction,
      6 x 256 LeakyReLU), 80 planes, Adam 5e-3 -> 1e-4, 1024-ray batches, reconstruction only for
      the first 30 %, then lambda_ac = lambda_dc = 1.
    * ``fast``: explicit multi-resolution plane textures (see cmc.mpi.fields.PyramidPlaneField),
      alpha initialised by an occlusion-aware, edge-aware plane sweep with the AD-Census cost
      (``sweep.cost="ad_census"``) and semi-global aggregation (``sweep.smoothness=(0.2,
      2.0)``: an untextured wall takes the depth its neighbours agree on), softmin temperature
      0.3, run on a grid twice as fine as alpha's finest level while that grid holds at most
      ``sweep.max_texels`` (``sweep.supersample=2``), the margin beyond the photo starting
      with the border's geometry (``sweep.extend_border``); 56 planes, the paper's losses
      except L_ac (which blurred novel views in the ablation), the depth-consistency terms
      in an occlusion-tolerant form (cmc.method.losses.robust_depth_consistency), plus a concentration
      prior on each ray's opacity (cmc.method.losses.distortion) and a binary-entropy prior on the alpha
      a ray sees (cmc.method.losses.alpha_entropy: no faint fog in front of surfaces; at half its
      weight in the first half of the steps and 1.5 times it in the second,
      ``loss.alpha_entropy_schedule``: the other views move the geometry further before alpha
      settles at 0 or 1), a full-resolution
      base colour per group of 7 planes (``model.pyramid.base_groups=8``: a surface hidden in
      the reference photo gets its own texture) sampled bicubically
      (``model.pyramid.base_interpolation``: detail survives the sub-texel shifts of a novel
      view) plus each plane's own colour residual at 1/4, 1/8 and 1/16 of the plane extent
      (``model.pyramid.colour_scales``: a 1/2 level changed no view and cost 7-21 % of the
      training), behind every texel's visible surface the base colours of the farther plane groups
      starting as the background nearby (``pyramid.hidden_colour_everywhere``: what a view beside
      the photo sees past an outline is background, not a smear of the occluder), the colour
      gradients each MPI gets from the other input views' rays scaled by 0.1
      (``loss.cross_view_colour``: its colours stay those of its own photo, its geometry answers
      to every view), 6144 rays per input view and step drawn as slices of a random order of
      the photo's pixels (``ray_sampling="permutation"``), every other one of them rendered by
      the other views' MPIs too (``cross_view_rays=0.5``: a third fewer samples a step, the
      same views), 1024 rays at the step's unseen pose (``unseen_rays``: twice as many moved no
      validation view by 0.02 dB), Adam's learning rate 0.04 falling to
      0.005, the 56 planes spaced by where a first
      plane sweep finds the surfaces (``model.plane_density_floor=0.05``: a twentieth of them
      uniform in disparity, the rest following the cube root of the sweep's density) over the
      depths where that sweep finds the scene, not all of near..far (``model.fit_depth_range``:
      the views do not depend on how loose the bounds are), each input
      photo's colour response learnt and renders shown in their mean
      (``model.exposure_compensation``: photos shot at different exposures do not bend the
      geometry), while training a colour term that follows the ray's direction where the photo is
      untextured (``model.pyramid.view_colour_scale``: reflections the other photos see are not
      explained by geometry; bakes hold the reference camera's colours), 300 steps, no colour
      gradient for a plane sample weighing under 1e-3 in its ray (``colour_grad_min_weight``: the
      same views, a shorter backward pass).
    """
    if name == "paper":
        cfg = TrainConfig(
            preset="paper",
            steps=20000,
            rays_per_view=1024,
            ray_sampling="uniform",
            cross_view_rays=1.0,
            unseen_rays=1024,
            lr=5e-3,
            lr_final=1e-4,
            colour_grad_min_weight=0.0,
            model=ModelConfig(
                field_type="mlp",
                num_planes=80,
                plane_density_floor=1.0,
                fit_depth_range=False,
                exposure_compensation=False,
            ),
            loss=LossConfig(
                lambda_dc_input=1.0,
                lambda_ac=1.0,
                lambda_dc=1.0,
                lambda_distortion=0.0,
                depth_consistency="squared",
                lambda_alpha_entropy=0.0,
                cross_view_colour=1.0,
            ),
        )
    elif name == "fast":
        cfg = TrainConfig()  # why each setting, with its measurements: bench/PRESET_HISTORY.md
    else:
        raise ConfigError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
    return replace(cfg, **overrides)


def with_settings(cfg: TrainConfig, settings: list[str]) -> TrainConfig:
    """``cfg`` with dotted ``KEY=VALUE`` overrides applied, e.g. ``loss.lambda_ac=0.5``.

    Values are parsed as JSON (numbers, true/false, lists) where they parse, else kept as text,
    and must have the type of the field they replace; unknown keys raise ConfigError.
    """
    for item in settings:
        key, sep, text = item.partition("=")
        if not sep:
            raise ConfigError(f"setting {item!r} is not KEY=VALUE")
        try:
            value: Any = json.loads(text)
        except json.JSONDecodeError:
            value = text
        cfg = _replace_path(cfg, key.split("."), value, key)
    return cfg


def _replace_path(obj: Any, path: list[str], value: Any, key: str) -> Any:
    name = path[0]
    if not is_dataclass(obj) or name not in {f.name for f in fields(obj)}:
        raise ConfigError(f"unknown setting {key!r}")
    current = getattr(obj, name)
    if len(path) > 1:
        return replace(obj, **{name: _replace_path(current, path[1:], value, key)})
    if isinstance(current, tuple) and isinstance(value, list):
        value = tuple(value)
    elif isinstance(current, float) and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if type(value) is not type(current):
        raise ConfigError(f"setting {key!r} needs a {type(current).__name__}, got {value!r}")
    return replace(obj, **{name: value})
