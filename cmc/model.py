"""The CMC model: one MPI (frame + field) per input view, and novel-view rendering by blending."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from cmc.config import ModelConfig
from cmc.datasets import Scene
from cmc.fields import MLPField, MPIField, PyramidPlaneField
from cmc.geometry import texel_grid
from cmc.planesweep import alpha_from_weights, plane_sweep_weights
from cmc.rendering import ImageOutput, MPIFrame, render_image


def padded_reference(image: np.ndarray, frame: MPIFrame) -> torch.Tensor:
    """[3, h, w] the reference photo resampled onto the plane extent, edge-extended into the
    margin (the initial colour of a pyramid field)."""
    img = torch.as_tensor(image, dtype=torch.float32).permute(2, 0, 1)[None]
    h, w = frame.extent
    grid = texel_grid(h, w)[None] * frame.margin  # plane grid -> image grid coordinates
    return F.grid_sample(img, grid, align_corners=False, padding_mode="border")[0]


class CMCModel(nn.Module):
    """Per-view MPIs for the N views of a scene.

    Attributes:
        frames: N :class:`MPIFrame` (reference camera and plane depths of each MPI).
        fields: N fields (``nn.ModuleList``).
        near, far: the plane range (scene units) shared by all MPIs.
    """

    def __init__(self, scene: Scene, cfg: ModelConfig, device: torch.device | str = "cpu"):
        super().__init__()
        self.cfg = cfg
        self.near, self.far = scene.near, scene.far
        cams = scene.cameras
        self.width, self.height = cams.width, cams.height
        self.frames = [
            MPIFrame.create(
                cams.K[i],
                cams.world_from_cam[i],
                self.near,
                self.far,
                cfg.num_planes,
                cams.width,
                cams.height,
                cfg.margin,
                device,
            )
            for i in range(len(scene))
        ]
        fields: list[MPIField] = []
        images = torch.as_tensor(scene.images, device=device).permute(0, 3, 1, 2)
        for i, fr in enumerate(self.frames):
            if cfg.field_type == "mlp":
                fields.append(MLPField(cfg.num_planes, cfg.mlp))
            elif cfg.field_type == "pyramid":
                init_alpha = None
                if cfg.pyramid.stereo_init:
                    h, w = (max(2, round(e * cfg.pyramid.scales[0])) for e in fr.extent)
                    probs = plane_sweep_weights(
                        self.frames,
                        images,
                        i,
                        h,
                        w,
                        cfg.pyramid.stereo_temperature,
                        occlusion_aware=cfg.pyramid.stereo_occlusion_aware,
                        edge_sigma=cfg.pyramid.stereo_edge_sigma or None,
                        extend_border=cfg.pyramid.stereo_extend_border,
                    )
                    init_alpha = alpha_from_weights(probs)
                rgb = padded_reference(scene.images[i], fr)
                fields.append(PyramidPlaneField(cfg.num_planes, *fr.extent, cfg.pyramid, rgb, init_alpha))
            else:
                raise ValueError(f"unknown field type {cfg.field_type!r}")
        self.fields = nn.ModuleList(fields).to(device)

    def render(
        self,
        K: np.ndarray,
        world_from_cam: np.ndarray,
        width: int,
        height: int,
        mpi_index: int | None = None,
        min_weight: float = 0.0,
    ) -> ImageOutput:
        """Render colour and depth for any camera (see :func:`cmc.rendering.render_image`)."""
        return render_image(
            list(self.fields), self.frames, K, world_from_cam, width, height, mpi_index, min_weight=min_weight
        )  # type: ignore[arg-type]
