"""The rasterizer's entry point: ``render_views(gaussians, cameras, request)``.

One :class:`RenderOutput` per camera of the same Gaussians and request. The server renders many
viewers of one avatar state (a room's participants: same posed Gaussians, same request,
different cameras); one camera is the common case, and :func:`rasterize.rasterize` is that case
(``render_views(g, [camera], r)[0]``). On gsplat, the cameras of one image size go to the GPU
in one call (:func:`rasterize_gsplat.rasterize_gsplat_views`); the torch and cpu backends have
no batched kernel and render the cameras one by one with ``rasterize``, so every backend
returns exactly what one call per camera would. Both paths start with the same checks
(:mod:`checks`).
"""

from __future__ import annotations

import time
from collections.abc import Sequence

from .camera import Camera
from .checks import (
    check_gaussians,
    check_request,
    clamp_opacities,
    rendered_sh_degree,
    sized_camera,
)
from .rasterize import rasterize, resolve_backend
from .types import GaussianSet, RenderOutput, RenderRequest

__all__ = ["render_views"]


def render_views(gaussians: GaussianSet, cameras: Sequence[Camera],
                 request: RenderRequest = RenderRequest(),  # noqa: B008
                 *, check_finite: bool = True) -> list[RenderOutput]:
    """One :class:`RenderOutput` per camera, in order: the picture ``rasterize`` gives for
    each camera alone (see :mod:`avatar_core.render.types`).

    Differentiable with respect to the Gaussians on the torch and cpu backends, and on gsplat
    for one camera. Raises ``ValueError`` for no camera, NaN/Inf inputs, bad shapes or a bad
    request; ``check_finite=False`` skips the NaN/Inf scan (as ``rasterize``'s does).
    """
    cameras = list(cameras)
    if not cameras:
        raise ValueError("render_views needs at least one camera")
    backend = resolve_backend(request.backend, gaussians.means.device)
    if backend != "gsplat" or len(cameras) == 1:
        return [rasterize(gaussians, cam, request, check_finite=check_finite)
                for cam in cameras]
    return _gsplat_views(gaussians, cameras, request, check_finite)


def _gsplat_views(gaussians: GaussianSet, cameras: list[Camera], request: RenderRequest,
                  check_finite: bool) -> list[RenderOutput]:
    """Several cameras on gsplat: one call per image size."""
    from .rasterize_gsplat import rasterize_gsplat_views

    t_start = time.perf_counter()
    check_request(request)
    check_gaussians(gaussians, check_finite)
    gaussians = clamp_opacities(gaussians)
    cameras = [sized_camera(cam, request) for cam in cameras]
    sh_degree = rendered_sh_degree(gaussians, request)
    by_size: dict[tuple[int, int], list[int]] = {}  # (width, height) -> camera indices
    for i, cam in enumerate(cameras):
        by_size.setdefault(cam.size, []).append(i)
    results: list[RenderOutput | None] = [None] * len(cameras)
    for idx in by_size.values():
        outs = rasterize_gsplat_views(gaussians, [cameras[i] for i in idx], request,
                                      sh_degree, t_start)
        for i, out in zip(idx, outs, strict=True):
            results[i] = out
    return results  # type: ignore[return-value]
