"""Frame images as numpy arrays; OpenCV is imported only when a frame is decoded."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from protocol import Frame


def decode_image(frame: Frame | bytes, *, rgb: bool = True) -> np.ndarray:
    """A JPEG/PNG frame as uint8 [H, W, 3] (RGB by default, BGR with rgb=False)."""
    import cv2

    if isinstance(frame, Frame) and frame.codec == "h264":
        raise ValueError("h264 frames are a video stream: decode them with PyAV, not one by one")
    data = frame.data if isinstance(frame, Frame) else frame
    image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        raise ValueError("the frame is not a decodable JPEG or PNG image")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB) if rgb else image


def decode_depth(frame: Frame) -> np.ndarray | None:
    """The frame's depth in metres (float32 [H, W]; 0 where nothing), or None if not sent."""
    import cv2

    if frame.depth is None:
        return None
    mm = cv2.imdecode(np.frombuffer(frame.depth, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if mm is None:
        raise ValueError("the depth is not a decodable 16-bit PNG")
    return mm.astype(np.float32) / 1000.0


def save_frame(frame: Frame, path: Path) -> Path:
    """Write the frame's encoded bytes as they came (no re-encoding): .jpg or .png."""
    if frame.codec == "h264":
        raise ValueError("h264 frames cannot be saved as single images")
    path = Path(path).with_suffix(".jpg" if frame.codec == "jpeg" else ".png")
    path.write_bytes(frame.data)
    return path
