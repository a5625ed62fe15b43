"""The webcam: a pinhole with a horizontal field of view, principal point at the centre.

The camera sits at the model-space origin looking down -z (the body model faces +z, toward
the viewer), so camera coordinates are model coordinates with y and z flipped: OpenCV's x
right, y down, z forward. The subject's placement is the fitted `transl`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

MIN_DEPTH_M = 0.05  # points nearer than this (or behind) are clamped, never divide by ~0


@dataclass(frozen=True)
class WebcamCamera:
    width: int
    height: int
    fov_x_deg: float = 60.0

    @property
    def focal(self) -> float:
        return 0.5 * self.width / math.tan(math.radians(self.fov_x_deg) / 2)

    @property
    def center(self) -> tuple[float, float]:
        return 0.5 * self.width, 0.5 * self.height

    def project(self, points: Tensor) -> Tensor:
        """Model-space points [..., 3] -> pixels [..., 2] (x right, y down)."""
        depth = (-points[..., 2]).clamp(min=MIN_DEPTH_M)
        cx, cy = self.center
        u = self.focal * points[..., 0] / depth + cx
        v = self.focal * -points[..., 1] / depth + cy
        return torch.stack([u, v], dim=-1)

    def unproject_depth(self, pixels: np.ndarray, depth: float) -> np.ndarray:
        """Pixels [..., 2] at camera depth `depth` -> model-space points [..., 3]."""
        cx, cy = self.center
        x = (pixels[..., 0] - cx) * depth / self.focal
        y = -(pixels[..., 1] - cy) * depth / self.focal
        return np.stack([x, y, np.full_like(x, -depth)], axis=-1)


def project_points(points: np.ndarray, camera: WebcamCamera
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Model-space points [K, 3] -> pixels [K, 2] and d pixels / d point [K, 2, 3]
    (`WebcamCamera.project`; the depth clamp's derivative is 0)."""
    depth_raw = -points[:, 2]
    clamped = depth_raw < MIN_DEPTH_M
    depth = np.where(clamped, MIN_DEPTH_M, depth_raw)
    f = camera.focal
    cx, cy = camera.center
    u = f * points[:, 0] / depth + cx
    v = -f * points[:, 1] / depth + cy
    d = np.zeros((points.shape[0], 2, 3))
    d[:, 0, 0] = f / depth
    d[:, 1, 1] = -f / depth
    dz = np.where(clamped, 0.0, 1.0 / depth ** 2)
    d[:, 0, 2] = f * points[:, 0] * dz
    d[:, 1, 2] = -f * points[:, 1] * dz
    return np.stack([u, v], axis=-1), d
