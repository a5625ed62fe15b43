"""Cameras and the Gaussian rasterizer.

``rasterize(gaussians, camera, request) -> RenderOutput`` is the one entry point; backends
"torch" (reference), "cpu" (numba) and "gsplat" (CUDA) render the same picture.
``render_views(gaussians, cameras, request)`` renders several cameras of the same Gaussians
(one gsplat call on CUDA, a loop elsewhere).
"""

from .rasterize import available_backends, rasterize
from .types import GaussianSet, RenderOutput, RenderRequest
from .views import render_views

__all__ = ["GaussianSet", "RenderOutput", "RenderRequest", "available_backends", "rasterize",
           "render_views"]
