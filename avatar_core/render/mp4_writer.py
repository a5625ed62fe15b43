"""Writing RGB frames to an MP4 file (OpenCV's mp4v encoder)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np


class Mp4Writer:
    """Append uint8 RGB frames [H, W, 3]; the size is taken from the first frame."""

    def __init__(self, path: Path, fps: float) -> None:
        self.path, self.fps = Path(path), fps
        self._writer: cv2.VideoWriter | None = None

    def write(self, rgb: np.ndarray) -> None:
        if self._writer is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            h, w = rgb.shape[:2]
            self._writer = cv2.VideoWriter(str(self.path), cv2.VideoWriter_fourcc(*"mp4v"),
                                           self.fps, (w, h))
            if not self._writer.isOpened():
                raise OSError(f"no MP4 encoder available to write {self.path}; "
                              "write PNG frames instead")
        self._writer.write(np.ascontiguousarray(rgb[..., ::-1]))  # OpenCV wants BGR

    def close(self) -> None:
        if self._writer is not None:
            self._writer.release()
            self._writer = None

    def __enter__(self) -> Mp4Writer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
