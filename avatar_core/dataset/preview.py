"""Pictures that let a person judge a dataset at a glance: a contact sheet of one frame across
all cameras, and a strip of frames from one camera."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from .loader import Dataset

__all__ = ["contact_sheet", "frame_strip", "grid", "tile", "write_png"]


def tile(rgb: np.ndarray, label: str, size: int) -> np.ndarray:
    """uint8 [size, size, 3] thumbnail with a caption; non-square images are letterboxed."""
    h, w = rgb.shape[:2]
    scale = size / max(h, w)
    small = cv2.resize((np.clip(rgb, 0, 1) * 255).astype(np.uint8),
                       (max(1, round(w * scale)), max(1, round(h * scale))),
                       interpolation=cv2.INTER_AREA)
    tile = np.full((size, size, 3), 255, np.uint8)
    y0, x0 = (size - small.shape[0]) // 2, (size - small.shape[1]) // 2
    tile[y0:y0 + small.shape[0], x0:x0 + small.shape[1]] = small
    font_scale = max(0.3, size / 400)
    (tw, th), base = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, font_scale, 1)
    cv2.rectangle(tile, (0, 0), (tw + 6, th + base + 4), (255, 255, 255), -1)  # legible caption
    cv2.putText(tile, label, (3, th + 2), cv2.FONT_HERSHEY_SIMPLEX, font_scale, (20, 20, 20), 1,
                cv2.LINE_AA)
    return tile


def grid(tiles: list[np.ndarray], columns: int) -> np.ndarray:
    columns = max(1, min(columns, len(tiles)))
    blank = np.full_like(tiles[0], 255)
    tiles = tiles + [blank] * (-len(tiles) % columns)
    rows = [np.concatenate(tiles[i:i + columns], axis=1) for i in range(0, len(tiles), columns)]
    return np.concatenate(rows, axis=0)


def contact_sheet(dataset: Dataset, sequence: str, frame: int, *,
                  cameras: Sequence[str] | None = None, columns: int = 6,
                  size: int = 256) -> np.ndarray:
    """uint8 RGB grid of `frame` of `sequence` seen by every camera (or those named)."""
    names = list(cameras) if cameras is not None else list(dataset.cameras)
    if not names:
        raise ValueError("the dataset has no cameras")
    tiles = [tile(dataset.view(sequence, frame, cam).rgb, cam, size) for cam in names]
    return grid(tiles, columns)


def frame_strip(dataset: Dataset, shots: Sequence[tuple[str, int, str]], camera: str, *,
                columns: int = 8, size: int = 256) -> np.ndarray:
    """uint8 RGB grid of (sequence, frame, caption) shots from one camera."""
    if not shots:
        raise ValueError("no shots given")
    tiles = [tile(dataset.view(seq, frame, camera).rgb, caption, size)
             for seq, frame, caption in shots]
    return grid(tiles, columns)


def write_png(path: str | Path, rgb: np.ndarray) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1])):
        raise OSError(f"could not write {path}")
    return path
