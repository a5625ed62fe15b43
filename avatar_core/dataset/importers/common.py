"""Helpers shared by the importers of foreign capture layouts."""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..imageio import read_header

__all__ = ["Progress", "is_plain_rgb", "mask_to_uint8", "nearest_rotation", "read_image",
           "safe_name"]

Progress = Callable[[int, int], None]  # (done, total)


def nearest_rotation(M: Any, what: str, *, tol: float = 1e-3) -> np.ndarray:
    """The rotation closest to M [3, 3] (SVD), for matrices that are rotations up to the
    rounding of the file they came from; anything further than `tol` off is an error."""
    M = np.asarray(M, dtype=np.float64)
    if M.shape != (3, 3) or not np.all(np.isfinite(M)):
        raise ValueError(f"{what}: expected a finite 3x3 rotation, got {M.tolist()}")
    U, _, Vt = np.linalg.svd(M)
    R = U @ Vt
    if np.linalg.det(R) < 0 or np.max(np.abs(R - M)) > tol:
        raise ValueError(f"{what} is not a rotation (scaled, mirrored or sheared): {M.tolist()}")
    return R


def safe_name(text: str) -> str:
    """A folder-safe sequence/camera name: other characters become '_'."""
    out = re.sub(r"[^A-Za-z0-9._-]", "_", text).lstrip("._-")
    return out[:128] or "unnamed"


def is_plain_rgb(path: Path, ext: str) -> bool:
    """Whether the file is already what a dataset stores (8-bit RGB `ext`): copy, not convert."""
    try:
        h = read_header(path)
    except (OSError, ValueError):
        return False
    return (h.kind, h.bit_depth, h.channels, h.palette) == (ext, 8, 3, False)


def read_image(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """(RGB uint8 [H, W, 3], alpha uint8 [H, W] or None) of any 8/16-bit gray/RGB/RGBA file."""
    data = np.fromfile(str(path), dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        raise ValueError(f"cannot decode image {path}")
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    if img.dtype != np.uint8:
        raise ValueError(f"{path}: unsupported pixel type {img.dtype}")
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2RGB), None
    if img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB), np.ascontiguousarray(img[..., 3])
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB), None


def mask_to_uint8(path: Path) -> np.ndarray:
    """A foreground mask file as 8-bit alpha [H, W]: first channel of a colour file, 16-bit
    scaled down, and a 0/1 mask scaled to 0/255."""
    data = np.fromfile(str(path), dtype=np.uint8)
    m = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if m is None:
        raise ValueError(f"cannot decode mask {path}")
    if m.ndim == 3:
        m = m[..., 0]
    if m.dtype == np.uint16:
        m = (m >> 8).astype(np.uint8)
    if m.dtype != np.uint8:
        raise ValueError(f"{path}: unsupported mask pixel type {m.dtype}")
    if m.max() <= 1:
        m = m * np.uint8(255)
    return np.ascontiguousarray(m)
