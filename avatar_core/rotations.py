"""Quaternion helpers (w, x, y, z), batched and differentiable; shared by body and gaussians."""

from __future__ import annotations

import torch
from torch import Tensor


def matrix_to_quaternion(rot: Tensor) -> Tensor:
    """Rotation matrices to unit quaternions with w >= 0. [..., 3, 3] -> [..., 4].

    Picks the best-conditioned of Shepperd's four formulas, so it is stable at every angle.
    """
    m = rot
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    cand = torch.stack(
        [
            1 + m00 + m11 + m22,
            1 + m00 - m11 - m22,
            1 - m00 + m11 - m22,
            1 - m00 - m11 + m22,
        ],
        -1,
    )
    # sqrt with a zero (not infinite) derivative at 0: an unpicked candidate that is exactly 0
    # (e.g. at the identity) would otherwise turn the backward into inf * 0 = NaN.
    positive = cand > 0
    q_abs = torch.where(positive, torch.sqrt(torch.where(positive, cand, 1.0)), 0.0)
    # [..., 4] = 2 |w|, 2 |x|, 2 |y|, 2 |z|
    d21, d02, d10 = (
        m[..., 2, 1] - m[..., 1, 2],
        m[..., 0, 2] - m[..., 2, 0],
        m[..., 1, 0] - m[..., 0, 1],
    )
    s10, s02, s21 = (
        m[..., 1, 0] + m[..., 0, 1],
        m[..., 0, 2] + m[..., 2, 0],
        m[..., 2, 1] + m[..., 1, 2],
    )
    cands = torch.stack(
        [
            torch.stack([q_abs[..., 0] ** 2, d21, d02, d10], -1),
            torch.stack([d21, q_abs[..., 1] ** 2, s10, s02], -1),
            torch.stack([d02, s10, q_abs[..., 2] ** 2, s21], -1),
            torch.stack([d10, s02, s21, q_abs[..., 3] ** 2], -1),
        ],
        -2,
    )  # [..., 4, 4], row i = quaternion * 2 q_abs[i]
    cands = cands / (2.0 * q_abs[..., None].clamp(min=0.1))
    best = q_abs.argmax(-1)[..., None, None].expand(*q_abs.shape[:-1], 1, 4)
    quat = cands.gather(-2, best)[..., 0, :]
    return torch.where(quat[..., :1] < 0, -quat, quat)


def quaternion_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product a * b (rotate by b, then by a). [..., 4] x [..., 4] -> [..., 4]."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


def quaternion_to_matrix(q: Tensor) -> Tensor:
    """Quaternions (any norm > 0) to rotation matrices. [..., 4] -> [..., 3, 3]."""
    q = q / q.norm(dim=-1, keepdim=True).clamp(min=1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        -1,
    ).reshape(*q.shape[:-1], 3, 3)
