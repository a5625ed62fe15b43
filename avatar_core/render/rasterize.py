"""One camera: ``rasterize(gaussians, camera, request) -> RenderOutput``.

The rasterizer's entry point is :func:`avatar_core.render.render_views` (several cameras of
the same Gaussians); this is its one-camera case, what it runs per camera on the torch and cpu
backends, and what gsplat runs for a single camera.

Stages: validate (:mod:`checks`, shared with ``render_views``) -> project (torch,
differentiable) -> count each splat's (Gaussian, tile) pairs (:mod:`cost`) -> keep the
visible Gaussians, or the ``budget`` most important of them, and only as many of the most
important as fit in ``max_tile_pairs`` pairs (a frame over its cost bound is degraded, on
every backend, before anything per pair is allocated) -> colour from SH (only when rgb is
asked) -> composite on the chosen backend -> expected depth (only when asked). Everything
before compositing is shared, so the torch and cpu backends differ only in the compositing
kernel. When nothing needs gradients, the cpu backend runs
projection and colour with their numba twins (:mod:`project_cpu`) as well: same stages, same
picture, no per-op tensor overhead.
"""

from __future__ import annotations

import time

import numpy as np
import torch
from torch import Tensor

from .budget import budget_count, drop_over_budget_np, select_rendered
from .camera import Camera
from .checks import (
    check_gaussians,
    check_request,
    clamp_opacities,
    rendered_sh_degree,
    sized_camera,
)
from .contract import NEAR_PLANE
from .cost import pair_bound, tile_pairs, tile_pairs_np
from .projection import depth_key, project_gaussians
from .sh import sh_to_rgb
from .types import (
    BACKENDS,
    GaussianSet,
    RenderOutput,
    RenderRequest,
    background_output,
)

__all__ = ["available_backends", "rasterize", "resolve_backend"]


def _gsplat_available() -> bool:
    from . import rasterize_gsplat

    return rasterize_gsplat.available()


def available_backends() -> list[str]:
    """Backends that can run here ("torch" and "cpu" always; "gsplat" with CUDA)."""
    return ["torch", "cpu"] + (["gsplat"] if _gsplat_available() else [])


def resolve_backend(name: str, device: torch.device) -> str:
    """"auto": gsplat for CUDA tensors when installed, the numba kernels for CPU tensors,
    else the PyTorch reference."""
    if name not in BACKENDS:
        raise ValueError(f"unknown backend {name!r}; expected one of {BACKENDS}")
    if name != "auto":
        return name
    if device.type == "cuda" and _gsplat_available():
        return "gsplat"
    return "cpu" if device.type == "cpu" else "torch"


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1e3


def rasterize(gaussians: GaussianSet, camera: Camera,
              request: RenderRequest = RenderRequest(),  # noqa: B008
              *, check_finite: bool = True) -> RenderOutput:
    """Render ``gaussians`` seen by ``camera`` (see :mod:`avatar_core.render.types`): what
    ``render_views(gaussians, [camera], request)[0]`` returns.

    Differentiable with respect to the Gaussians on every backend. Raises ``ValueError`` for
    NaN/Inf inputs, bad shapes or a bad request. ``check_finite=False`` skips the NaN/Inf
    scan (a host round trip per tensor on CUDA) for callers that guard their results
    themselves (the trainer's device-side step guard).
    """
    t_start = time.perf_counter()
    check_request(request)
    check_gaussians(gaussians, check_finite)
    gaussians = clamp_opacities(gaussians)
    camera = sized_camera(camera, request)
    width, height = camera.width, camera.height
    outputs = set(request.outputs)
    device, dtype = gaussians.means.device, gaussians.means.dtype
    backend = resolve_backend(request.backend, device)
    sh_degree = rendered_sh_degree(gaussians, request)

    if backend == "gsplat":
        from .rasterize_gsplat import rasterize_gsplat

        return rasterize_gsplat(gaussians, camera, request, sh_degree, t_start)

    stats: dict = {"backend": backend, "n_gaussians": gaussians.num}
    if backend == "cpu" and not _needs_grad(gaussians):
        return _rasterize_cpu_no_grad(gaussians, camera, request, sh_degree, stats, t_start)
    t0 = time.perf_counter()
    viewmat, K = camera.to_torch(device, dtype)
    proj = project_gaussians(gaussians.means, gaussians.quats, gaussians.scales,
                             gaussians.opacities, viewmat, K, width, height, NEAR_PLANE,
                             request.antialiased, validate=False)
    max_pairs = pair_bound(request.max_tile_pairs)
    pairs = tile_pairs(proj.means2d, proj.radii, width, height)  # [N]
    sel, stats["n_visible"] = select_rendered(proj, request.budget, pairs, max_pairs)
    stats["n_rendered"] = int(sel.numel())
    stats["tile_pairs"] = int(pairs[sel].sum())
    stats["n_cost_dropped"] = (budget_count(request.budget, stats["n_visible"])
                               - stats["n_rendered"])  # by the pair bound
    stats["project_ms"] = _ms(t0)

    bg = torch.tensor(request.background, dtype=dtype, device=device)
    if sel.numel() == 0:
        return background_output(request, width, height, dtype, device, stats, t_start)

    # all kept (the common case): slices instead of gathers, which cost ~5 ms at 20k
    # Gaussians with their backward (scatters into zeros)
    take = slice(None) if sel.numel() == gaussians.num else sel
    t0 = time.perf_counter()
    colors = None
    if "rgb" in outputs:
        campos = torch.as_tensor(camera.center, dtype=dtype, device=device)
        k = (sh_degree + 1) ** 2
        colors = sh_to_rgb(sh_degree, gaussians.sh[take, :k], gaussians.means[take] - campos)
    stats["color_ms"] = _ms(t0)

    t0 = time.perf_counter()
    if backend == "cpu":
        from .rasterize_cpu import rasterize_to_pixels
    else:
        from .rasterize_torch import rasterize_to_pixels
    with_depth = "depth" in outputs
    keys = depth_key(gaussians.means, camera.viewmat())[take]
    rgb, alpha, depth_acc = rasterize_to_pixels(
        proj.means2d[take], proj.conics[take], colors, proj.opacities[take], proj.depths[take],
        proj.radii[take], width, height, background=bg, with_depth=with_depth, sort_keys=keys,
        max_pairs=max_pairs)
    depth = _expected_depth(depth_acc, alpha) if with_depth else None
    stats["raster_ms"] = _ms(t0)
    stats["total_ms"] = _ms(t_start)
    return RenderOutput(rgb=rgb, alpha=alpha if "alpha" in outputs else None, depth=depth,
                        stats=stats)


