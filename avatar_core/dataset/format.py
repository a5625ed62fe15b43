"""Format v1 of a Telesplat multi-view dataset: names, paths and the camera record.

The full specification is docs/dataset.md ("Format v1"). In short::

    DATASET/dataset.json, cameras.json, splits.json
    DATASET/sequences/<seq>/params.npz
    DATASET/sequences/<seq>/{images,masks,parts}/<cam>/<frame:05d>.<ext>

`K` uses the engine's pixel convention (render/camera.py): pixel (j, i) has its centre at
(j + 0.5, i + 0.5). A K calibrated with OpenCV (centres on integers) gets +0.5 on cx, cy.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from ..bounded_npz import NpzLimits
from ..render.camera import Camera

__all__ = [
    "CAMERAS_JSON", "CameraSpec", "DATASET_JSON", "FORMAT_NAME", "FORMAT_VERSION",
    "IMAGE_FORMATS", "KINDS", "MASK_FORMAT", "PARAMS_NPZ", "ROOT_CONVENTIONS", "SPLITS_JSON",
    "PARAMS_NPZ_LIMITS", "check_name", "frame_file", "inside", "opencv_to_engine_K",
    "view_path",
]

FORMAT_NAME = "telesplat.dataset"
FORMAT_VERSION = 1
DATASET_JSON = "dataset.json"
CAMERAS_JSON = "cameras.json"
SPLITS_JSON = "splits.json"
PARAMS_NPZ = "params.npz"
IMAGE_FORMATS = ("png", "jpg")
MASK_FORMAT = "png"  # masks and part labels are lossless
KINDS = ("images", "masks", "parts")  # folder names of the three per-view files
# How global_orient / transl place the body (see docs/dataset.md, "body_model").
ROOT_CONVENTIONS = ("smplx", "origin")

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")
_DRIVE = re.compile(r"^[A-Za-z]:")
# params.npz is read within these bounds (a few MB in practice: [T, ~200] floats).
PARAMS_NPZ_LIMITS = NpzLimits(max_array_bytes=256 * 2**20, max_total_bytes=512 * 2**20)


def check_name(name: Any, what: str) -> str:
    """Sequence and camera names become folder names: letters, digits, '.', '_', '-'."""
    if not isinstance(name, str) or not _NAME.match(name):
        raise ValueError(f"{what} name {name!r} must match {_NAME.pattern} (it names a folder)")
    return name


def inside(root: Path, rel: Any) -> Path | None:
    """``root / rel`` when ``rel`` is a relative path that stays inside ``root`` (no absolute
    path, drive, backslash or '..'; symlinks resolved), else None. Nothing outside ``root`` is
    looked at, so the answer cannot tell whether such a path exists."""
    if not isinstance(rel, str) or not rel or "\x00" in rel or "\\" in rel or _DRIVE.match(rel):
        return None
    parts = PurePosixPath(rel)
    if parts.is_absolute() or ".." in parts.parts:
        return None
    target = Path(root).joinpath(*parts.parts)
    try:
        if not target.resolve().is_relative_to(Path(root).resolve()):
            return None
    except (OSError, RuntimeError):  # a symlink loop
        return None
    return target


def frame_file(frame: int, ext: str) -> str:
    return f"{frame:05d}.{ext}"


def view_path(root: Path, sequence: str, kind: str, camera: str, frame: int, ext: str) -> Path:
    """DATASET/sequences/<seq>/<kind>/<cam>/<frame:05d>.<ext>."""
    return Path(root) / "sequences" / sequence / kind / camera / frame_file(frame, ext)


def opencv_to_engine_K(K: Any) -> np.ndarray:
    """OpenCV puts pixel centres on integers, the engine at +0.5: shift the principal point."""
    out = np.array(K, dtype=np.float64)
    out[0, 2] += 0.5
    out[1, 2] += 0.5
    return out


def _distortion(values: Any) -> np.ndarray:
    arr = np.zeros(5) if values is None else np.array(values, dtype=np.float64).reshape(-1)
    if arr.shape != (5,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"distortion must be 5 finite numbers [k1, k2, p1, p2, k3], got {values}")
    arr.flags.writeable = False
    return arr


@dataclass(frozen=True, eq=False)
class CameraSpec:
    """One calibrated camera of a dataset. Construction validates (via `Camera`): K [3, 3]
    with positive focal lengths, R [3, 3] a rotation (world -> camera, OpenCV axes), t [3]
    metres, positive integer size, everything finite. `distortion` is what was removed from
    the images (OpenCV order k1, k2, p1, p2, k3; for reference only, never re-applied)."""

    name: str
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int
    distortion: np.ndarray = field(default_factory=lambda: _distortion(None))
    role: str = "unknown"  # "front" | "rear" | ... free text, used to pick views

    def __post_init__(self) -> None:
        check_name(self.name, "camera")
        cam = Camera(self.K, self.R, self.t, self.width, self.height)  # raises ValueError
        object.__setattr__(self, "K", cam.K)
        object.__setattr__(self, "R", cam.R)
        object.__setattr__(self, "t", cam.t)
        object.__setattr__(self, "width", cam.width)
        object.__setattr__(self, "height", cam.height)
        object.__setattr__(self, "distortion", _distortion(self.distortion))
        if not isinstance(self.role, str) or not self.role:
            raise ValueError(f"camera {self.name}: role must be a non-empty string")

    @property
    def camera(self) -> Camera:
        return Camera(self.K, self.R, self.t, self.width, self.height)

    @classmethod
    def from_camera(cls, name: str, camera: Camera, *, role: str = "unknown",
                    distortion: Any = None) -> CameraSpec:
        return cls(name, camera.K, camera.R, camera.t, camera.width, camera.height,
                   _distortion(distortion), role)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready; floats are written with repr precision, so the round trip is exact."""
        return {"name": self.name, "K": self.K.tolist(), "R": self.R.tolist(),
                "t": self.t.tolist(), "width": self.width, "height": self.height,
                "distortion": self.distortion.tolist(), "role": self.role}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> CameraSpec:
        missing = [k for k in ("name", "K", "R", "t", "width", "height") if k not in d]
        if missing:
            raise ValueError(f"camera record is missing {missing}")
        return cls(d["name"], d["K"], d["R"], d["t"], d["width"], d["height"],
                   _distortion(d.get("distortion")), d.get("role", "unknown"))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, CameraSpec):
            return NotImplemented
        return (self.name == other.name and self.role == other.role
                and self.camera == other.camera
                and np.array_equal(self.distortion, other.distortion))

    def __hash__(self) -> int:
        return hash((self.name, self.camera))


def is_finite_number(x: Any) -> bool:
    return (isinstance(x, (int, float)) and not isinstance(x, bool)
            and math.isfinite(float(x)))
