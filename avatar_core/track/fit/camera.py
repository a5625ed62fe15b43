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

    def K(self) -> np.ndarray:
        cx, cy = self.center
        return np.array([[self.focal, 0, cx], [0, self.focal, cy], [0, 0, 1.0]])

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
