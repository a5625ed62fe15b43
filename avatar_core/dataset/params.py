"""The arrays of a sequence's params.npz: which keys exist, their shapes, and the checks.

Every array has a leading frame axis [T, ...] except the *shared* ones (identity shape,
static offsets), which may be stored once without it. SMPL-X keys carry the `smplx` package
names; FLAME keys are prefixed "flame_", MANO keys "mano_left_" / "mano_right_".
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["ParamIssue", "ParamSpec", "check_params", "frame_slice", "num_frames_of",
           "param_spec"]

ANY = -1  # a dimension whose size the body model decides (betas, expression, PCA, vertices)


@dataclass(frozen=True)
class ParamSpec:
    per_frame: tuple[int, ...]              # trailing shape after the frame axis
    alt: tuple[int, ...] | None = None      # another accepted trailing shape (PCA hands)
    shared: bool = False                    # may be stored once, without the frame axis
    shared_only: bool = False               # must be stored once


_HAND = ParamSpec((15, 3), alt=(ANY,))
_SMPLX = {
    "betas": ParamSpec((ANY,), shared=True),
    "expression": ParamSpec((ANY,)),
    "global_orient": ParamSpec((3,)),
    "body_pose": ParamSpec((21, 3)),
    "jaw_pose": ParamSpec((3,)),
    "leye_pose": ParamSpec((3,)),
    "reye_pose": ParamSpec((3,)),
    "left_hand_pose": _HAND,
    "right_hand_pose": _HAND,
    "transl": ParamSpec((3,)),
    "vertex_offsets": ParamSpec((ANY, 3), shared=True),
}
_FLAME = {
    "shape": ParamSpec((ANY,), shared=True),
    "expr": ParamSpec((ANY,)),
    "rotation": ParamSpec((3,)),
    "neck_pose": ParamSpec((3,)),
    "jaw_pose": ParamSpec((3,)),
    "eyes_pose": ParamSpec((6,)),
    "translation": ParamSpec((3,)),
    "static_offset": ParamSpec((ANY, 3), shared=True, shared_only=True),
    "dynamic_offset": ParamSpec((ANY, 3)),
}
_MANO = {
    "betas": ParamSpec((ANY,), shared=True),
    "global_orient": ParamSpec((3,)),
    "hand_pose": _HAND,
    "transl": ParamSpec((3,)),
}


def _all_specs() -> dict[str, ParamSpec]:
    out = dict(_SMPLX)
    out.update({f"flame_{k}": v for k, v in _FLAME.items()})
    for side in ("left", "right"):
        out.update({f"mano_{side}_{k}": v for k, v in _MANO.items()})
    return out


def param_spec(key: str) -> ParamSpec | None:
    return _all_specs().get(key)


def _is_shared(spec: ParamSpec, arr: np.ndarray) -> bool:
    return spec.shared and arr.ndim == len(spec.per_frame)


def _fits(shape: tuple[int, ...], want: tuple[int, ...]) -> bool:
    return len(shape) == len(want) and all(w == ANY or s == w for s, w in zip(shape, want,
                                                                              strict=True))


def num_frames_of(params: Mapping[str, np.ndarray]) -> int | None:
    """The frame count of the per-frame arrays (the first known one), None if there are none."""
    for key, arr in params.items():
        spec = param_spec(key)
        a = np.asarray(arr)
        if spec is not None and not _is_shared(spec, a) and a.ndim >= 1:
            return int(a.shape[0])
    return None


@dataclass(frozen=True)
class ParamIssue:
    code: str                      # params_unknown_key, params_bad_dtype, ... (docs)
    key: str
    message: str
    frames: tuple[int, ...] = ()
    warning: bool = False


def _expected_dims(body_model: Mapping[str, Any] | None) -> dict[str, int]:
    """Sizes the declared body model fixes: {key: size of the last axis}."""
    bm = body_model or {}
    nb, ne = bm.get("num_betas"), bm.get("num_expression")
    sizes = {"smplx": {"betas": nb, "expression": ne},
             "flame": {"flame_shape": nb, "flame_expr": ne},
             "mano": {"mano_left_betas": nb, "mano_right_betas": nb}}.get(bm.get("type"), {})
    return {k: n for k, n in sizes.items() if isinstance(n, int) and not isinstance(n, bool)}


def _hand_trailing(body_model: Mapping[str, Any] | None) -> tuple[int, ...]:
    pca = (body_model or {}).get("hand_pca")
    return (pca,) if isinstance(pca, int) and not isinstance(pca, bool) else (15, 3)


def check_params(params: Mapping[str, Any], num_frames: int | None,
                 body_model: Mapping[str, Any] | None = None) -> list[ParamIssue]:
    """Every issue of a parameter set: unknown keys (warning), non-float dtype, wrong shape,
    frame count other than `num_frames` (or than each other, when None), NaN/Inf (with the
    frames affected). Sizes the body model fixes (betas, expression, PCA hands) are checked
    when `body_model` is given."""
    issues: list[ParamIssue] = []
    dims = _expected_dims(body_model)
    hand = _hand_trailing(body_model)
    expected_T = num_frames
    for key in sorted(params):
        arr = np.asarray(params[key])
        spec = param_spec(key)
        if spec is None:
            issues.append(ParamIssue("params_unknown_key", key,
                                     f"unknown key {key!r} (ignored by the engine)",
                                     warning=True))
            continue
        if arr.dtype.kind != "f":
            issues.append(ParamIssue("params_bad_dtype", key,
                                     f"{key} must be float32 or float64, got {arr.dtype}"))
            continue
        shared = _is_shared(spec, arr)
        trailing = arr.shape if shared else arr.shape[1:]
        wants = [spec.per_frame] + ([spec.alt] if spec.alt else [])
        if key in ("left_hand_pose", "right_hand_pose"):
            wants = [hand]  # the body model decides: full [15, 3] or its PCA count
        if spec.shared_only and not shared:
            issues.append(ParamIssue("params_bad_shape", key,
                                     f"{key} is shared: shape {spec.per_frame} without a "
                                     f"frame axis, got {arr.shape}"))
            continue
        if arr.ndim == 0 or not any(_fits(trailing, w) for w in wants):
            want = " or ".join(f"[T, {', '.join('*' if d == ANY else str(d) for d in w)}]"
                               for w in wants)
            issues.append(ParamIssue("params_bad_shape", key,
                                     f"{key} has shape {list(arr.shape)}, expected {want}"
                                     + (" (or without T when shared)" if spec.shared else "")))
            continue
        if key in dims and trailing[-1] != dims[key]:
            issues.append(ParamIssue("params_bad_shape", key,
                                     f"{key} has {trailing[-1]} coefficients but body_model "
                                     f"declares {dims[key]}"))
            continue
        if not shared:
            if expected_T is None:
                expected_T = arr.shape[0]
            elif arr.shape[0] != expected_T:
                issues.append(ParamIssue("params_frame_count", key,
                                         f"{key} has {arr.shape[0]} frames, expected "
                                         f"{expected_T}"))
                continue
        finite = np.isfinite(arr)
        if not finite.all():
            bad: tuple[int, ...] = ()
            if not shared:
                bad = tuple(int(f) for f in np.nonzero(~finite.reshape(len(arr), -1)
                                                       .all(axis=1))[0])
            where = f"frame(s) {list(bad)}" if bad else "its shared value"
            issues.append(ParamIssue("params_nonfinite", key,
                                     f"{key} holds NaN/Inf in {where}", bad))
    return issues


def frame_slice(params: Mapping[str, np.ndarray], frame: int) -> dict[str, np.ndarray]:
    """One frame's values: per-frame arrays indexed at `frame`, shared arrays as they are
    (so `betas` is [B] either way). Unknown keys are passed through when per-frame-shaped."""
    out = {}
    for key, arr in params.items():
        spec = param_spec(key)
        shared = spec is not None and _is_shared(spec, arr)
        out[key] = arr if shared or arr.ndim == 0 else arr[frame]
    return out
