"""Adapter to gsplat's CUDA rasterizer (``gsplat.rasterization``), imported lazily.

Maps a :class:`RenderRequest` onto gsplat's arguments: pinhole camera, near plane 0.01, far
plane 1e10, eps2d 0.3, 16 px tiles, SH evaluated by gsplat (``colors`` = coefficients with
``sh_degree``: ``max(SH + 0.5, 0)``, the same convention), ``rasterize_mode="antialiased"``
for ``antialiased``, ``render_mode`` "RGB" / "RGB+ED" / "ED" (expected depth, 0 where alpha
is 0) and the background for the colour channels only. A ``budget`` is applied before the
call, with the shared importance (opacity x 3-sigma footprint area, from our projection).
So is the render cost bound (``max_tile_pairs``, :mod:`cost`): the (Gaussian, tile) pairs of
our projection's radius boxes, with the least important splats dropped until they fit
(without a budget as a device-side mask, :func:`budget.kept_within_pairs`: no host read).
gsplat bins what it is given with its own radius, which is no wider than ours (recent
releases: opacity-aware and per axis), so its lists hold at most that many pairs; this is
argued, not measured here (no CUDA in the test environment).

gsplat's kernels get only what our projection keeps (visible, sane: see
:mod:`projection`), unit quaternions (a zero one as the identity) and SH coefficients clamped
to ``+-SH_COEFF_MAX``, so an absurd but finite Gaussian cannot reach its float32 tile and
colour arithmetic (overflowing tile ranges, Inf or NaN colours).

Known differences from the contract that gsplat itself fixes: it clamps alpha at 0.999
(3DGS and our other backends: 0.99), and recent releases bound each splat's tiles with an
opacity-aware, per-axis radius. Pictures agree closely, not to float rounding.

Several cameras (:func:`rasterize_gsplat_views`, behind ``render_views``): one gsplat call
with one batch entry per camera (``viewmats [C, 1, 4, 4]``, ``Ks [C, 1, 3, 3]``) over the
union of the Gaussians any camera keeps; a Gaussian that camera ``c`` does not keep (culled
by our projection or dropped by the budget) sits at camera ``c``'s centre with opacity 0 in
entry ``c``, which gsplat's near-plane test culls first, so each picture is the single-camera
one. Costs ``C`` copies of that union
on the device (gsplat makes the broadcast contiguous). All cameras must share one size.

Pinned: the ``cuda`` extra's ``gsplat==1.5.3`` (batch dimensions on every argument).
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import torch

from .budget import kept_within_pairs, select_rendered
from .camera import Camera
from .contract import EPS2D, FAR_PLANE, NEAR_PLANE, SH_COEFF_MAX, TILE_SIZE
from .cost import pair_bound, tile_pairs
from .projection import Projected, project_gaussians
from .types import GaussianSet, RenderOutput, RenderRequest, background_output

__all__ = ["available", "gsplat_arguments", "gsplat_views_arguments", "rasterize_gsplat",
           "rasterize_gsplat_views"]


def available() -> bool:
    """gsplat importable and a CUDA device present."""
    try:
        import gsplat  # noqa: F401
    except Exception:  # noqa: BLE001 (any import failure means: not available)
        return False
    return torch.cuda.is_available()


def _render_mode(outputs: set[str]) -> str:
    if "rgb" in outputs:
        return "RGB+ED" if "depth" in outputs else "RGB"
    return "ED"  # alpha and/or depth only: one cheap channel


def gsplat_arguments(gaussians: GaussianSet, camera: Camera, request: RenderRequest,
                     sh_degree: int) -> dict:
    """Keyword arguments for ``gsplat.rasterization`` (exposed so it can be tested without
    CUDA)."""
    device, dtype = gaussians.means.device, gaussians.means.dtype
    viewmat, K = camera.to_torch(device, dtype)
    k = (sh_degree + 1) ** 2
    bg = torch.tensor(request.background, dtype=dtype, device=device)[None]  # [1, 3]
    mode = _render_mode(set(request.outputs))
    return dict(
        means=gaussians.means, quats=_unit_quats(gaussians.quats), scales=gaussians.scales,
        opacities=gaussians.opacities,
        colors=gaussians.sh[:, :k].clamp(-SH_COEFF_MAX, SH_COEFF_MAX), sh_degree=sh_degree,
        viewmats=viewmat[None], Ks=K[None], width=camera.width, height=camera.height,
        near_plane=NEAR_PLANE, far_plane=FAR_PLANE, eps2d=EPS2D, tile_size=TILE_SIZE,
        backgrounds=bg if mode != "ED" else None, render_mode=mode,
        rasterize_mode="antialiased" if request.antialiased else "classic",
        packed=False,
    )


def _unit_quats(quats: torch.Tensor) -> torch.Tensor:
    """Normalised after a max-abs rescale (a huge quaternion's norm overflows float32), the
    zero quaternion as the identity (``projection.quat_to_rotmat``'s rules)."""
    amax = quats.detach().abs().amax(-1, keepdim=True)
    q = quats / amax.clamp_min(1e-30)
    n = q.norm(dim=-1, keepdim=True)
    ident = torch.zeros_like(q)
    ident[:, 0] = 1.0
    return torch.where(amax * n > 1e-12, q / n.clamp_min(1e-12), ident)


def _apply_budget(gaussians: GaussianSet, camera: Camera,
                  request: RenderRequest) -> tuple[GaussianSet, int]:
    """The subset that our projection keeps and ``request.budget`` (if any) and the pair
    bound select (the shared importance rule)."""
    viewmat, K = camera.to_torch(gaussians.means.device, gaussians.means.dtype)
    with torch.no_grad():
        p = project_gaussians(gaussians.means, gaussians.quats, gaussians.scales,
                              gaussians.opacities, viewmat, K, camera.width, camera.height,
                              antialiased=request.antialiased, validate=False)
        pairs = tile_pairs(p.means2d, p.radii, camera.width, camera.height)
        sel, _ = select_rendered(p, request.budget, pairs, pair_bound(request.max_tile_pairs))
    sub = GaussianSet(*(t[sel] for t in (gaussians.means, gaussians.quats, gaussians.scales,
                                         gaussians.opacities, gaussians.sh)))
    return sub, int(sel.numel())


def _mask_culled(gaussians: GaussianSet, camera: Camera,
                 request: RenderRequest) -> tuple[GaussianSet, torch.Tensor]:
    """Every Gaussian, those our projection culls (or the pair bound drops) moved to the
    camera centre with opacity 0 (gsplat's first test, the near plane, drops them before
    any covariance arithmetic), and the kept count as a 0-d device tensor: no ``nonzero``,
    no gather, no host round trip (the training step on CUDA). Without a budget this keeps
    what :func:`_apply_budget` keeps."""
    device, dtype = gaussians.means.device, gaussians.means.dtype
    viewmat, K = camera.to_torch(device, dtype)
    with torch.no_grad():
        p = project_gaussians(gaussians.means, gaussians.quats, gaussians.scales,
                              gaussians.opacities, viewmat, K, camera.width, camera.height,
                              antialiased=request.antialiased, validate=False)
        pairs = tile_pairs(p.means2d, p.radii, camera.width, camera.height)
        kept = kept_within_pairs(p, pairs, pair_bound(request.max_tile_pairs))  # [N]
    keep = kept[:, None]  # [N, 1]
    centre = torch.as_tensor(camera.center, dtype=dtype, device=device)
    return GaussianSet(
        torch.where(keep, gaussians.means, centre), gaussians.quats,
        torch.where(keep, gaussians.scales, torch.ones_like(gaussians.scales)),
        gaussians.opacities * kept.to(dtype), gaussians.sh), kept.sum()


def rasterize_gsplat(gaussians: GaussianSet, camera: Camera, request: RenderRequest,
                     sh_degree: int, t_start: float) -> RenderOutput:
    """Render with gsplat (called by :func:`avatar_core.render.rasterize`). Without a budget
    no host round trip: ``stats["n_rendered"]`` is then a 0-d device tensor (``int()`` it)."""
    from gsplat import rasterization

    stats: dict = {"backend": "gsplat", "n_gaussians": gaussians.num}
    # always through our projection: gsplat never sees a Gaussian that it culls
    if request.budget is None:
        gaussians, stats["n_rendered"] = _mask_culled(gaussians, camera, request)
    else:
        gaussians, stats["n_rendered"] = _apply_budget(gaussians, camera, request)
        if stats["n_rendered"] == 0:
            return background_output(request, camera.width, camera.height,
                                     gaussians.means.dtype, gaussians.means.device, stats,
                                     t_start)
    outputs = set(request.outputs)
    t0 = time.perf_counter()
    colors, alphas, _ = rasterization(**gsplat_arguments(gaussians, camera, request,
                                                            sh_degree))
    colors, alphas = colors[0], alphas[0, ..., 0]  # [H, W, X], [H, W]
    stats["raster_ms"] = (time.perf_counter() - t0) * 1e3
    stats["total_ms"] = (time.perf_counter() - t_start) * 1e3
    rgb = colors[..., :3] if "rgb" in outputs else None
    depth = colors[..., -1] if "depth" in outputs else None
    return RenderOutput(rgb=rgb, alpha=alphas if "alpha" in outputs else None, depth=depth,
                        stats=stats)


def _kept_masks(gaussians: GaussianSet, cameras: Sequence[Camera],
                request: RenderRequest) -> torch.Tensor:
    """[C, N] bool: the Gaussians our projection keeps and the budget and the pair bound
    select, per camera (the single-camera rule of :func:`_apply_budget`). Without a budget,
    every camera at once (:func:`kept_masks_batched`); with one, camera by camera."""
    if request.budget is None:
        return kept_masks_batched(gaussians, cameras, request)
    n = gaussians.num
    masks = torch.zeros(len(cameras), n, dtype=torch.bool, device=gaussians.means.device)
    with torch.no_grad():
        for c, cam in enumerate(cameras):
            viewmat, K = cam.to_torch(gaussians.means.device, gaussians.means.dtype)
            p = project_gaussians(gaussians.means, gaussians.quats, gaussians.scales,
                                  gaussians.opacities, viewmat, K, cam.width, cam.height,
                                  antialiased=request.antialiased, validate=False)
            pairs = tile_pairs(p.means2d, p.radii, cam.width, cam.height)
            sel, _ = select_rendered(p, request.budget, pairs,
                                     pair_bound(request.max_tile_pairs))
            masks[c, sel] = True
    return masks


def kept_masks_batched(gaussians: GaussianSet, cameras: Sequence[Camera],
                       request: RenderRequest) -> torch.Tensor:
    """[C, N] bool: :func:`_mask_culled`'s kept set for every camera (one size, no budget),
    with the projection and the pair bound vectorised over the cameras (``torch.func.vmap``):
    one pass of kernels for all of them and no host read, instead of one pass and a read
    per camera. Equal to the camera-by-camera masks (tested)."""
    width, height = cameras[0].width, cameras[0].height
    device, dtype = gaussians.means.device, gaussians.means.dtype
    mats = [cam.to_torch(device, dtype) for cam in cameras]
    viewmats = torch.stack([v for v, _ in mats])  # [C, 4, 4]
    Ks = torch.stack([k for _, k in mats])  # [C, 3, 3]
    g = gaussians

    def one(viewmat: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, ...]:
        p = project_gaussians(g.means, g.quats, g.scales, g.opacities, viewmat, K, width,
                              height, antialiased=request.antialiased, validate=False)
        return (p.means2d, p.conics, p.depths, p.radii, p.opacities, p.valid,
                tile_pairs(p.means2d, p.radii, width, height))

    with torch.no_grad():
        *fields, pairs = torch.func.vmap(one)(viewmats, Ks)  # each [C, N, ...]
        return kept_within_pairs(Projected(*fields), pairs, pair_bound(request.max_tile_pairs))


def gsplat_views_arguments(gaussians: GaussianSet, cameras: Sequence[Camera],
                           request: RenderRequest, sh_degree: int) -> tuple[dict, torch.Tensor]:
    """Keyword arguments of one ``gsplat.rasterization`` call rendering every camera (same
    size), and the per-camera kept counts [C]; None arguments when no camera keeps any
    Gaussian. Exposed so the mapping is tested without CUDA."""
    width, height = cameras[0].width, cameras[0].height
    if any(cam.size != (width, height) for cam in cameras):
        raise ValueError("cameras of one gsplat call must share one image size")
    masks = _kept_masks(gaussians, cameras, request)  # [C, N]
    counts = masks.sum(1)  # [C]
    union = masks.any(0).nonzero().squeeze(1)  # [M]
    if union.numel() == 0:
        return {}, counts
    C, M = len(cameras), int(union.numel())
    g = gaussians
    single = gsplat_arguments(
        GaussianSet(g.means[union], g.quats[union], g.scales[union], g.opacities[union],
                    g.sh[union]), cameras[0], request, sh_degree)
    device, dtype = g.means.device, g.means.dtype
    views = [cam.to_torch(device, dtype) for cam in cameras]
    keep = masks[:, union]  # [C, M]
    # what camera c does not keep sits at its centre: culled at gsplat's near-plane test,
    # before any arithmetic on it (see _mask_culled)
    centres = torch.stack([torch.as_tensor(cam.center, dtype=dtype, device=device)
                           for cam in cameras])[:, None]  # [C, 1, 3]
    kw = dict(single)
    kw.update(
        means=torch.where(keep[..., None], single["means"], centres),  # [C, M, 3]
        quats=single["quats"].expand(C, M, 4),
        scales=torch.where(keep[..., None], single["scales"], 1.0),  # [C, M, 3]
        opacities=single["opacities"] * keep.to(dtype),  # [C, M]
        colors=single["colors"].expand(C, *single["colors"].shape),  # [C, M, K, 3]
        viewmats=torch.stack([v for v, _ in views])[:, None],  # [C, 1, 4, 4]
        Ks=torch.stack([k for _, k in views])[:, None],  # [C, 1, 3, 3]
        backgrounds=(None if single["backgrounds"] is None
                     else single["backgrounds"].expand(C, 1, 3)),  # [C, 1, 3]
    )
    return kw, counts


def rasterize_gsplat_views(gaussians: GaussianSet, cameras: Sequence[Camera],
                           request: RenderRequest, sh_degree: int,
                           t_start: float) -> list[RenderOutput]:
    """Every camera (one size) in one gsplat call (called by ``render_views``)."""
    from gsplat import rasterization

    outputs = set(request.outputs)
    width, height = cameras[0].width, cameras[0].height
    kw, counts = gsplat_views_arguments(gaussians, cameras, request, sh_degree)
    counts = counts.tolist()  # one host read for the whole batch
    t0 = time.perf_counter()
    if kw:
        colors, alphas, _ = rasterization(**kw)  # [C, 1, H, W, X], [C, 1, H, W, 1]
    raster_ms = (time.perf_counter() - t0) * 1e3
    results = []
    for c in range(len(cameras)):
        stats = {"backend": "gsplat", "n_gaussians": gaussians.num, "n_rendered": counts[c],
                 "n_views": len(cameras)}
        if not kw or counts[c] == 0:
            results.append(background_output(request, width, height, gaussians.means.dtype,
                                              gaussians.means.device, stats, t_start))
            continue
        stats["raster_ms"] = raster_ms  # of the whole batch
        stats["total_ms"] = (time.perf_counter() - t_start) * 1e3
        col, alpha = colors[c, 0], alphas[c, 0, ..., 0]  # [H, W, X], [H, W]
        results.append(RenderOutput(
            rgb=col[..., :3] if "rgb" in outputs else None,
            alpha=alpha if "alpha" in outputs else None,
            depth=col[..., -1] if "depth" in outputs else None, stats=stats))
    return results
