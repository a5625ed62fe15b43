"""Cameras and the Gaussian rasterizer.

``rasterize(gaussians, camera, request) -> RenderOutput`` is the one entry point; backends
"torch" (reference), "cpu" (numba) and "gsplat" (CUDA) render the same picture.
"""

from .rasterize import available_backends, rasterize
from .types import GaussianSet, RenderOutput, RenderRequest

__all__ = ["GaussianSet", "RenderOutput", "RenderRequest", "available_backends", "rasterize"]
