"""Image-quality metrics: PSNR, SSIM and LPIPS, matching the implementations papers report.

Conventions shared by every function here:

* Images are ``[H, W, C]`` (``C = 3`` for LPIPS), float, values in ``[0, 1]`` (data range 1),
  given as numpy arrays or torch tensors. Both images of a pair have the same shape.
* Higher is better for PSNR (dB) and SSIM; lower is better for LPIPS (a distance, 0 for equal images).

What each metric reproduces:

* ``psnr``: ``-10 log10(MSE)`` over all pixels and channels; ``inf`` for identical images.
* ``ssim``: scikit-image's ``structural_similarity(gaussian_weights=True, sigma=1.5,
  use_sample_covariance=False, win_size=11, data_range=1, channel_axis=2)``: local statistics under
  an 11-tap Gaussian (sigma 1.5, scipy's truncation at 3.5 sigma), SSIM map averaged over the
  pixels at least 5 from the border, then over channels. Computed in float64.
* ``LPIPS``: LPIPS v0.1 (Zhang et al. 2018, the ``lpips`` package) with the AlexNet or VGG16 backbone;
  weights are read from a state dict with torchvision's ``features.<idx>.weight/bias`` names and the
  linear heads under ``lin<k>.model.1.weight``. The weights file is found from an explicit directory
  or the ``CMC_LPIPS_DIR`` environment variable (a directory holding ``lpips_alex.pth`` and
  ``lpips_vgg.pth``).
"""

from __future__ import annotations

import functools
import math
import os
from pathlib import Path
from typing import Literal, TypedDict

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

LpipsNet = Literal["alex", "vgg"]
ImageLike = np.ndarray | torch.Tensor

LPIPS_DIR_ENV = "CMC_LPIPS_DIR"

# SSIM constants (Wang et al. 2004, as in scikit-image).
_SSIM_K1 = 0.01
_SSIM_K2 = 0.03
_SSIM_SIGMA = 1.5
_SSIM_TRUNCATE = 3.5


def _as_hwc_float64(image: ImageLike, name: str) -> torch.Tensor:
    """Returns ``image`` as a detached CPU float64 tensor ``[H, W, C]``."""
    if isinstance(image, torch.Tensor):
        tensor = image.detach().to(device="cpu", dtype=torch.float64)
    else:
        tensor = torch.tensor(np.asarray(image), dtype=torch.float64)
    if tensor.ndim != 3:
        raise ValueError(f"{name} must be [H, W, C], got shape {tuple(tensor.shape)}")
    return tensor


def _check_pair(a: ImageLike, b: ImageLike) -> tuple[torch.Tensor, torch.Tensor]:
    ta, tb = _as_hwc_float64(a, "a"), _as_hwc_float64(b, "b")
    if ta.shape != tb.shape:
        raise ValueError(f"images differ in shape: {tuple(ta.shape)} vs {tuple(tb.shape)}")
    return ta, tb


def psnr(a: ImageLike, b: ImageLike) -> float:
    """Peak signal-to-noise ratio in dB of two ``[H, W, C]`` images in ``[0, 1]`` (data range 1).

    Computed in float64 as ``-10 log10(mean((a - b)^2))`` over all pixels and channels;
    returns ``inf`` when the images are identical.
    """
    ta, tb = _check_pair(a, b)
    mse = torch.mean((ta - tb) ** 2).item()
    return math.inf if mse == 0.0 else -10.0 * math.log10(mse)


def _gaussian_taps(sigma: float, truncate: float) -> torch.Tensor:
    """scipy.ndimage's 1-D Gaussian: radius ``int(truncate * sigma + 0.5)``, weights summing to 1."""
    radius = int(truncate * sigma + 0.5)
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    taps = torch.exp(-0.5 * (x / sigma) ** 2)
    return taps / taps.sum()


def ssim(a: ImageLike, b: ImageLike) -> float:
    """Mean structural similarity of two ``[H, W, C]`` images in ``[0, 1]`` (data range 1).

    Matches scikit-image's ``structural_similarity`` with ``gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, win_size=11, data_range=1, channel_axis=2``. scikit-image filters
    the whole image (scipy ``mode='reflect'``) and then drops a 5-pixel border of the SSIM map; the
    kept pixels never see the padding, so a valid (unpadded) convolution gives the same values.
    Needs ``H, W >= 11``. Returns 1.0 for identical images.
    """
    ta, tb = _check_pair(a, b)
    height, width, channels = ta.shape
    taps = _gaussian_taps(_SSIM_SIGMA, _SSIM_TRUNCATE)
    win = taps.numel()
    if height < win or width < win:
        raise ValueError(f"ssim needs images of at least {win}x{win} pixels, got {height}x{width}")

    # [5 * C, 1, H, W]: the five quantities to average locally, one plane per channel.
    x = ta.permute(2, 0, 1)
    y = tb.permute(2, 0, 1)
    planes = torch.cat([x, y, x * x, y * y, x * y]).unsqueeze(1)
    filtered = F.conv2d(planes, taps.view(1, 1, win, 1))
    filtered = F.conv2d(filtered, taps.view(1, 1, 1, win))
    mu_x, mu_y, e_xx, e_yy, e_xy = filtered.squeeze(1).split(channels)

    var_x = e_xx - mu_x * mu_x
    var_y = e_yy - mu_y * mu_y
    cov_xy = e_xy - mu_x * mu_y
    c1 = _SSIM_K1**2  # (K1 * data_range)^2 with data_range = 1
    c2 = _SSIM_K2**2
    ssim_map = ((2 * mu_x * mu_y + c1) * (2 * cov_xy + c2)) / ((mu_x * mu_x + mu_y * mu_y + c1) * (var_x + var_y + c2))
    # Mean per channel, then over channels (equal-size channels: one global mean is the same).
    return ssim_map.mean().item()


