"""Frame quality: brightness, sharpness and change per frame; the take refused when too dark
or too blurred as a whole; blurred and duplicated frames dropped and counted."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from .config import EnrollConfig
from .errors import EnrollmentRefused

STAT_SIZE = 256  # px, the longest side the statistics are measured at (resolution-free)


@dataclass
class FrameQuality:
    brightness: np.ndarray  # [N] mean luma in [0, 1]
    sharpness: np.ndarray   # [N] variance of the Laplacian of the luma in [0, 1]


def _luma(frame: np.ndarray) -> np.ndarray:
    h, w = frame.shape[:2]
    s = min(1.0, STAT_SIZE / max(h, w))
    small = cv2.resize(frame, (max(1, round(w * s)), max(1, round(h * s))),
                       interpolation=cv2.INTER_AREA) if s < 1 else frame
    return cv2.cvtColor(small, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0


def measure(frames: Sequence[np.ndarray]) -> tuple[FrameQuality, list[np.ndarray]]:
    lumas = [_luma(f) for f in frames]
    bright = np.array([float(y.mean()) for y in lumas])
    sharp = np.array([float(cv2.Laplacian(y, cv2.CV_32F).var()) for y in lumas])
    return FrameQuality(bright, sharp), lumas


def select_frames(frames: Sequence[np.ndarray], config: EnrollConfig
                  ) -> tuple[list[int], dict[str, int], FrameQuality]:
    """(indices kept, {"blurred": n, "duplicate": n}, quality). Raises EnrollmentRefused
    for a take too dark or too blurred as a whole."""
    quality, lumas = measure(frames)
    if float(np.median(quality.brightness)) < config.min_brightness:
        raise EnrollmentRefused(
            "too_dark", f"The video is too dark (mean brightness "
            f"{np.median(quality.brightness):.2f}, at least {config.min_brightness} needed).",
            "Record facing a window or a lamp, with the light on your face.")
    median_sharp = float(np.median(quality.sharpness))
    if median_sharp < config.min_sharpness:
        raise EnrollmentRefused(
            "too_blurred", f"The video is too blurred (sharpness {median_sharp:.2e}, at "
            f"least {config.min_sharpness:.1e} needed).",
            "Keep the camera still, clean the lens, and turn slowly.")
    kept: list[int] = []
    dropped = {"blurred": 0, "duplicate": 0}
    for i in range(len(frames)):
        if quality.sharpness[i] < config.blur_ratio * median_sharp:
            dropped["blurred"] += 1
            continue
        if kept and float(np.abs(lumas[i] - lumas[kept[-1]]).mean()) < \
                config.duplicate_threshold:
            dropped["duplicate"] += 1
            continue
        kept.append(i)
    return kept, dropped, quality
