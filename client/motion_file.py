"""Motion files for streaming: per-frame parameters, read into a list of drive updates.

Two formats:

- ``.json``: a list of per-frame dicts, or ``{"fps": 30, "frames": [...]}`` (the shape
  ``GET /v1/motions/{name}`` answers). A per-frame dict is family-keyed
  (``{"smplx": {...}, "flame": {...}}``) or holds SMPL-X fields directly (``{"jaw_pose": ...}``).
- ``.npz``: one array per parameter with the frame axis first, named ``jaw_pose`` (SMPL-X) or
  ``family.field`` / ``family/field`` (``flame.expr``, ``mano_left.hand_pose``). A 1-D
  ``betas`` / ``expression`` / ``shape`` (no frame axis) is sent once, with the first frame.
  An optional scalar ``fps`` (or ``mocap_framerate``) gives the frame rate.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from protocol import FAMILIES

from .stream import params_of

_META_KEYS = ("fps", "mocap_framerate")
_STATIC_VECTORS = ("betas", "expression", "shape")


@dataclass(frozen=True)
class Motion:
    frames: list[dict[str, dict[str, Any]]]  # per frame: family -> field -> values
    fps: float | None = None

    def __len__(self) -> int:
        return len(self.frames)


def load_motion(path: str | Path) -> Motion:
    path = Path(path)
    if path.suffix == ".json":
        return _load_json(path)
    if path.suffix == ".npz":
        return _load_npz(path)
    raise ValueError(f"{path}: a motion file is .json or .npz")


def _load_json(path: Path) -> Motion:
    return motion_from_json(json.loads(path.read_text()), str(path))


def motion_from_json(data: Any, where: str = "motion") -> Motion:
    """A motion from parsed JSON: a list of per-frame objects or ``{"fps", "frames"}`` (the
    answer of ``GET /v1/motions/{name}``)."""
    fps = None
    if isinstance(data, dict):
        fps, data = data.get("fps"), data.get("frames")
    if not isinstance(data, list) or not data or not all(isinstance(f, dict) for f in data):
        raise ValueError(f"{where}: expected a non-empty list of per-frame objects "
                         f"(or {{'frames': [...]}})")
    return Motion([params_of(frame) for frame in data], float(fps) if fps else None)


def is_motion_file(spec: str | Path) -> bool:
    """Whether a ``--motion`` names a file (else a built-in clip the server has)."""
    return Path(spec).suffix in (".json", ".npz") or Path(spec).is_file()


def _split_key(key: str) -> tuple[str, str]:
    for sep in (".", "/"):
        family, found, name = key.partition(sep)
        if found:
            return family, name
    return "smplx", key


def _load_npz(path: Path) -> Motion:
    with np.load(path, allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files}
    fps = next((float(arrays.pop(k)) for k in _META_KEYS if k in arrays), None)
    per_frame: dict[tuple[str, str], np.ndarray] = {}
    static: dict[tuple[str, str], np.ndarray] = {}
    for key, value in arrays.items():
        family, name = _split_key(key)
        if family not in FAMILIES or name not in FAMILIES[family]:
            raise ValueError(f"{path}: unknown parameter {key!r}; use SMPL-X field names or "
                             f"family.field with a family of {sorted(FAMILIES)}")
        if name in _STATIC_VECTORS and value.ndim == 1:
            static[family, name] = value
        elif value.ndim >= 2:
            per_frame[family, name] = value
        else:
            raise ValueError(f"{path}: {key} needs a frame axis first, got shape {value.shape}")
    counts = {v.shape[0] for v in per_frame.values()}
    if len(counts) != 1:
        raise ValueError(f"{path}: per-frame arrays must share the frame count, got "
                         f"{sorted(counts) or 'none'}")
    frames: list[dict[str, dict[str, Any]]] = []
    for i in range(counts.pop()):
        frame: dict[str, dict[str, Any]] = {}
        for (family, name), value in per_frame.items():
            frame.setdefault(family, {})[name] = value[i]
        if i == 0:
            for (family, name), value in static.items():
                frame.setdefault(family, {})[name] = value
        frames.append(frame)
    return Motion(frames, fps)
