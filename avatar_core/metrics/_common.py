"""Input checks and NaN-safe reductions shared by the metrics.

Every metric raises ``ValueError`` naming the argument for NaN/Inf values, non-float images
and shape mismatches, so a bad render is caught where it is measured, not three plots later.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor


def as_tensor(x: Any, name: str) -> Tensor:
    """A tensor view of a tensor or array-like (numpy arrays are shared, not copied)."""
    if isinstance(x, Tensor):
        return x
    try:
        arr = np.asarray(x)
        if arr.dtype == object:
            raise TypeError
        return torch.from_numpy(np.ascontiguousarray(arr))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name!r} must be a tensor or a numeric array, got "
                         f"{type(x).__name__}") from exc


def check_finite(name: str, t: Tensor) -> None:
    """Raise ``ValueError`` if ``t`` holds NaN or Inf."""
    if not t.numel():
        return
    # A finite sum proves every entry finite and is much cheaper than isfinite().all();
    # a non-finite sum may be overflow, so only then look element-wise.
    if not bool(torch.isfinite(t.detach().sum())) and not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name!r} contains NaN or Inf values")


def compute_dtype(*ts: Tensor) -> torch.dtype:
    """Common float dtype; half precision is promoted (the SSIM variances need the bits)."""
    dtype = ts[0].dtype
    for t in ts[1:]:
        dtype = torch.promote_types(dtype, t.dtype)
    return torch.float32 if dtype in (torch.float16, torch.bfloat16) else dtype


def as_image_pair(pred: Any, target: Any, *, pred_name: str = "pred",
                  target_name: str = "target", batched: bool | None = None,
                  ) -> tuple[Tensor, Tensor, bool]:
    """Images ``[H, W, C]`` or ``[B, H, W, C]`` -> ``([B, H, W, C], [B, H, W, C], batched)``.

    ``batched=True`` requires the 4-D layout (sequences). Images must be floating point
    (values in [0, 1]; integer images are refused rather than silently scaled).
    """
    out = []
    for x, name in ((pred, pred_name), (target, target_name)):
        t = as_tensor(x, name)
        if not t.is_floating_point():
            raise ValueError(f"{name!r} must be a float image in [0, 1], got dtype {t.dtype} "
                             "(divide 8-bit images by 255)")
        allowed = (4,) if batched else (3, 4)
        if t.ndim not in allowed or t.shape[-1] < 1 or 0 in t.shape:
            layout = "[T, H, W, C]" if batched else "[H, W, C] or [B, H, W, C]"
            raise ValueError(f"{name!r} must have shape {layout}, got {tuple(t.shape)}")
        check_finite(name, t)
        out.append(t)
    p, g = out
    if p.shape != g.shape:
        raise ValueError(f"{pred_name!r} and {target_name!r} must have the same shape, got "
                         f"{tuple(p.shape)} and {tuple(g.shape)}")
    is_batched = p.ndim == 4
    dtype = compute_dtype(p, g)
    p = p.to(dtype)
    g = g.to(dtype=dtype, device=p.device)
    if not is_batched:
        p, g = p[None], g[None]
    return p, g, is_batched


def as_mask(mask: Any, batch: int, height: int, width: int, like: Tensor,
            name: str = "mask") -> Tensor:
    """Weights ``[B, H, W]`` (``like``'s dtype and device) from a bool or float mask of shape
    ``[H, W]`` or ``[B, H, W]``. Weights must be finite and non-negative."""
    m = as_tensor(mask, name)
    if m.shape not in ((height, width), (batch, height, width)):
        raise ValueError(f"{name!r} must have shape [H, W] = {[height, width]} or [B, H, W] = "
                         f"{[batch, height, width]}, got {list(m.shape)}")
    if not (m.dtype == torch.bool or m.is_floating_point()):
        raise ValueError(f"{name!r} must be bool or float weights, got dtype {m.dtype}")
    m = m.to(dtype=like.dtype, device=like.device)
    check_finite(name, m)
    if bool((m < 0).any()):
        raise ValueError(f"{name!r} has negative weights")
    return m.expand(batch, height, width)


def weighted_mean(values: Tensor, weights: Tensor | None) -> Tensor:
    """Per-image mean of ``values [B, H, W]`` under ``weights [B, H, W]`` -> ``[B]``.

    An image whose weights are all zero gives NaN, with a zero (finite) gradient: the clamped
    denominator keeps the masked-out branch finite and ``where`` discards it.
    """
    if weights is None:
        return values.mean(dim=(1, 2))
    total = weights.sum(dim=(1, 2))  # [B]
    mean = (values * weights).sum(dim=(1, 2)) / total.clamp_min(torch.finfo(total.dtype).tiny)
    return torch.where(total > 0, mean, torch.full_like(mean, float("nan")))


def nan_mean(values: Tensor) -> Tensor:
    """Mean of the non-NaN entries (NaN if there are none), with finite gradients.

    ``torch.nanmean`` would send 0 * inf = NaN back through an all-NaN input.
    """
    valid = ~torch.isnan(values)
    count = valid.sum()
    total = torch.where(valid, values, torch.zeros_like(values)).sum()
    mean = total / count.clamp_min(1)
    return torch.where(count > 0, mean, torch.full_like(mean, float("nan")))


def reduce_images(per_image: Tensor, reduction: str, batched: bool) -> Tensor:
    """``'mean'``: mean over the images that are defined (not NaN); ``'none'``: ``[B]``
    (a 0-dim tensor for an unbatched input)."""
    if reduction == "mean":
        return nan_mean(per_image)
    if reduction == "none":
        return per_image if batched else per_image[0]
    raise ValueError(f"reduction must be 'mean' or 'none', got {reduction!r}")
