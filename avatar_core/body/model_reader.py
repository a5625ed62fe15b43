"""Reading official body-model files (.npz, .pkl) without chumpy.

Official SMPL/FLAME/MANO pickles were written by Python 2 and store some arrays as
`chumpy.ch.Ch` objects and regressors as `scipy.sparse` matrices. Unpickling maps chumpy's
classes to a stub that keeps the pickled state; a plain `Ch` keeps its array under `x`,
which is all a model file holds. Only numpy, scipy.sparse, chumpy and builtin types may be
unpickled, so a model file cannot run arbitrary code.
"""

from __future__ import annotations

import _compat_pickle
import importlib
import pickle
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse

from .errors import ModelFileError

_ALLOWED_MODULES = ("numpy", "scipy.sparse", "copyreg", "builtins", "_codecs", "collections")


class ChumpyStub:
    """Stands in for any chumpy class while unpickling; keeps the pickled state."""

    chumpy_class = "chumpy.ch.Ch"

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.state: dict[str, Any] = {}

    def __setstate__(self, state: Any) -> None:
        self.state = state if isinstance(state, dict) else {"state": state}


class _SafeUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> Any:
        # Python 2 names (__builtin__.set, copy_reg, ...), as pickle's own find_class maps them.
        if (module, name) in _compat_pickle.NAME_MAPPING:
            module, name = _compat_pickle.NAME_MAPPING[(module, name)]
        module = _compat_pickle.IMPORT_MAPPING.get(module, module)
        if module == "chumpy" or module.startswith("chumpy."):
            return type(name, (ChumpyStub,), {"chumpy_class": f"{module}.{name}"})
        if module.startswith("scipy.sparse"):
            # Old pickles name private modules (scipy.sparse.csc) that newer SciPy moved.
            if hasattr(scipy.sparse, name):
                return getattr(scipy.sparse, name)
        if module == "numpy.core" or module.startswith("numpy.core."):
            module = "numpy._core" + module[len("numpy.core"):]
        if not any(module == m or module.startswith(m + ".") for m in _ALLOWED_MODULES):
            raise pickle.UnpicklingError(f"refusing to load {module}.{name} from a model file")
        return getattr(importlib.import_module(module), name)


def to_array(value: Any, key: str, path: Path) -> np.ndarray:
    """A model-file value as a dense numpy array (chumpy and scipy.sparse resolved)."""
    if isinstance(value, ChumpyStub):
        if "x" not in value.state:
            raise ModelFileError(
                f"{path}: '{key}' is a chumpy expression ({value.chumpy_class}), not a plain array;"
                " load the file once with chumpy installed and re-save its arrays as .npz")
        value = value.state["x"]
    if scipy.sparse.issparse(value):
        value = value.toarray()
    try:
        return np.asarray(value)
    except Exception as exc:  # noqa: BLE001 - anything unreadable gets the same clear error
        raise ModelFileError(f"{path}: '{key}' is not an array ({type(value).__name__})") from exc


def _read_npy(path: Path) -> Any:
    """A .npy file; an object array (a pickled dict) goes through the safe unpickler."""
    with path.open("rb") as f:
        version = np.lib.format.read_magic(f)
        read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                       else np.lib.format.read_array_header_2_0)
        _, _, dtype = read_header(f)
        if not dtype.hasobject:
            f.seek(0)
            return np.load(f, allow_pickle=False)
        data = _SafeUnpickler(f, encoding="latin1").load()
    return data.item() if isinstance(data, np.ndarray) and data.shape == () else data


def read_model_file(path: str | Path) -> dict[str, Any]:
    """Raw key -> value mapping of a .npz or .pkl model file (values not yet converted)."""
    path = Path(path)
    if not path.is_file():
        raise ModelFileError(f"model file not found: {path}")
    suffix = path.suffix.lower()
    try:
        if suffix == ".npz":
            out = {}
            with np.load(path, allow_pickle=False) as npz:
                for k in npz.files:
                    try:
                        out[k] = npz[k]
                    except ValueError:  # pickled objects (e.g. 'part2num'): never executed
                        continue
            return out
        if suffix in (".pkl", ".pickle"):
            with path.open("rb") as f:
                data = _SafeUnpickler(f, encoding="latin1").load()
        elif suffix == ".npy":
            data = _read_npy(path)
        else:
            raise ModelFileError(f"{path}: unknown model file type '{suffix}' (use .npz or .pkl)")
    except ModelFileError:
        raise
    except Exception as exc:
        raise ModelFileError(f"{path}: cannot read model file: {exc}") from exc
    if not isinstance(data, dict):
        raise ModelFileError(f"{path}: expected a dict of arrays, got {type(data).__name__}")
    return data


def require(data: dict[str, Any], key: str, path: Path, *, ndim: int | None = None,
            shape: tuple[int | None, ...] | None = None, what: str = "") -> np.ndarray:
    """data[key] as an array, with a clear error naming a missing key or a wrong shape."""
    if key not in data:
        raise ModelFileError(f"{path}: missing key '{key}'{f' ({what})' if what else ''}; "
                             f"the file has {sorted(data)}")
    arr = to_array(data[key], key, path)
    if shape is not None:
        ndim = len(shape)
    if ndim is not None and arr.ndim != ndim:
        raise ModelFileError(f"{path}: '{key}' should have {ndim} dimensions, "
                             f"got shape {list(arr.shape)}")
    pairs = zip(shape or (), arr.shape, strict=False)
    if shape is not None and any(s is not None and s != a for s, a in pairs):
        want = "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
        raise ModelFileError(f"{path}: '{key}' should have shape {want}, got {list(arr.shape)}")
    return arr
