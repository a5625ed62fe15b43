"""Body-model parameters on the wire: SMPL-X, FLAME and MANO, by the names their tools use.

A ``drive`` carries any subset of any family (a partial update): fields not sent keep their
last value in the session. Shapes are per frame (no batch axis); a fixed-shape field may also
come flattened (``body_pose`` as 63 numbers).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .arrays import to_array
from .errors import ProtocolError
from .limits import Limits

# field -> ("fixed", shape) or ("vector", max length) or ("hand", ()): [15, 3], [45] or
# PCA coefficients [n <= 45].
FieldSpec = tuple[str, Any]

SMPLX_FIELDS: dict[str, FieldSpec] = {
    "betas": ("vector", 300), "expression": ("vector", 100),
    "global_orient": ("fixed", (3,)), "body_pose": ("fixed", (21, 3)),
    "jaw_pose": ("fixed", (3,)), "leye_pose": ("fixed", (3,)), "reye_pose": ("fixed", (3,)),
    "left_hand_pose": ("hand", ()), "right_hand_pose": ("hand", ()), "transl": ("fixed", (3,)),
}
FLAME_FIELDS: dict[str, FieldSpec] = {
    "shape": ("vector", 300), "expr": ("vector", 100), "rotation": ("fixed", (3,)),
    "neck_pose": ("fixed", (3,)), "jaw_pose": ("fixed", (3,)), "eyes_pose": ("fixed", (6,)),
    "translation": ("fixed", (3,)),
}
MANO_FIELDS: dict[str, FieldSpec] = {
    "betas": ("vector", 10), "global_orient": ("fixed", (3,)), "hand_pose": ("hand", ()),
    "transl": ("fixed", (3,)),
}
# What a parameter's values are, for their range check against the Limits: "rotation" (rows
# of axis-angle, bounded in norm), "coefficient" (each bounded in size), "translation" (bounded
# in norm), or "hand" (a full [15, 3] / [45] pose is rotations, fewer numbers PCA coefficients).
VALUE_KINDS: dict[str, str] = {
    "betas": "coefficient", "expression": "coefficient", "shape": "coefficient",
    "expr": "coefficient", "global_orient": "rotation", "body_pose": "rotation",
    "jaw_pose": "rotation", "leye_pose": "rotation", "reye_pose": "rotation",
    "rotation": "rotation", "neck_pose": "rotation", "eyes_pose": "rotation",
    "left_hand_pose": "hand", "right_hand_pose": "hand", "hand_pose": "hand",
    "transl": "translation", "translation": "translation",
}
# drive field -> the family's fields
FAMILIES: dict[str, dict[str, FieldSpec]] = {
    "smplx": SMPLX_FIELDS, "flame": FLAME_FIELDS,
    "mano_left": MANO_FIELDS, "mano_right": MANO_FIELDS,
}


def _shape_ok(arr: np.ndarray, spec: FieldSpec) -> tuple[bool, np.ndarray, str]:
    kind, arg = spec
    if kind == "fixed":
        ok = arr.shape == arg or (arr.ndim == 1 and arr.size == math.prod(arg))
        return ok, arr.reshape(arg) if ok else arr, f"{list(arg)}"
    if kind == "vector":
        ok = arr.ndim == 1 and 1 <= arr.size <= arg
        return ok, arr, f"[n] with 1 <= n <= {arg}"
    ok = arr.shape == (15, 3) or (arr.ndim == 1 and 1 <= arr.size <= 45)
    if ok and arr.size == 45:
        arr = arr.reshape(15, 3)
    return ok, arr, "[15, 3], [45] or [n <= 45] PCA coefficients"


def value_range(name: str, size: int, limits: Limits) -> tuple[str, float, str]:
    """(kind, bound, description) of a parameter's values: kind "norm" bounds each row of 3,
    kind "abs" each value."""
    kind = VALUE_KINDS[name]
    if kind == "hand":
        kind = "rotation" if size == 45 else "coefficient"
    if kind == "rotation":
        return "norm", limits.max_rotation_rad, "rotation angle (norm of each axis-angle row)"
    if kind == "translation":
        return "norm", limits.max_translation_m, "translation norm (m)"
    return "abs", limits.max_coefficient, "coefficient size"


def check_range(family: str, name: str, arr: np.ndarray, limits: Limits) -> None:
    """ProtocolError("invalid") naming the field and its range when a value is out of it."""
    how, bound, what = value_range(name, arr.size, limits)
    worst = float(np.abs(arr).max(initial=0.0))
    if how == "norm" and worst <= bound:  # each value in range first: the norm cannot overflow
        worst = float(np.linalg.norm(arr.reshape(-1, 3), axis=1).max(initial=0.0))
    if worst > bound:
        raise ProtocolError("invalid", f"{family}.{name}: {what} {worst:.6g} is out of range "
                                       f"[0, {bound:.6g}]")


def validate_family(family: str, values: Any, limits: Limits) -> dict[str, np.ndarray]:
    """One family's partial parameters as float64 arrays of their per-frame shapes, each value
    within the limits' ranges."""
    spec = FAMILIES.get(family)
    if spec is None:
        raise ProtocolError("invalid", f"unknown parameter family {family!r}; "
                                       f"expected one of {sorted(FAMILIES)}")
    if not isinstance(values, dict):
        raise ProtocolError("invalid", f"{family} must be a map of parameter arrays")
    unknown = sorted(str(k) for k in values if k not in spec)
    if unknown:
        raise ProtocolError("invalid", f"{family}: unknown parameter(s) {unknown}; "
                                       f"expected some of {sorted(spec)}")
    out = {}
    for name, value in values.items():
        arr = to_array(value, limits.max_array_elements, f"{family}.{name}")
        ok, arr, want = _shape_ok(arr, spec[name])
        if not ok:
            raise ProtocolError("invalid", f"{family}.{name}: expected shape {want}, "
                                           f"got {list(arr.shape)}")
        check_range(family, name, arr, limits)
        out[name] = arr
    return out
