"""The quality budget: which of the visible Gaussians are composited, shared by every backend.

``RenderRequest.budget`` keeps all visible Gaussians (``None``), the ``K`` most important
(an int) or a fraction of the visible ones (a float in (0, 1], rounded up). Importance is
opacity x 3-sigma footprint area in px^2; ties keep the lower index.

The render cost bound uses the same rule: with each splat's (Gaussian, tile) pairs
(:mod:`cost`) and a bound ``max_pairs``, the least important splats are dropped until the
pairs of the rest fit, i.e. what is kept is the longest run of the most important ones whose
pairs sum to at most ``max_pairs`` (and at most the budget's ``K``). So a frame over its cost
bound is degraded the way a quality budget degrades it, never allocated unbounded.

:func:`select_rendered` is the torch reference (the torch and gsplat backends),
:func:`drop_over_budget_np` its numpy twin for the cpu backend's no-gradient path, and
:func:`kept_within_pairs` the selection as a device-side mask (gsplat's training step, which
reads nothing back to the host); tests check that they choose the same set.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from .projection import Projected

__all__ = ["budget_count", "drop_over_budget_np", "footprint_area", "kept_within_pairs",
           "select_rendered"]

_DET_FLOOR = 1e-30  # conic determinants are floored here before the square root (no Inf area)


def budget_count(budget: int | float | None, n_visible: int) -> int:
    """How many of ``n_visible`` Gaussians the budget keeps."""
    if budget is None:
        return n_visible
    if isinstance(budget, float):
        return min(n_visible, math.ceil(budget * n_visible))
    return min(n_visible, budget)


def footprint_area(conics: Tensor) -> Tensor:
    """Area in px^2 of the 3-sigma ellipse of each conic [..., 3] (``9 pi sqrt(det cov2d)``)."""
    det_conic = (conics[..., 0] * conics[..., 2] - conics[..., 1] ** 2).clamp_min(_DET_FLOOR)
    return 9.0 * math.pi / torch.sqrt(det_conic)


def _importance(proj: Projected) -> Tensor:
    """[N] opacity x 3-sigma footprint area (px^2), detached."""
    return (proj.opacities * footprint_area(proj.conics)).detach()


def select_rendered(proj: Projected, budget: int | float | None,
                    pairs: Tensor | None = None,
                    max_pairs: int | None = None) -> tuple[Tensor, int]:
    """Indices [K] (ascending) of the Gaussians to composite, and the number visible: all
    visible ones, or the ``budget`` most important (opacity x 3-sigma footprint area; ties
    keep the lower index). With ``pairs`` [N] (``cost.tile_pairs``) and ``max_pairs``, also
    at most as many of the most important as fit in ``max_pairs`` pairs."""
    sel = torch.nonzero(proj.valid).squeeze(1)  # [V]
    n_visible = int(sel.numel())
    keep = budget_count(budget, n_visible)
    over = (pairs is not None and max_pairs is not None
            and int(pairs[sel].sum()) > max_pairs)
    if keep < n_visible or over:
        order = torch.sort(_importance(proj)[sel], descending=True, stable=True).indices
        if over:
            fits = torch.cumsum(pairs[sel][order], 0) <= max_pairs  # [V], a prefix
            keep = min(keep, int(fits.sum()))
        sel = torch.sort(sel[order[:keep]]).values
    return sel, n_visible


def kept_within_pairs(proj: Projected, pairs: Tensor, max_pairs: int) -> Tensor:
    """[..., N] bool: :func:`select_rendered`'s choice without a budget, as a mask computed on
    the device with no host read: the visible Gaussians, less the least important ones whose
    pairs do not fit in ``max_pairs``. Leading dimensions (cameras) are independent rows."""
    importance = torch.where(proj.valid, _importance(proj),
                             torch.full_like(proj.opacities, -torch.inf).detach())
    order = torch.sort(importance, dim=-1, descending=True, stable=True).indices  # [..., N]
    cost = torch.where(proj.valid, pairs, torch.zeros_like(pairs)).gather(-1, order)
    fits = torch.zeros_like(proj.valid).scatter(-1, order, torch.cumsum(cost, -1) <= max_pairs)
    return proj.valid & fits


def drop_over_budget_np(conics: np.ndarray, opacities: np.ndarray, radii: np.ndarray,
                        budget: int | float | None, pairs: np.ndarray | None = None,
                        max_pairs: int | None = None) -> tuple[int, int]:
    """The numpy twin of :func:`select_rendered` on the numba projection's outputs: sets
    ``radii`` to 0 (in place) for the visible Gaussians the budget, or the pair bound
    (``pairs`` [N] from ``cost.tile_pairs_np``, ``max_pairs``), drops.

    -> ``(n_visible, n_rendered)``.
    """
    vis = np.flatnonzero(radii > 0)
    keep = budget_count(budget, int(vis.size))
    over = pairs is not None and max_pairs is not None and int(pairs[vis].sum()) > max_pairs
    if keep < vis.size or over:
        c = conics[vis]
        area = 9.0 * np.pi / np.sqrt(np.maximum(c[:, 0] * c[:, 2] - c[:, 1] ** 2, _DET_FLOOR))
        order = np.argsort(-(opacities[vis] * area), kind="stable")
        if over:
            fits = np.cumsum(pairs[vis][order]) <= max_pairs  # a prefix
            keep = min(keep, int(fits.sum()))
        radii[vis[order[keep:]]] = 0
    return int(vis.size), keep
