"""The training iteration on CUDA, with no host round trip.

:meth:`Trainer._fit` decides on the host whether a view is skipped (``float(loss)`` and a
finite-gradient check: two waits for the GPU per iteration) and the rasterizer, the
regularisers and the density statistics each scan their inputs for NaN (more waits). Here the
same iteration stays on the device:

* the scans are off (``check_finite=False`` / ``check=False`` / ``validate=False``): their job
  is done by the guard below, which keeps a non-finite step from ever reaching the model;
* the guard ``ok = isfinite(loss) & isfinite(sum of every gradient)`` is a device tensor;
  both Adam optimisers are torch's fused kernels, which take ``found_inf = !ok`` and leave
  parameters, moments and step count untouched when it is set (GradScaler's mechanism), and
  the density statistics count the view only where ``ok``;
* loss, psnr and skips are tallied on the device (:class:`DeviceTally`) and read only when
  the trainer reports progress or checkpoints (every ``progress_interval`` iterations).

Densification and pruning run on the device tensors on their own schedule (every
``densify.interval`` iterations; their few counts are read then). The result is the CPU
path's iteration except for when a skipped view is logged (at the next report, as a count).
"""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from ..render.rasterize import rasterize
from ..render.types import RenderRequest
from .density import screen_grad_norm, screen_visibility
from .photometric import photometric_loss_fast
from .posing import world_gaussians
from .regularizers import avatar_regularizers, mask_loss

if TYPE_CHECKING:
    from .data import TrainView
    from .trainer import StepResult, Trainer

log = logging.getLogger(__name__)

__all__ = ["DeviceTally", "fit_on_device"]


class DeviceTally:
    """Loss sum, steps taken and views skipped since the last read, kept on the device."""

    def __init__(self, device: torch.device) -> None:
        zero = torch.zeros((), dtype=torch.float64, device=device)
        self.loss_sum, self.steps, self.skipped = zero.clone(), zero.clone(), zero.clone()

    def add(self, loss: Tensor, ok: Tensor) -> None:
        self.loss_sum += torch.where(ok, loss.detach().double(), 0.0)
        self.steps += ok.double()
        self.skipped += (~ok).double()

    def take(self) -> tuple[float, int, int]:
        """(loss sum, steps taken, views skipped) since the last take: the one host read of
        a reporting interval."""
        loss_sum, steps, skipped = torch.stack([self.loss_sum, self.steps,
                                                self.skipped]).tolist()
        for t in (self.loss_sum, self.steps, self.skipped):
            t.zero_()
        return loss_sum, int(steps), int(skipped)


def fit_on_device(tr: Trainer, view: TrainView, it: int) -> StepResult | None:
    """:meth:`Trainer._fit` without a host read (see the module docstring): the skip's result
    when the view has nothing to learn from, else None (stepped or skipped on the device; the
    loss is in ``tr.tally`` until the next report)."""
    cfg = tr.config
    if view.weight_sum <= 0:  # a host float of the prepared view: no device read
        return tr._skip("empty loss mask (only masked-out pixels)", view)
    frames = tr._frames(view.key.sequence, view.key.frame)
    tr._posed_k = frames.scale.detach()
    gaussians = world_gaussians(tr.state, frames, cfg.active_sh_degree(it))
    gaussians.means.retain_grad()
    background = tr.background(it)
    view = replace(view, target=view.on_background(background), background=background)
    request = RenderRequest(outputs=tr._outputs(view), background=background)
    out = rasterize(gaussians, view.camera, request, check_finite=False)
    pred = out.rgb  # [h, w, 3]
    visible, radii = screen_visibility(gaussians, view.camera, validate=False)  # [N], [N]
    loss = photometric_loss_fast(pred, view.target, view.weight, cfg.loss.lambda_dssim)
    if tr.lpips is not None:
        keep = view.weight[..., None] > 0
        loss = loss + cfg.loss.lambda_lpips * tr.lpips(torch.where(keep, pred, view.target),
                                                       view.target)
    if out.alpha is not None:
        loss = loss + cfg.loss.lambda_mask * mask_loss(out.alpha, view.alpha, view.weight)
    reg = avatar_regularizers(tr.state["local_means"], tr.state["log_scales"],
                              weight=visible, config=tr.regularizer, check=False)
    loss = loss + reg["pos"] + reg["scale"]
    loss.backward()
    grads = [t.grad.sum() for t in tr._leaves() if t.grad is not None]
    ok = torch.isfinite(loss.detach())
    if grads:
        ok = ok & torch.isfinite(torch.stack(grads).sum())
    with torch.no_grad():
        if cfg.densify.enabled and it < cfg.densify.until_iter:
            grad = screen_grad_norm(gaussians.means, gaussians.means.grad, view.camera)
            tr.stats.update(grad, visible & ok, radii, check=False)
        found_inf = (~ok).to(torch.float32)
        for optimizer in (tr.optimizer, tr.param_optimizer):
            if optimizer is not None:
                optimizer.found_inf = found_inf  # read by the fused kernel: skip when set
                optimizer.step()
    tr._drop_grads()
    tr._last = (pred.detach(), view)
    tr.tally.add(loss, ok)
    return None