def _needs_grad(g: GaussianSet) -> bool:
    return torch.is_grad_enabled() and any(
        t.requires_grad for t in (g.means, g.quats, g.scales, g.opacities, g.sh))


def _np32(t: Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().to("cpu", torch.float32).numpy())


def _rasterize_cpu_no_grad(g: GaussianSet, camera: Camera, request: RenderRequest,
                           sh_degree: int, stats: dict, t_start: float) -> RenderOutput:
    """The cpu backend without autograd: projection and colour in numba too (the twins of
    the torch stages above), no tensor round trips. Same picture as the autograd path."""
    from .project_cpu import project_np, sh_rgb_np
    from .rasterize_cpu import composite_np, pairs_allocated

    width, height = camera.width, camera.height
    outputs = set(request.outputs)
    dtype = g.means.dtype
    t0 = time.perf_counter()
    means, opac = _np32(g.means), _np32(g.opacities)
    m2, co, de, rad, op = project_np(means, _np32(g.quats), _np32(g.scales), opac,
                                     camera.viewmat(), camera.K, width, height, NEAR_PLANE,
                                     request.antialiased)
    max_pairs = pair_bound(request.max_tile_pairs)
    pairs = tile_pairs_np(m2, rad, width, height)  # [N], before anything per pair
    stats["n_visible"], keep = drop_over_budget_np(co, op, rad, request.budget, pairs,
                                                   max_pairs)
    stats["n_rendered"] = keep
    stats["tile_pairs"] = int(pairs[rad > 0].sum())
    stats["n_cost_dropped"] = budget_count(request.budget, stats["n_visible"]) - keep
    stats["project_ms"] = _ms(t0)
    if keep == 0:
        return background_output(request, width, height, dtype, g.means.device, stats,
                                 t_start)

    t0 = time.perf_counter()
    feats = np.zeros((means.shape[0], 4), np.float32)  # rgb, then depth
    n_col = 3 if "rgb" in outputs else 0
    if n_col:
        sh_rgb_np(sh_degree, _np32(g.sh), means, camera.center, rad, feats)
    if "depth" in outputs:
        feats[:, n_col] = de
    stats["color_ms"] = _ms(t0)

    t0 = time.perf_counter()
    bg = np.zeros(4)
    bg[:n_col] = request.background[:n_col]
    keys = depth_key(g.means, camera.viewmat()).cpu().numpy()
    out, T, state = composite_np(m2, co, op, feats, keys, rad, width, height, bg, max_pairs)
    stats["pairs_allocated"] = pairs_allocated(state)
    to = dict(dtype=dtype, device=g.means.device)
    alpha = torch.from_numpy(1.0 - T).to(**to)
    rgb = torch.from_numpy(out[..., :3]).to(**to) if n_col else None
    depth = None
    if "depth" in outputs:
        depth = _expected_depth(torch.from_numpy(out[..., n_col]).to(**to), alpha)
    stats["raster_ms"] = _ms(t0)
    stats["total_ms"] = _ms(t_start)
    return RenderOutput(rgb=rgb, alpha=alpha if "alpha" in outputs else None, depth=depth,
                        stats=stats)


def _expected_depth(depth_acc: Tensor, alpha: Tensor) -> Tensor:
    """sum(w z) / alpha, 0 where alpha == 0 (guarded so no NaN reaches the gradients)."""
    hit = alpha > 0
    return torch.where(hit, depth_acc / torch.where(hit, alpha, torch.ones_like(alpha)),
                       torch.zeros_like(alpha))