# ----------------------------------------------------------------------------------------------
# LPIPS
# ----------------------------------------------------------------------------------------------

# torchvision layer layouts, so that ``features.<idx>`` names line up with the weights file.
# ("C", in, out, kernel, stride, padding) convolution; "R" ReLU; ("M", kernel, stride) max-pool.
_ALEX_LAYERS: list[tuple | str] = [
    ("C", 3, 64, 11, 4, 2), "R", ("M", 3, 2),
    ("C", 64, 192, 5, 1, 2), "R", ("M", 3, 2),
    ("C", 192, 384, 3, 1, 1), "R",
    ("C", 384, 256, 3, 1, 1), "R",
    ("C", 256, 256, 3, 1, 1), "R",
]  # fmt: skip
_VGG16_LAYERS: list[tuple | str] = [
    ("C", 3, 64, 3, 1, 1), "R", ("C", 64, 64, 3, 1, 1), "R", ("M", 2, 2),
    ("C", 64, 128, 3, 1, 1), "R", ("C", 128, 128, 3, 1, 1), "R", ("M", 2, 2),
    ("C", 128, 256, 3, 1, 1), "R", ("C", 256, 256, 3, 1, 1), "R", ("C", 256, 256, 3, 1, 1), "R",
    ("M", 2, 2),
    ("C", 256, 512, 3, 1, 1), "R", ("C", 512, 512, 3, 1, 1), "R", ("C", 512, 512, 3, 1, 1), "R",
    ("M", 2, 2),
    ("C", 512, 512, 3, 1, 1), "R", ("C", 512, 512, 3, 1, 1), "R", ("C", 512, 512, 3, 1, 1), "R",
]  # fmt: skip

# Indices in ``features`` of the ReLUs whose outputs LPIPS compares:
# alex relu1..relu5; vgg16 relu1_2, relu2_2, relu3_3, relu4_3, relu5_3.
_LPIPS_TAPS: dict[str, tuple[int, ...]] = {
    "alex": (1, 4, 7, 9, 11),
    "vgg": (3, 8, 15, 22, 29),
}
_LPIPS_LAYERS: dict[str, list[tuple | str]] = {
    "alex": _ALEX_LAYERS,
    "vgg": _VGG16_LAYERS,
}

# LPIPS ScalingLayer, applied to inputs in [-1, 1]: (x - shift) / scale.
_LPIPS_SHIFT = (-0.030, -0.088, -0.188)
_LPIPS_SCALE = (0.458, 0.448, 0.450)
_LPIPS_EPS = 1e-10


def _build_features(layers: list[tuple | str]) -> nn.Sequential:
    modules: list[nn.Module] = []
    for spec in layers:
        if isinstance(spec, str):  # "R"
            modules.append(nn.ReLU())
        elif spec[0] == "C":
            _, c_in, c_out, kernel, stride, padding = spec
            modules.append(nn.Conv2d(c_in, c_out, kernel, stride=stride, padding=padding))
        else:
            _, kernel, stride = spec
            modules.append(nn.MaxPool2d(kernel, stride=stride))
    return nn.Sequential(*modules)


