"""Small pose builders shared by the geometry, camera and rendering tests."""

from __future__ import annotations

import math

import numpy as np


def rotation(axis, angle: float) -> np.ndarray:
    """[3, 3] rotation by ``angle`` radians about ``axis`` (Rodrigues)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    Kx = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * Kx + (1 - math.cos(angle)) * Kx @ Kx


def rigid(R: np.ndarray, t) -> np.ndarray:
    """[4, 4] rigid transform with rotation R and translation t."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T
