"""Several views of the same Gaussians: ``render_views(gaussians, cameras, request)``.

The server renders many viewers of one avatar state (a room's participants: same posed
Gaussians, same request, different cameras). On gsplat, the cameras of one image size go to
the GPU in one call (:func:`rasterize_gsplat.rasterize_gsplat_views`); the torch and cpu
backends have no batched kernel and render the cameras one by one with :func:`rasterize`,
so every backend returns exactly what one call per camera would.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

from .camera import Camera
from .rasterize import _check_gaussians, _check_request, rasterize, resolve_backend
from .types import GaussianSet, RenderOutput, RenderRequest

__all__ = ["render_views"]


def render_views(gaussians: GaussianSet, cameras: Sequence[Camera],
                 request: RenderRequest = RenderRequest()  # noqa: B008
                 ) -> list[RenderOutput]:
    """One :class:`RenderOutput` per camera, in order: the pictures ``rasterize`` gives for
    each camera alone. Raises ``ValueError`` for no camera and as ``rasterize`` does."""
    cameras = list(cameras)
    if not cameras:
        raise ValueError("render_views needs at least one camera")
    backend = resolve_backend(request.backend, gaussians.means.device)
    if backend != "gsplat" or len(cameras) == 1:
        return [rasterize(gaussians, cam, request) for cam in cameras]
    return _gsplat_views(gaussians, cameras, request)


def _gsplat_views(gaussians: GaussianSet, cameras: list[Camera],
                  request: RenderRequest) -> list[RenderOutput]:
    from .rasterize_gsplat import rasterize_gsplat_views

    t_start = time.perf_counter()
    _check_request(request)
    _check_gaussians(gaussians)
    # rasterize's clamp of the contract's [0, 1] (see there)
    gaussians = GaussianSet(gaussians.means, gaussians.quats, gaussians.scales,
                            gaussians.opacities.clamp(0.0, 1.0), gaussians.sh)
    if request.width is not None or request.height is not None:
        cameras = [cam.resized(request.width or cam.width, request.height or cam.height)
                   for cam in cameras]
    sh_degree = gaussians.sh_degree if request.sh_degree is None \
        else min(request.sh_degree, gaussians.sh_degree)
    by_size: dict[tuple[int, int], list[int]] = {}
    for i, cam in enumerate(cameras):
        by_size.setdefault(cam.size, []).append(i)
    results: list[RenderOutput | None] = [None] * len(cameras)
    for idx in by_size.values():  # one gsplat call per image size
        outs = rasterize_gsplat_views(gaussians, [cameras[i] for i in idx], request,
                                      sh_degree, t_start)
        for i, out in zip(idx, outs, strict=True):
            results[i] = out
    return results  # type: ignore[return-value]
