"""Cameras and the Gaussian rasterizer.

``render_views(gaussians, cameras, request) -> list[RenderOutput]`` is the one entry point:
several cameras of the same Gaussians (one gsplat call on CUDA, a loop elsewhere).
``rasterize(gaussians, camera, request) -> RenderOutput`` is its one-camera case. Backends
"torch" (reference), "cpu" (numba) and "gsplat" (CUDA) render the same picture.
"""

from .rasterize import available_backends, rasterize
from .types import GaussianSet, RenderOutput, RenderRequest
from .views import render_views

__all__ = ["GaussianSet", "RenderOutput", "RenderRequest", "available_backends", "rasterize",
           "render_views"]
