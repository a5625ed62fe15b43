"""Decoding a video into RGB frames with OpenCV: the stand-in until the probe/limits module
(``enroll.video``, PyAV) is on this branch. Refuses what it cannot read, with what to do."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from .errors import EnrollmentRefused


def read_frames(path: str | Path, *, max_frames: int = 3_600, max_pixels: int = 4096 * 2160
                ) -> tuple[list[np.ndarray], float]:
    """(uint8 [H, W, 3] RGB frames, fps) of a video file; at most ``max_frames`` frames."""
    path = Path(path)
    if not path.is_file():
        raise EnrollmentRefused("no_video", f"{path} is not a file.",
                                "Give the path of a video recorded with your camera.")
    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            raise EnrollmentRefused("corrupt_video", f"{path.name} cannot be decoded.",
                                    "Record it again, or export it as an mp4 (H.264).")
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        frames: list[np.ndarray] = []
        while len(frames) < max_frames:
            ok, frame = cap.read()
            if not ok:
                break
            if frame.shape[0] * frame.shape[1] > max_pixels:
                raise EnrollmentRefused(
                    "too_large_resolution", f"{path.name} is {frame.shape[1]}x"
                    f"{frame.shape[0]}, more than {max_pixels} pixels a frame.",
                    "Record at 1080p or less.")
            frames.append(np.ascontiguousarray(frame[..., ::-1]))
    finally:
        cap.release()
    if not frames:
        raise EnrollmentRefused("no_video_stream", f"{path.name} holds no video frames.",
                                "Give a video file (not audio only), recorded with your camera.")
    return frames, fps if 0 < fps <= 240 else 30.0
