"""Placing posed Gaussians in a shared scene: a rigid transform per seat, then one set of all.

A room seats several avatars. Each seat has a placement (an axis-angle rotation, then a
translation in metres): :func:`seat_transform` turns it into ``R [3, 3]`` and ``t [3]`` once,
:func:`place` moves a seat's posed Gaussians by them every frame, :func:`placed_point` moves the
seat's framing target, and :func:`union` makes one set of every seat for one render.

The identity is ``None`` (no rotation, no translation): :func:`place` then returns its input
unchanged, so an unplaced seat costs nothing. :func:`seat_transform` rejects a non-finite
placement (``ValueError``); :func:`place` does no check of its own (it runs every frame, and a
check would read the tensors back from the GPU): NaN in ``R`` or ``t`` gives NaN means, which
the renderer rejects with a ``ValueError``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from ..body.lbs import rodrigues
from ..render.types import GaussianSet
from ..rotations import matrix_to_quaternion, quaternion_multiply

__all__ = ["place", "placed_point", "seat_transform", "union"]


def seat_transform(rotation_axis_angle: Sequence[float] | np.ndarray,
                   translation: Sequence[float] | np.ndarray, dtype: torch.dtype,
                   device: torch.device | str) -> tuple[Tensor | None, Tensor | None]:
    """``(R [3, 3], t [3])`` of a placement in ``dtype`` on ``device``: ``R`` from the axis-angle
    [3] (Rodrigues), ``t`` the translation [3]; each None where it is zero (the identity).
    Raises ``ValueError`` for a shape other than [3] or a NaN/Inf component."""
    rot = _vector3("rotation", rotation_axis_angle)
    trans = _vector3("translation", translation)
    rotation = None if not rot.any() else rodrigues(torch.as_tensor(rot, dtype=dtype,
                                                                    device=device))
    shift = None if not trans.any() else torch.as_tensor(trans, dtype=dtype, device=device)
    return rotation, shift


def _vector3(name: str, values: Sequence[float] | np.ndarray) -> np.ndarray:
    v = np.asarray(values, dtype=np.float64)  # [3]
    if v.shape != (3,):
        raise ValueError(f"a seat's {name} must be 3 numbers, got shape {v.shape}")
    if not np.isfinite(v).all():
        raise ValueError(f"a seat's {name} must be finite, got {v.tolist()}")
    return v


def place(gaussians: GaussianSet, rotation: Tensor | None,
          translation: Tensor | None) -> GaussianSet:
    """The Gaussians moved rigidly: means rotated by ``rotation`` [3, 3] then translated by
    ``translation`` [3], orientations composed with the rotation (so each covariance becomes
    ``R Σ Rᵀ``); scales, opacities and SH kept. None is the identity; both None returns
    ``gaussians`` itself. View-dependent SH colour is not rotated: exact for the DC term."""
    if rotation is None and translation is None:
        return gaussians
    means, quats = gaussians.means, gaussians.quats  # [N, 3], [N, 4]
    if rotation is not None:
        means = means @ rotation.T  # [N, 3]
        q = matrix_to_quaternion(rotation).expand_as(quats)  # [N, 4]
        quats = quaternion_multiply(q, quats)  # rotate by the Gaussian's own, then by R
    if translation is not None:
        means = means + translation
    return GaussianSet(means=means, quats=quats, scales=gaussians.scales,
                       opacities=gaussians.opacities, sh=gaussians.sh)


def placed_point(point: np.ndarray, rotation: Tensor | None,
                 translation: Tensor | np.ndarray | None) -> np.ndarray:
    """A seat-space point [3] in the scene, as :func:`place` moves the means: ``R p + t``, in
    float64. Pass the translation as given (float64) for full precision."""
    p = np.asarray(point, dtype=np.float64)  # [3]
    if rotation is not None:
        p = _float64(rotation) @ p
    if translation is not None:
        p = p + _float64(translation)
    return p


def _float64(x: Tensor | np.ndarray) -> np.ndarray:
    if isinstance(x, Tensor):
        return x.detach().double().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def union(sets: Sequence[GaussianSet]) -> GaussianSet:
    """One set of every set's Gaussians, in order (set 0's first). SH of a lower degree is
    padded with zero coefficients to the highest degree (its colour unchanged). One set is
    returned as is; no set raises ``ValueError``."""
    if not sets:
        raise ValueError("union needs at least one set of Gaussians")
    if len(sets) == 1:
        return sets[0]
    bases = max(g.sh.shape[1] for g in sets)  # K of the highest degree
    sh = [g.sh if g.sh.shape[1] == bases else  # [N_i, K, 3]
          torch.nn.functional.pad(g.sh, (0, 0, 0, bases - g.sh.shape[1])) for g in sets]
    return GaussianSet(means=torch.cat([g.means for g in sets]),  # [sum N_i, 3]
                       quats=torch.cat([g.quats for g in sets]),
                       scales=torch.cat([g.scales for g in sets]),
                       opacities=torch.cat([g.opacities for g in sets]), sh=torch.cat(sh))
