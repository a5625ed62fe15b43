"""Temporal jitter error (TJE): flicker a render adds on top of the real motion.

For a rendered sequence ``pred`` and the ground truth ``gt``, both ``[T, H, W, C]``::

    TJE = 1 / (T - 1) * sum_{t=0}^{T-2} mean_pixels | (pred[t+1] - pred[t]) - (gt[t+1] - gt[t]) |

i.e. the L1 distance between the frame-to-frame changes of the render and of the ground
truth, averaged over pixels and channels, then over the T - 1 frame pairs. A render that is
wrong by the same amount in every frame (a constant offset) has TJE 0: only *changes* that
the ground truth does not make count. A render alternating ``gt + a``, ``gt - a`` scores
``2a``. Units are those of the images (intensity in [0, 1]).

With a ``mask`` (``[H, W]``, or ``[T, H, W]`` per frame; bool or non-negative weights), pair
``(t, t+1)`` is averaged under ``max(mask[t], mask[t+1])``: a pixel counts when it is in
either frame's mask, so flicker at a moving silhouette's edge is included. A pair with an
empty mask is skipped; TJE is NaN when every pair is empty.

``keypoint_tje`` is the same on 2-D keypoint tracks ``[T, K, 2]``, with the Euclidean norm
(pixels) instead of L1: the mean over pairs and keypoints of
``|| (pred[t+1] - pred[t]) - (gt[t+1] - gt[t]) ||``, counting a keypoint in pair
``(t, t+1)`` only where it is visible in both frames (NaN if none is).

Fewer than 2 frames raise ``ValueError``; so do NaN/Inf inputs and shape mismatches.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from ._common import as_image_pair, as_mask, as_tensor, check_finite, nan_mean, weighted_mean

__all__ = ["keypoint_tje", "tje"]


def _check_frames(num_frames: int) -> None:
    if num_frames < 2:
        raise ValueError(f"TJE needs at least 2 frames, got T={num_frames}")


def tje(pred: Any, gt: Any, mask: Any = None) -> Tensor:
    """Temporal jitter error of image sequences ``[T, H, W, C]`` (0-dim tensor,
    differentiable in ``pred``)."""
    p, g, _ = as_image_pair(pred, gt, target_name="gt", batched=True)
    t, h, w, _ = p.shape
    _check_frames(t)
    jitter = ((p[1:] - p[:-1]) - (g[1:] - g[:-1])).abs().mean(dim=-1)  # [T-1, H, W]
    weights = None
    if mask is not None:
        m = as_mask(mask, t, h, w, p)  # [T, H, W]
        weights = torch.maximum(m[1:], m[:-1])  # [T-1, H, W]
    return nan_mean(weighted_mean(jitter, weights))


def keypoint_tje(pred: Any, gt: Any, visible: Any = None) -> float:
    """Temporal jitter error of 2-D keypoint tracks ``[T, K, 2]`` in pixels."""
    p = as_tensor(pred, "pred")
    g = as_tensor(gt, "gt")
    for x, name in ((p, "pred"), (g, "gt")):
        if x.ndim != 3 or x.shape[-1] != 2 or not x.is_floating_point():
            raise ValueError(f"{name!r} must be float keypoint tracks [T, K, 2], got "
                             f"{tuple(x.shape)} {x.dtype}")
    if p.shape != g.shape:
        raise ValueError(f"'pred' and 'gt' must have the same shape, got {tuple(p.shape)} "
                         f"and {tuple(g.shape)}")
    _check_frames(p.shape[0])
    dtype = torch.promote_types(p.dtype, g.dtype)
    p, g = p.detach().to(dtype), g.detach().to(dtype=dtype, device=p.device)
    if visible is None:
        vis = torch.ones(p.shape[:-1], dtype=torch.bool, device=p.device)
    else:
        vis = as_tensor(visible, "visible").to(p.device)
        if vis.dtype != torch.bool or vis.shape != p.shape[:-1]:
            raise ValueError(f"'visible' must be bool [T, K] = {list(p.shape[:-1])}, got "
                             f"{list(vis.shape)} {vis.dtype}")
    # Invisible keypoints may hold NaN (e.g. behind the camera): check only what is used.
    check_finite("pred", p[vis])
    check_finite("gt", g[vis])
    pair = vis[1:] & vis[:-1]  # [T-1, K]
    jitter = (p[1:] - p[:-1]) - (g[1:] - g[:-1])  # [T-1, K, 2]
    dist = torch.linalg.vector_norm(jitter[pair], dim=-1)  # [N]
    return float(dist.mean()) if len(dist) else float("nan")
