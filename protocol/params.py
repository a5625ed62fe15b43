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


def validate_family(family: str, values: Any, max_elements: int) -> dict[str, np.ndarray]:
    """One family's partial parameters as float64 arrays of their per-frame shapes."""
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
        arr = to_array(value, max_elements, f"{family}.{name}")
        ok, arr, want = _shape_ok(arr, spec[name])
        if not ok:
            raise ProtocolError("invalid", f"{family}.{name}: expected shape {want}, "
                                           f"got {list(arr.shape)}")
        out[name] = arr
    return out