class _LinearHead(nn.Module):
    """1x1 convolution to one channel, no bias; ``model.0`` stands for the official eval-time
    dropout (a no-op), so the weight is named ``model.1.weight`` as in the weights files."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.model = nn.Sequential(nn.Identity(), nn.Conv2d(channels, 1, 1, bias=False))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.model(x)


class _LpipsNetwork(nn.Module):
    """Backbone + linear heads of LPIPS v0.1; parameter names match the weights files."""

    def __init__(self, net: LpipsNet) -> None:
        super().__init__()
        self.taps = _LPIPS_TAPS[net]
        self.features = _build_features(_LPIPS_LAYERS[net])
        for k, tap in enumerate(self.taps):
            self.add_module(f"lin{k}", _LinearHead(self.features[tap - 1].out_channels))
        self.register_buffer("shift", torch.tensor(_LPIPS_SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(_LPIPS_SCALE).view(1, 3, 1, 1), persistent=False)

    def _tapped_features(self, x: torch.Tensor) -> list[torch.Tensor]:
        out = []
        for idx, layer in enumerate(self.features[: self.taps[-1] + 1]):
            x = layer(x)
            if idx in self.taps:
                out.append(x)
        return out

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """``x, y``: ``[B, 3, H, W]`` in ``[0, 1]``; returns the distances ``[B]``."""
        both = torch.cat([x, y]) * 2.0 - 1.0
        both = (both - self.shift) / self.scale
        total = x.new_zeros(x.shape[0])
        for k, feat in enumerate(self._tapped_features(both)):
            feat = feat / (torch.sqrt(torch.sum(feat**2, dim=1, keepdim=True)) + _LPIPS_EPS)
            fx, fy = feat.chunk(2)
            weighted = getattr(self, f"lin{k}")((fx - fy) ** 2)
            total = total + weighted.mean(dim=(1, 2, 3))
        return total


def lpips_weights_path(net: LpipsNet, weights_dir: str | Path | None = None) -> Path:
    """Path of ``lpips_<net>.pth`` in ``weights_dir``, or else in ``$CMC_LPIPS_DIR``.

    Raises:
        FileNotFoundError: neither is given, or the file is not in the chosen directory.
    """
    if net not in _LPIPS_TAPS:
        raise ValueError(f"unknown LPIPS network {net!r}; expected one of {sorted(_LPIPS_TAPS)}")
    if weights_dir is None:
        weights_dir = os.environ.get(LPIPS_DIR_ENV) or None
    if weights_dir is None:
        raise FileNotFoundError(
            f"LPIPS weights directory not set: pass weights_dir=... or set the environment "
            f"variable {LPIPS_DIR_ENV} to a directory holding lpips_alex.pth and lpips_vgg.pth"
        )
    path = Path(weights_dir) / f"lpips_{net}.pth"
    if not path.is_file():
        raise FileNotFoundError(f"LPIPS weights file not found: {path}")
    return path


@functools.lru_cache(maxsize=8)
def _load_lpips_network(net: LpipsNet, path: Path, device: torch.device) -> _LpipsNetwork:
    """Builds the network, loads ``path`` strictly, freezes it; cached per (net, file, device)."""
    model = _LpipsNetwork(net)
    model.load_state_dict(torch.load(path, map_location="cpu", weights_only=True))
    model.requires_grad_(False)
    return model.eval().to(device)


class LPIPS:
    """LPIPS v0.1 distance with the AlexNet (``"alex"``) or VGG16 (``"vgg"``) backbone.

    The weights file ``lpips_<net>.pth`` is taken from ``weights_dir`` or else from the directory
    in ``$CMC_LPIPS_DIR``. Loaded networks are cached, so constructing ``LPIPS`` repeatedly is cheap.

    Convention: inputs in ``[0, 1]`` are mapped to ``[-1, 1]`` (the official ``normalize=True``),
    then the official ScalingLayer, backbone ReLU features unit-normalised over channels, squared
    differences weighted by the linear heads, averaged spatially and summed over the five layers.
    """

    def __init__(
        self,
        net: LpipsNet,
        weights_dir: str | Path | None = None,
        device: str | torch.device = "cpu",
    ) -> None:
        self.net = net
        self.device = torch.device(device)
        path = lpips_weights_path(net, weights_dir).resolve()
        self._network = _load_lpips_network(net, path, self.device)

    def batch(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Distances ``[B]`` between ``x`` and ``y``, both ``[B, 3, H, W]`` float in ``[0, 1]``.

        Differentiable with respect to the inputs (the network itself is frozen), so it can serve
        as a loss; wrap in ``torch.no_grad()`` for evaluation.
        """
        if x.shape != y.shape or x.ndim != 4 or x.shape[1] != 3:
            raise ValueError(f"expected two [B, 3, H, W] tensors, got {tuple(x.shape)}, {tuple(y.shape)}")
        return self._network(x.to(self.device, torch.float32), y.to(self.device, torch.float32))

    def __call__(self, a: ImageLike, b: ImageLike) -> float:
        """Distance between two ``[H, W, 3]`` images in ``[0, 1]`` (numpy or torch)."""
        ta, tb = _check_pair(a, b)
        with torch.no_grad():
            return self.batch(ta.permute(2, 0, 1)[None], tb.permute(2, 0, 1)[None]).item()


class ImageMetrics(TypedDict):
    """The metrics of one predicted image against its ground truth."""

    psnr: float
    ssim: float
    lpips_alex: float
    lpips_vgg: float


def image_metrics(pred: ImageLike, gt: ImageLike, lpips_weights_dir: str | Path | None = None) -> ImageMetrics:
    """PSNR, SSIM and LPIPS (alex, vgg) of ``pred`` against ``gt``, both ``[H, W, 3]`` in ``[0, 1]``.

    ``lpips_weights_dir`` as in ``LPIPS`` (``None``: use ``$CMC_LPIPS_DIR``).
    """
    return ImageMetrics(
        psnr=psnr(pred, gt),
        ssim=ssim(pred, gt),
        lpips_alex=LPIPS("alex", lpips_weights_dir)(pred, gt),
        lpips_vgg=LPIPS("vgg", lpips_weights_dir)(pred, gt),
    )
