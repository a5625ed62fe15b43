"""Person mask: selfie_segmentation (general, 256x256) on the whole frame, resized back."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from .onnx_model import ModelSource, OnnxModel


class SelfieSegmentation:
    def __init__(self, models: ModelSource = None, providers: Sequence | None = None,
                 threads: int | None = None):
        self.model = OnnxModel("selfie_segmentation", models, providers, threads)

    def __call__(self, frame_bgr: np.ndarray) -> np.ndarray:
        """[H, W] float32 person probability in [0, 1] at the frame's size."""
        h, w = frame_bgr.shape[:2]
        mw, mh = self.model.input_size
        small = cv2.resize(frame_bgr, (mw, mh), interpolation=cv2.INTER_AREA)
        x = cv2.cvtColor(small, cv2.COLOR_BGR2RGB).astype(np.float32)[None] / 255.0
        (prob,) = self.model(x)  # [1, 256, 256, 1], already a probability
        mask = cv2.resize(prob[0, :, :, 0], (w, h), interpolation=cv2.INTER_LINEAR)
        return np.clip(mask, 0.0, 1.0).astype(np.float32)
