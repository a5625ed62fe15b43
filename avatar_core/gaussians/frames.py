"""Per-triangle frames (R, T, k) of a posed mesh: the binding of GaussianAvatars.

R's columns: the first edge's direction, the in-plane perpendicular, the face normal
(orthonormal and right-handed by construction). T: the centroid. k: the mean of the first
edge's length and the triangle's height on that edge.

Degenerate triangles (a zero-length first edge, collinear or coincident corners) still get a
finite orthonormal frame: the edge direction falls back to the longest edge, then to +x; the
normal falls back to an axis perpendicular to the edge when the corners are collinear (the
sine of the angle at v0 below `COLLINEAR_SIN`). k is floored at `MIN_SCALE`, so a
collapsed triangle carries its Gaussians as tiny splats, never as NaN.
"""

from __future__ import annotations

import torch
from torch import Tensor

MIN_SCALE = 1e-8
COLLINEAR_SIN = 1e-6  # corners whose angle's sine is below this count as collinear
_TINY = 1e-30  # inside sqrt: keeps the norm's gradient finite at zero


def _norm(x: Tensor) -> Tensor:
    return torch.sqrt((x * x).sum(-1, keepdim=True) + _TINY)


def _unit_or(x: Tensor, fallback: Tensor, eps: float) -> Tensor:
    """x normalised where it is longer than eps, else `fallback` (already unit)."""
    n = _norm(x)
    return torch.where(n > eps, x / n.clamp(min=eps), fallback)


def _perpendicular(u: Tensor) -> Tensor:
    """A unit vector perpendicular to unit u: cross with the axis least aligned to it."""
    axes = torch.eye(3, dtype=u.dtype, device=u.device)
    ref = axes[u.abs().argmin(-1)]  # [..., 3]
    p = torch.cross(u, ref, dim=-1)
    return p / _norm(p)


def triangle_frames(vertices: Tensor, faces: Tensor, eps: float = 1e-12
                    ) -> tuple[Tensor, Tensor, Tensor]:
    """Frames of every triangle. vertices [..., V, 3], faces [F, 3]
    -> R [..., F, 3, 3], T [..., F, 3], k [..., F]."""
    v0, v1, v2 = (vertices[..., faces[:, i], :] for i in range(3))  # [..., F, 3]
    e01, e02, e12 = v1 - v0, v2 - v0, v2 - v1
    x_axis = torch.zeros_like(e01)
    x_axis[..., 0] = 1.0
    lengths = torch.cat([_norm(e01), _norm(e02), _norm(e12)], -1)  # [..., F, 3]
    longest = torch.stack([e01, e02, e12], -2).gather(
        -2, lengths.argmax(-1)[..., None, None].expand(*e01.shape[:-1], 1, 3))[..., 0, :]
    edge = _unit_or(e01, _unit_or(longest, x_axis, eps), eps)
    cross = torch.cross(e01, e02, dim=-1)
    # Collinear or coincident corners: |e01 x e02| is rounding noise (fused multiply-adds leave
    # ~1e-17, not 0), so test it against |e01| |e02| (the sine of the corner angle), not an
    # absolute epsilon; the noise would otherwise pick an arbitrary normal.
    cross_sq = (cross * cross).sum(-1, keepdim=True)
    span_sq = (e01 * e01).sum(-1, keepdim=True) * (e02 * e02).sum(-1, keepdim=True)
    flat = cross_sq <= COLLINEAR_SIN**2 * span_sq
    normal = torch.where(flat, _perpendicular(edge), cross / _norm(cross))
    # Re-orthogonalise: with a fallback edge the raw normal may not be perpendicular to it.
    normal = normal - (normal * edge).sum(-1, keepdim=True) * edge
    normal = _unit_or(normal, _perpendicular(edge), eps)
    binormal = torch.cross(normal, edge, dim=-1)
    rot = torch.stack([edge, binormal, normal], -1)  # columns
    centroid = (v0 + v1 + v2) / 3.0
    edge_len = _norm(e01)[..., 0]
    height = _norm(cross)[..., 0] / edge_len.clamp(min=eps)
    scale = (0.5 * (edge_len + height)).clamp(min=MIN_SCALE)
    return rot, centroid, scale
