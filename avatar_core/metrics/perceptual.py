"""LPIPS, only when it can run offline.

``lpips_metric()`` returns a callable when the ``lpips`` package, torchvision and the
backbone's ImageNet weights are all on local disk, else ``None`` after logging one line
``LPIPS off: <reason>``. Nothing is ever downloaded: the backbone weights must already be in
torch hub's checkpoint cache (``$TORCH_HOME/hub/checkpoints``, where torchvision keeps them),
and the LPIPS linear heads ship inside the ``lpips`` package.
"""

from __future__ import annotations

import importlib.util
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from ._common import as_image_pair, reduce_images

__all__ = ["BACKBONE_WEIGHTS", "lpips_metric", "lpips_unavailable_reason"]

log = logging.getLogger(__name__)

# torchvision's checkpoint file for each LPIPS backbone (what `pretrained=True` loads).
BACKBONE_WEIGHTS = {
    "alex": "alexnet-owt-7be5be79.pth",
    "vgg": "vgg16-397923af.pth",
    "squeeze": "squeezenet1_1-b8a52dc0.pth",
}


def _module_available(name: str) -> bool:
    return importlib.util.find_spec(name) is not None


def _checkpoint_dir() -> Path:
    return Path(torch.hub.get_dir()) / "checkpoints"


def lpips_unavailable_reason(net: str = "alex") -> str | None:
    """Why LPIPS with backbone ``net`` cannot run offline here, or ``None`` if it can.
    Imports nothing heavy and touches no network."""
    if net not in BACKBONE_WEIGHTS:
        raise ValueError(f"net must be one of {sorted(BACKBONE_WEIGHTS)}, got {net!r}")
    if not _module_available("lpips"):
        return "the 'lpips' package is not installed"
    if not _module_available("torchvision"):
        return "torchvision (LPIPS's backbones) is not installed"
    heads = _lpips_heads_file(net)
    if heads is None or not heads.is_file():
        return f"the lpips package has no linear-head weights for {net!r}"
    backbone = _checkpoint_dir() / BACKBONE_WEIGHTS[net]
    if not backbone.is_file():
        return f"backbone weights {backbone} are not cached (no download is attempted)"
    return None


def _lpips_heads_file(net: str) -> Path | None:
    spec = importlib.util.find_spec("lpips")
    if spec is None or spec.origin is None:
        return None
    return Path(spec.origin).parent / "weights" / "v0.1" / f"{net}.pth"


def lpips_metric(net: str = "alex", device: Any = None,
                 ) -> Callable[..., Tensor] | None:
    """``fn(pred, target, *, reduction='mean') -> Tensor`` computing LPIPS on images in [0, 1]
    (``[H, W, 3]`` or ``[B, H, W, 3]``), or ``None`` with one logged ``LPIPS off`` line."""
    reason = lpips_unavailable_reason(net)
    if reason is not None:
        log.warning("LPIPS off: %s", reason)
        return None
    import lpips  # optional dependency, checked above

    device = torch.device("cpu" if device is None else device)
    model = lpips.LPIPS(net=net, verbose=False).eval().to(device)
    for p in model.parameters():
        p.requires_grad_(False)

    def fn(pred: Any, target: Any, *, reduction: str = "mean") -> Tensor:
        p, g, batched = as_image_pair(pred, target)
        # lpips wants [B, 3, H, W]; normalize=True maps [0, 1] to its [-1, 1].
        p = p.permute(0, 3, 1, 2).to(device)
        g = g.permute(0, 3, 1, 2).to(device)
        per_image = model(p, g, normalize=True).reshape(-1)  # [B]
        return reduce_images(per_image, reduction, batched)

    return fn
