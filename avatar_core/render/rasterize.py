"""The one rasterizer entry point: ``rasterize(gaussians, camera, request) -> RenderOutput``.

Stages: validate -> project (torch, differentiable) -> keep the visible Gaussians, or the
``budget`` most important of them -> colour from SH (only when rgb is asked) -> composite on
the chosen backend -> expected depth (only when asked). Everything before compositing is
shared, so the torch and cpu backends differ only in the compositing kernel. When nothing
needs gradients, the cpu backend runs projection and colour with their numba twins
(:mod:`project_cpu`) as well: same stages, same picture, no per-op tensor overhead.
"""

from __future__ import annotations

import time

import numpy as np
import torch
from torch import Tensor

from .budget import drop_over_budget_np, select_rendered
from .camera import Camera
from .contract import NEAR_PLANE
from .projection import check_finite, depth_key, project_gaussians
from .sh import sh_to_rgb
from .types import (
    BACKENDS,
    OUTPUTS,
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


def _check_request(request: RenderRequest) -> None:
    outs = tuple(request.outputs)
    if not outs or any(o not in OUTPUTS for o in outs):
        raise ValueError(f"outputs must be a non-empty subset of {OUTPUTS}, got {outs!r}")
    budget = request.budget
    if budget is not None:
        if isinstance(budget, bool) or not isinstance(budget, (int, float)):
            raise ValueError(f"budget must be an int count or a float fraction, got {budget!r}")
        if isinstance(budget, int) and budget < 0:
            raise ValueError(f"budget count must be >= 0, got {budget}")
        if isinstance(budget, float) and not 0.0 < budget <= 1.0:
            raise ValueError(f"budget fraction must be in (0, 1], got {budget}")
    if request.sh_degree is not None and not 0 <= request.sh_degree <= 3:
        raise ValueError(f"sh_degree must be in 0..3, got {request.sh_degree}")
    if len(request.background) != 3:
        raise ValueError(f"background must be an RGB triple, got {request.background!r}")


def _check_gaussians(g: GaussianSet, finite: bool = True) -> None:
    n = g.means.shape[0] if g.means.ndim == 2 else -1
    shapes = {"means": (n, 3), "quats": (n, 4), "scales": (n, 3), "opacities": (n,)}
    for name, shape in shapes.items():
        t = getattr(g, name)
        if tuple(t.shape) != shape:
            raise ValueError(f"gaussians.{name} must have shape {shape}, got {tuple(t.shape)}")
    if g.sh.ndim != 3 or g.sh.shape[0] != n or g.sh.shape[2] != 3 \
            or g.sh.shape[1] not in (1, 4, 9, 16):
        raise ValueError(f"gaussians.sh must be [N, K in (1, 4, 9, 16), 3], got "
                         f"{tuple(g.sh.shape)}")
    if finite:
        check_finite(means=g.means, quats=g.quats, scales=g.scales, opacities=g.opacities,
                     sh=g.sh)


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1e3


def rasterize(gaussians: GaussianSet, camera: Camera,
              request: RenderRequest = RenderRequest(),  # noqa: B008
              *, check_finite: bool = True) -> RenderOutput:
    """Render ``gaussians`` seen by ``camera`` (see :mod:`avatar_core.render.types`).

    Differentiable with respect to the Gaussians on every backend. Raises ``ValueError`` for
    NaN/Inf inputs, bad shapes or a bad request. ``check_finite=False`` skips the NaN/Inf
    scan (a host round trip per tensor on CUDA) for callers that guard their results
    themselves (the trainer's device-side step guard).
    """
    t_start = time.perf_counter()
    _check_request(request)
    _check_gaussians(gaussians, check_finite)
    # the contract's [0, 1], enforced: a huge opacity times a vanishing Gaussian overflows the
    # gradients (Inf * 0); the clamp's gradient is 1 inside, so training is unaffected
    gaussians = GaussianSet(gaussians.means, gaussians.quats, gaussians.scales,
                            gaussians.opacities.clamp(0.0, 1.0), gaussians.sh)
    if request.width is not None or request.height is not None:
        camera = camera.resized(request.width or camera.width, request.height or camera.height)
    width, height = camera.width, camera.height
    outputs = set(request.outputs)
    device, dtype = gaussians.means.device, gaussians.means.dtype
    backend = resolve_backend(request.backend, device)
    sh_degree = gaussians.sh_degree if request.sh_degree is None \
        else min(request.sh_degree, gaussians.sh_degree)

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
    sel, stats["n_visible"] = select_rendered(proj, request.budget)
    stats["n_rendered"] = int(sel.numel())
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
        proj.radii[take], width, height, background=bg, with_depth=with_depth, sort_keys=keys)
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
    from .rasterize_cpu import composite_np

    width, height = camera.width, camera.height
    outputs = set(request.outputs)
    dtype = g.means.dtype
    t0 = time.perf_counter()
    means, opac = _np32(g.means), _np32(g.opacities)
    m2, co, de, rad, op = project_np(means, _np32(g.quats), _np32(g.scales), opac,
                                     camera.viewmat(), camera.K, width, height, NEAR_PLANE,
                                     request.antialiased)
    stats["n_visible"], keep = drop_over_budget_np(co, op, rad, request.budget)
    stats["n_rendered"] = keep
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
    out, T, _ = composite_np(m2, co, op, feats, keys, rad, width, height, bg)
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
