"""Real spherical harmonics, degrees 0-3, with the constants and sign convention of 3DGS.

Colour of a Gaussian seen along unit direction ``d`` (from the camera centre to the mean):
``rgb = max(sum_k Y_k(d) * coeffs[k] + 0.5, 0)`` (the +0.5 and the clamp are applied by the
rasterizer, :func:`sh_to_rgb`). Coefficient ``k`` follows the band order of the reference 3DGS
code: 0 | 1..3 | 4..8 | 9..15.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from .contract import SH_COEFF_MAX

__all__ = ["SH_C0", "eval_sh", "num_sh_bases", "rgb_to_sh0", "sh0_to_rgb",
           "sh_to_rgb"]

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
         0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def num_sh_bases(degree: int) -> int:
    return (degree + 1) ** 2


def sh_degree_from_bases(num_bases: int) -> int:
    """The SH degree whose basis has `num_bases` coefficients (1, 4, 9, 16 -> 0..3)."""
    return int(round(num_bases**0.5)) - 1


def _sh_bases(degree: int, dirs: Tensor) -> list[Tensor]:
    """The (degree + 1)^2 basis values at unit ``dirs [N, 3]``, each [N]."""
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree < 1:
        return out
    out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree < 2:
        return out
    xx, yy, zz = x * x, y * y, z * z
    xy, yz, xz = x * y, y * z, x * z
    out += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2.0 * zz - xx - yy), SH_C2[3] * xz,
            SH_C2[4] * (xx - yy)]
    if degree < 3:
        return out
    out += [
        SH_C3[0] * y * (3.0 * xx - yy),
        SH_C3[1] * xy * z,
        SH_C3[2] * y * (4.0 * zz - xx - yy),
        SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
        SH_C3[4] * x * (4.0 * zz - xx - yy),
        SH_C3[5] * z * (xx - yy),
        SH_C3[6] * x * (xx - 3.0 * yy),
    ]
    return out


def eval_sh(degree: int, coeffs: Tensor, dirs: Tensor) -> Tensor:
    """Evaluate SH of ``degree`` (0..3) with ``coeffs [N, K, 3]`` (K >= (degree + 1)^2; extra
    coefficients are ignored) along ``dirs [N, 3]`` (normalised here) -> [N, 3].

    Differentiable in both ``coeffs`` and ``dirs``; no +0.5 offset, no clamp.
    """
    if not 0 <= degree <= 3:
        raise ValueError(f"SH degree must be in 0..3, got {degree}")
    k = num_sh_bases(degree)
    if coeffs.ndim != 3 or coeffs.shape[1] < k:
        raise ValueError(f"coeffs must be [N, K>={k}, C] for degree {degree}, "
                         f"got {tuple(coeffs.shape)}")
    if degree == 0:  # the common case: no direction needed
        return SH_C0 * coeffs[:, 0]
    dirs = F.normalize(dirs, dim=-1)  # [N, 3]; zero stays zero
    bases = torch.stack(_sh_bases(degree, dirs), dim=-1)  # [N, k]
    return (bases[..., None] * coeffs[:, :k]).sum(dim=1)  # [N, 3]


def sh_to_rgb(degree: int, coeffs: Tensor, dirs: Tensor) -> Tensor:
    """3DGS colour: ``max(SH(dirs) + 0.5, 0)`` -> [N, 3], coefficients clamped to
    ``+-SH_COEFF_MAX``."""
    coeffs = coeffs.clamp(-SH_COEFF_MAX, SH_COEFF_MAX)
    return torch.clamp_min(eval_sh(degree, coeffs, dirs) + 0.5, 0.0)


def rgb_to_sh0(rgb: Tensor) -> Tensor:
    """DC coefficient that renders as ``rgb`` (any shape): ``(rgb - 0.5) / C0``."""
    return (rgb - 0.5) / SH_C0


def sh0_to_rgb(sh0: Tensor) -> Tensor:
    """Inverse of :func:`rgb_to_sh0`: ``sh0 * C0 + 0.5`` (no clamp)."""
    return sh0 * SH_C0 + 0.5
