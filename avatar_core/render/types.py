"""What goes into the rasterizer and what comes out: shared by every backend and caller."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from .sh import sh_degree_from_bases

OUTPUTS = ("rgb", "alpha", "depth")
BACKENDS = ("auto", "torch", "cpu", "gsplat")


@dataclass
class GaussianSet:
    """World-space Gaussians, ready to render (derived from an avatar each frame)."""

    means: Tensor       # [N, 3] world positions
    quats: Tensor       # [N, 4] (w, x, y, z), normalised inside the rasterizer
    scales: Tensor      # [N, 3] linear standard deviations (not log)
    opacities: Tensor   # [N] in [0, 1] (rendering clamps them there)
    sh: Tensor          # [N, K, 3] SH coefficients, K = (degree + 1) ** 2, K in {1, 4, 9, 16}

    @property
    def num(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_bases(self.sh.shape[1])


@dataclass(frozen=True)
class RenderRequest:
    """The effects a caller asks for; only these are computed."""

    outputs: tuple[str, ...] = ("rgb",)            # any of OUTPUTS
    width: int | None = None                       # None: the camera's size
    height: int | None = None
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    sh_degree: int | None = None                   # None: all the Gaussians carry
    # K most important Gaussians (int), or a fraction (float in (0, 1]) of the visible ones.
    budget: int | float | None = None
    antialiased: bool = False                      # opacity compensation (Mip-Splatting)
    backend: str = "auto"                          # BACKENDS
    # Most (Gaussian, tile) pairs the frame may composite (render/cost.py); past it the least
    # important splats are dropped until the rest fit. None: contract.MAX_TILE_PAIRS.
    max_tile_pairs: int | None = None


@dataclass
class RenderOutput:
    # [H, W, 3] float32; SH colours are clamped at 0 only (as in 3DGS), so clamp for display.
    rgb: Tensor | None = None
    alpha: Tensor | None = None   # [H, W]
    depth: Tensor | None = None   # [H, W] expected camera z (alpha-weighted mean), 0 where empty
    # backend, n_gaussians, n_visible, n_rendered (after the budget and the pair bound),
    # tile_pairs (of the rendered splats' radius boxes, cost.tile_pairs), n_cost_dropped
    # (visible splats the pair bound dropped), cpu: pairs_allocated (its tile lists);
    # timings in ms
    stats: dict = field(default_factory=dict)


def background_output(request: RenderRequest, width: int, height: int, dtype: torch.dtype,
                      device: torch.device, stats: dict, t_start: float) -> RenderOutput:
    """Nothing to composite (every backend's answer): the background, alpha 0, depth 0."""
    stats["color_ms"] = stats["raster_ms"] = 0.0
    stats["total_ms"] = (time.perf_counter() - t_start) * 1e3
    outputs = set(request.outputs)
    bg = torch.tensor(request.background, dtype=dtype, device=device)
    zeros = torch.zeros(height, width, dtype=dtype, device=device)
    return RenderOutput(rgb=bg.expand(height, width, 3).clone() if "rgb" in outputs else None,
                        alpha=zeros if "alpha" in outputs else None,
                        depth=zeros.clone() if "depth" in outputs else None, stats=stats)


def to_uint8(image: Tensor) -> np.ndarray:
    """A float image in [0, 1] (rgb [H, W, 3] or alpha [H, W], clamped here) as uint8 numpy,
    rounded to nearest, for display and encoding."""
    # one new tensor, rounded in place: half the time of four chained copies, same bytes
    scaled = image.detach().mul(255)
    return scaled.clamp_(0, 255).round_().to(torch.uint8).cpu().numpy()
