"""numpy arrays on the wire: a msgpack map {"nd": true, "dtype", "shape", "data"}.

A map (not a msgpack ext type) so that any msgpack library, the browser's included, reads it
without a custom codec. Plain (nested) lists of numbers are accepted wherever an array is.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .errors import ProtocolError

# Little-endian numeric dtypes only: no objects, no strings, no native-endian ambiguity.
WIRE_DTYPES = ("<f4", "<f8", "<i4", "<i8", "|u1", "<u2")
ND_KEY = "nd"


def pack_array(arr: np.ndarray) -> dict[str, Any]:
    arr = np.asarray(arr)
    if arr.dtype.kind == "f" and arr.dtype.itemsize not in (4, 8):
        arr = arr.astype("<f4")
    dtype = arr.dtype.newbyteorder("<") if arr.dtype.byteorder == ">" else arr.dtype
    arr = np.ascontiguousarray(arr, dtype=dtype)
    if arr.dtype.str not in WIRE_DTYPES:
        raise ProtocolError("invalid", f"arrays of dtype {arr.dtype} cannot be sent; "
                                       f"use one of {WIRE_DTYPES}")
    return {ND_KEY: True, "dtype": arr.dtype.str, "shape": list(arr.shape),
            "data": arr.tobytes()}


def is_packed_array(obj: Any) -> bool:
    return isinstance(obj, dict) and obj.get(ND_KEY) is True and "data" in obj


def unpack_array(obj: dict[str, Any], max_elements: int, name: str = "array") -> np.ndarray:
    """The array a packed map holds; a clear ProtocolError for any inconsistency."""
    dtype, shape, data = obj.get("dtype"), obj.get("shape"), obj.get("data")
    if dtype not in WIRE_DTYPES:
        raise ProtocolError("invalid", f"{name}: dtype must be one of {WIRE_DTYPES}, "
                                       f"got {dtype!r}")
    if (not isinstance(shape, list) or len(shape) > 4
            or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0
                       for s in shape)):
        raise ProtocolError("invalid", f"{name}: shape must be a list of at most 4 "
                                       f"non-negative ints, got {shape!r}")
    if not isinstance(data, bytes):
        raise ProtocolError("invalid", f"{name}: data must be bytes")
    count = math.prod(shape)
    if count > max_elements:
        raise ProtocolError("too_large", f"{name}: {count} elements, limit {max_elements}")
    if len(data) != count * np.dtype(dtype).itemsize:
        raise ProtocolError("invalid", f"{name}: {len(data)} bytes do not hold {dtype} "
                                       f"of shape {shape}")
    return np.frombuffer(data, dtype=dtype).reshape(shape)


def to_array(value: Any, max_elements: int, name: str) -> np.ndarray:
    """A packed array or a (nested) list of numbers as a float64 array; finite or an error."""
    if is_packed_array(value):
        arr = unpack_array(value, max_elements, name).astype(np.float64)
    elif isinstance(value, (list, tuple, int, float)) and not isinstance(value, bool):
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ProtocolError("invalid", f"{name}: expected numbers") from exc
        if arr.size > max_elements:
            raise ProtocolError("too_large", f"{name}: {arr.size} elements, "
                                             f"limit {max_elements}")
    elif isinstance(value, np.ndarray):
        if value.size > max_elements:
            raise ProtocolError("too_large", f"{name}: {value.size} elements, "
                                             f"limit {max_elements}")
        if value.dtype.kind not in "fiu":
            raise ProtocolError("invalid", f"{name}: expected numbers, got {value.dtype}")
        arr = value.astype(np.float64)
    else:
        raise ProtocolError("invalid", f"{name}: expected an array or a list of numbers, "
                                       f"got {type(value).__name__}")
    if not np.isfinite(arr).all():
        raise ProtocolError("invalid", f"{name} contains NaN or Inf")
    return arr
