"""Plane-sweep prior: finds a textured wall on the right plane; alphas reproduce the weights."""

from __future__ import annotations

import numpy as np
import torch

from cmc.datasets import Layer, render_layers, synthetic_cameras
from cmc.geometry import plane_depths
from cmc.planesweep import alpha_from_weights, plane_sweep_weights
from cmc.rendering import MPIFrame, composite


def test_wall_is_found_on_its_plane():
    """A textured wall at world z = 4 seen by 3 cameras looking at (0, 0, 4): for the middle
    camera, texels inside its image put most weight on the plane nearest the wall's depth."""
    cams = synthetic_cameras(3, width=96, height=72, baseline=0.6)
    images, depth = render_layers((Layer(4.0, (-1e3, 1e3, -1e3, 1e3), 5),), cams)
    near, far, D = 2.0, 8.0, 24
    frames = [MPIFrame.create(cams.K[i], cams.world_from_cam[i], near, far, D, 96, 72, 1.0) for i in range(3)]
    imgs = torch.as_tensor(images).permute(0, 3, 1, 2)
    w = plane_sweep_weights(frames, imgs, 1, 72, 96, temperature=0.02)
    assert w.shape == (D, 72, 96)
    torch.testing.assert_close(w.sum(0), torch.ones(72, 96))
    best = w.argmax(0)[20:52, 30:66]  # central texels, seen by all views
    true_plane = int(np.abs(plane_depths(near, far, D) - depth[1, 36, 48]).argmin())
    assert (best - true_plane).abs().le(1).float().mean() > 0.9


def test_alpha_from_weights_reproduces_the_composite_weights():
    w = torch.softmax(torch.randn(16, 50), 0)
    a = alpha_from_weights(w, lo=0.0, hi=1.0)
    a[-1] = 1.0
    out = composite(torch.eye(16)[None].expand(50, 16, 16), a.T, torch.zeros(50, 16))
    torch.testing.assert_close(out.rgb, w.T, atol=1e-5, rtol=1e-4)
