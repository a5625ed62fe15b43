"""The quality budget: which of the visible Gaussians are composited, shared by every backend.

``RenderRequest.budget`` keeps all visible Gaussians (``None``), the ``K`` most important
(an int) or a fraction of the visible ones (a float in (0, 1], rounded up). Importance is
opacity x 3-sigma footprint area in px^2; ties keep the lower index. :func:`select_rendered`
is the torch reference (the torch and gsplat backends), :func:`drop_over_budget_np` its numpy
twin for the cpu backend's no-gradient path; a test checks that they choose the same set.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from .projection import Projected

__all__ = ["budget_count", "drop_over_budget_np", "footprint_area", "select_rendered"]

_DET_FLOOR = 1e-30  # conic determinants are floored here before the square root (no Inf area)


def budget_count(budget: int | float | None, n_visible: int) -> int:
    """How many of ``n_visible`` Gaussians the budget keeps."""
    if budget is None:
        return n_visible
    if isinstance(budget, float):
        return min(n_visible, math.ceil(budget * n_visible))
    return min(n_visible, budget)


def footprint_area(conics: Tensor) -> Tensor:
    """Area in px^2 of the 3-sigma ellipse of each conic [N, 3] (``9 pi sqrt(det cov2d)``)."""
    det_conic = (conics[:, 0] * conics[:, 2] - conics[:, 1] ** 2).clamp_min(_DET_FLOOR)
    return 9.0 * math.pi / torch.sqrt(det_conic)


def select_rendered(proj: Projected, budget: int | float | None) -> tuple[Tensor, int]:
    """Indices [K] (ascending) of the Gaussians to composite, and the number visible: all
    visible ones, or the ``budget`` most important (opacity x 3-sigma footprint area; ties
    keep the lower index)."""
    sel = torch.nonzero(proj.valid).squeeze(1)  # [V]
    n_visible = int(sel.numel())
    keep = budget_count(budget, n_visible)
    if keep < n_visible:
        importance = (proj.opacities * footprint_area(proj.conics))[sel].detach()
        order = torch.sort(importance, descending=True, stable=True).indices[:keep]
        sel = torch.sort(sel[order]).values
    return sel, n_visible


def drop_over_budget_np(conics: np.ndarray, opacities: np.ndarray, radii: np.ndarray,
                        budget: int | float | None) -> tuple[int, int]:
    """The numpy twin of :func:`select_rendered` on the numba projection's outputs: sets
    ``radii`` to 0 (in place) for the visible Gaussians the budget drops.

    -> ``(n_visible, n_rendered)``.
    """
    vis = np.flatnonzero(radii > 0)
    keep = budget_count(budget, int(vis.size))
    if keep < vis.size:
        c = conics[vis]
        area = 9.0 * np.pi / np.sqrt(np.maximum(c[:, 0] * c[:, 2] - c[:, 1] ** 2, _DET_FLOOR))
        order = np.argsort(-(opacities[vis] * area), kind="stable")
        radii[vis[order[keep:]]] = 0
    return int(vis.size), keep
