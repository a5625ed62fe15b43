"""One target tracked across frames: the shared loop of the face and body pipelines."""

from __future__ import annotations

from typing import Any

import numpy as np

from .roi import settle_rect
from .types import RotatedRect


class SingleTargetPipeline:
    """detect -> region of interest -> landmarks; the next frame's region comes from this
    frame's landmarks (no detector), and a target lost while tracked is detected again in the
    same frame. Subclasses give ``detect_roi`` and ``landmarks``."""

    roi: RotatedRect | None = None

    def reset(self) -> None:
        self.roi = None

    def detect_roi(self, frame_bgr: np.ndarray) -> RotatedRect | None:
        raise NotImplementedError

    def landmarks(self, frame_bgr: np.ndarray, roi: RotatedRect
                  ) -> tuple[Any, RotatedRect] | None:
        """(the landmarks, the next frame's region), or None when the target is not there."""
        raise NotImplementedError

    def _find(self, frame_bgr: np.ndarray, roi: RotatedRect | None):
        return self.landmarks(frame_bgr, roi) if roi is not None else None

    def __call__(self, frame_bgr: np.ndarray) -> Any | None:
        tracked = self.roi is not None
        roi = self.roi if tracked else self.detect_roi(frame_bgr)
        found = self._find(frame_bgr, roi)
        if found is None and tracked:  # lost: detect again in this frame
            roi = self.detect_roi(frame_bgr)
            found = self._find(frame_bgr, roi)
        self.roi = settle_rect(roi if tracked else None, found[1]) if found else None
        return found[0] if found is not None else None
