"""GaussianAvatars' position and scaling regularisers, in the parent triangle's local frame.

They keep each Gaussian near its triangle and no larger than it (MVFGA uses the same two):

    L_pos   = mean_i relu(||mu_i|| - eps_pos)                 eps_pos = 1,   lambda 0.01
    L_scale = mean_i || relu(exp(s_i) - eps_scale) ||_2       eps_scale = 0.6, lambda 1

with mu the local mean and s the local log-scale, both in units of the triangle's k, so
eps_pos = 1 lets a Gaussian sit about one triangle size from the centroid. These match
ShenhanQian/GaussianAvatars ``train.py`` (``metric_xyz`` / ``metric_scale`` False, the
defaults): ``F.relu(_xyz.norm(dim=1) - threshold_xyz).mean()`` and
``F.relu(torch.exp(_scaling) - threshold_scale).norm(dim=1).mean()``; the paper's
"||max(mu, eps_pos)||" is that hinge on the norm. Note the scale term is the norm over the
three axes of the per-axis hinge, then the mean over Gaussians (not an element-wise mean).

GaussianAvatars applies both only to the Gaussians visible in the current view
(``visibility_filter``), i.e. where the RGB loss acts. The caller does the same by passing
``weight``: a bool mask (mean over the selected Gaussians) or non-negative per-Gaussian
weights (weighted mean), e.g. the Gaussians visible in the pixels the RGB loss keeps.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["RegularizerWeights", "avatar_regularizers", "mask_loss", "position_loss",
           "scaling_loss"]

@dataclass(frozen=True)
class RegularizerWeights:
    """GaussianAvatars ``arguments/__init__.py``: lambda_xyz, threshold_xyz, lambda_scale,
    threshold_scale."""

    lambda_pos: float = 1e-2
    eps_pos: float = 1.0
    lambda_scale: float = 1.0
    eps_scale: float = 0.6


def _norm(x: Tensor) -> Tensor:
    # exactly 0 at 0 with a zero (not NaN) gradient there: torch masks norm_backward at 0
    return torch.linalg.vector_norm(x, dim=-1)


def _check(name: str, t: Tensor, finite: bool = True) -> None:
    if t.ndim != 2 or t.shape[1] != 3:
        raise ValueError(f"{name} must be [N, 3], got {list(t.shape)}")
    if finite and not bool(torch.isfinite(t.detach()).all()):
        raise ValueError(f"{name} contains NaN or Inf")


def _weighted_mean(per_gaussian: Tensor, weight: Tensor | None, check: bool = True) -> Tensor:
    """Mean of per_gaussian [N], weighted by ``weight`` [N] (bool or >= 0); 0 when nothing
    is selected (or N = 0), with the graph kept so backward still works."""
    if weight is None:
        if per_gaussian.numel() == 0:
            return per_gaussian.sum()
        return per_gaussian.mean()
    if weight.shape != per_gaussian.shape:
        raise ValueError(f"weight must have shape {list(per_gaussian.shape)}, got "
                         f"{list(weight.shape)}")
    w = weight.detach().to(per_gaussian)
    if check and (not bool(torch.isfinite(w).all()) or bool((w < 0).any())):
        raise ValueError("weight must be finite and >= 0")
    total, norm = (w * per_gaussian).sum(), w.sum()
    return torch.where(norm > 0, total / torch.where(norm > 0, norm, 1.0), total * 0.0)


def position_loss(local_means: Tensor, eps: float = 1.0,
                  weight: Tensor | None = None, *, check: bool = True) -> Tensor:
    """``mean(relu(||local_mean|| - eps))``; zero inside the eps ball. [N, 3] -> [].
    ``check=False`` skips the NaN/Inf scans (host round trips on CUDA)."""
    _check("local_means", local_means, check)
    return _weighted_mean(torch.relu(_norm(local_means) - eps), weight, check)


def scaling_loss(log_scales: Tensor, eps: float = 0.6,
                 weight: Tensor | None = None, *, check: bool = True) -> Tensor:
    """``mean(||relu(exp(log_scale) - eps)||)``; zero when every axis is <= eps. [N, 3] ->
    []."""
    _check("log_scales", log_scales, check)
    return _weighted_mean(_norm(torch.relu(torch.exp(log_scales) - eps)), weight, check)


def avatar_regularizers(local_means: Tensor, log_scales: Tensor, weight: Tensor | None = None,
                        config: RegularizerWeights = RegularizerWeights(),  # noqa: B008
                        *, check: bool = True) -> dict[str, Tensor]:
    """The weighted terms to add to the loss: ``{"pos": lambda_pos L_pos, "scale":
    lambda_scale L_scale}`` (GaussianAvatars' ``losses['xyz']`` and ``losses['scale']``)."""
    return {
        "pos": config.lambda_pos * position_loss(local_means, config.eps_pos, weight,
                                                 check=check),
        "scale": config.lambda_scale * scaling_loss(log_scales, config.eps_scale, weight,
                                                    check=check),
    }


def mask_loss(alpha: Tensor, mask: Tensor, weight: Tensor) -> Tensor:
    """Weighted mean |rendered alpha - mask| over the view (both [h, w])."""
    return ((alpha - mask).abs() * weight).sum() / weight.sum().clamp(min=1e-8)
