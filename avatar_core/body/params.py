"""Parameter sets of the three body-model families and their validation.

Names and shapes follow the `smplx` package (SMPL-X) and the public FLAME / MANO tools.
Every field is optional (missing means zeros) and batched: [B, ...]. An unbatched value
(no leading batch axis) or a batch of 1 is broadcast to the batch of the others.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
import torch
from torch import Tensor

from .errors import ParameterError


class _Params:
    """Shared helpers of the parameter dataclasses."""

    @classmethod
    def from_dict(cls, values: dict[str, Any]):
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - names)
        if unknown:
            raise ParameterError(
                f"unknown {cls.__name__} field(s) {unknown}; expected some of {sorted(names)}")
        return cls(**values)

    def to_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)
                if getattr(self, f.name) is not None}


@dataclass
class SMPLXParams(_Params):
    betas: Any = None            # [B, S]
    expression: Any = None       # [B, E]
    global_orient: Any = None    # [B, 3]
    body_pose: Any = None        # [B, 21, 3]
    jaw_pose: Any = None         # [B, 3]
    leye_pose: Any = None        # [B, 3]
    reye_pose: Any = None        # [B, 3]
    left_hand_pose: Any = None   # [B, 15, 3], or [B, n] PCA coefficients for a PCA model
    right_hand_pose: Any = None  # [B, 15, 3], or [B, n]
    transl: Any = None           # [B, 3]
    # Per-vertex template displacement (like SMPL+D), e.g. a fused FLAME face shape.
    vertex_offsets: Any = None   # [B, V, 3]


@dataclass
class FLAMEParams(_Params):
    shape: Any = None        # [B, S]
    expr: Any = None         # [B, E]
    rotation: Any = None     # [B, 3] global (root) rotation
    neck_pose: Any = None    # [B, 3]
    jaw_pose: Any = None     # [B, 3]
    eyes_pose: Any = None    # [B, 6] left eye then right eye
    translation: Any = None  # [B, 3]


@dataclass
class MANOParams(_Params):
    betas: Any = None          # [B, 10]
    global_orient: Any = None  # [B, 3]
    hand_pose: Any = None      # [B, 15, 3], or [B, n] PCA coefficients
    transl: Any = None         # [B, 3]


def _to_tensor(name: str, value: Any, dtype: torch.dtype, device: torch.device) -> Tensor:
    if isinstance(value, Tensor):
        return value.to(device=device, dtype=dtype)
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"{name}: expected numbers, got {type(value).__name__}") from exc
    return torch.as_tensor(arr, dtype=dtype, device=device)


def normalize_params(
    params: _Params | dict[str, Any],
    spec: dict[str, tuple[int, ...]],
    *,
    dtype: torch.dtype,
    device: torch.device,
    family: str,
) -> dict[str, Tensor]:
    """Validate parameters against `spec` (field -> per-sample shape) and batch them.

    Returns every field of `spec` as a tensor [B, *shape]; missing fields are zeros. Raises
    ParameterError naming the field for an unknown field, a wrong shape, a batch mismatch or
    a non-finite value.
    """
    values = params.to_dict() if isinstance(params, _Params) else dict(params)
    unknown = sorted(k for k, v in values.items() if k not in spec and v is not None)
    if unknown:
        raise ParameterError(f"{family}: unknown parameter(s) {unknown}; "
                             f"expected some of {sorted(spec)}")
    shaped: dict[str, Tensor] = {}
    batched: dict[str, int] = {}
    for name, tail in spec.items():
        if values.get(name) is None:
            continue
        t = _to_tensor(f"{family}.{name}", values[name], dtype, device)
        size = math.prod(tail)
        if t.shape == tail or (t.dim() == 1 and t.numel() == size and len(tail) > 1):
            t = t.reshape(1, *tail)  # unbatched
        elif t.dim() >= 1 and (t.shape[1:] == tail or (t.dim() == 2 and t.shape[1] == size)):
            t = t.reshape(t.shape[0], *tail)
            batched[name] = t.shape[0]
        else:
            want = f"[B, {', '.join(map(str, tail))}]"
            alt = f" or [B, {size}]" if len(tail) > 1 else ""
            raise ParameterError(
                f"{family}.{name}: expected shape {want}{alt}, got {list(t.shape)}")
        if not torch.isfinite(t).all():
            raise ParameterError(f"{family}.{name} contains NaN or Inf")
        shaped[name] = t
    sizes = {b for b in batched.values() if b != 1}
    if len(sizes) > 1:
        raise ParameterError(f"{family}: batch sizes disagree: {batched}")
    batch = sizes.pop() if sizes else 1
    out = {}
    for name, tail in spec.items():
        t = shaped.get(name)
        if t is None:
            t = torch.zeros((batch, *tail), dtype=dtype, device=device)
        elif t.shape[0] != batch:
            t = t.expand(batch, *tail)
        out[name] = t
    return out
