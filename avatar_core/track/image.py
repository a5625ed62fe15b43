"""Frames in: encoded JPEG / PNG bytes -> BGR uint8, and checks on raw frames.

The dimensions are read from the header before anything is decoded, so an oversized image is
refused without allocating it (a "decompression bomb" costs nothing).
"""

from __future__ import annotations

import struct

import cv2
import numpy as np

from .types import TrackingInputError

DEFAULT_MAX_PIXELS = 4096 * 4096

_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
# JPEG start-of-frame markers (they carry the size); C4, C8 and CC are not frames.
_JPEG_SOF = set(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def image_size(data: bytes) -> tuple[str, int, int]:
    """(format, width, height) read from a PNG or JPEG header; TrackingInputError otherwise."""
    if data.startswith(_PNG_MAGIC):
        if len(data) < 24 or data[12:16] != b"IHDR":
            raise TrackingInputError("corrupt PNG: no IHDR header")
        width, height = struct.unpack(">II", data[16:24])
        return "png", width, height
    if data.startswith(b"\xff\xd8"):
        i = 2
        while i + 4 <= len(data):
            if data[i] != 0xFF:
                raise TrackingInputError("corrupt JPEG: bad marker before the frame header")
            marker = data[i + 1]
            if marker == 0xFF:  # fill byte
                i += 1
                continue
            if marker in (0x01,) or 0xD0 <= marker <= 0xD7:  # no length
                i += 2
                continue
            (length,) = struct.unpack(">H", data[i + 2:i + 4])
            if marker in _JPEG_SOF:
                if i + 9 > len(data):
                    break
                height, width = struct.unpack(">HH", data[i + 5:i + 9])
                return "jpeg", width, height
            if marker == 0xDA or length < 2:  # scan data before any frame header
                break
            i += 2 + length
        raise TrackingInputError("corrupt JPEG: no frame header (SOF) found")
    raise TrackingInputError("unsupported image: expected JPEG or PNG bytes")


def decode_image(data: bytes, max_pixels: int = DEFAULT_MAX_PIXELS) -> np.ndarray:
    """Encoded JPEG / PNG bytes -> [H, W, 3] uint8 BGR.

    Raises TrackingInputError for empty or non-bytes input, anything but JPEG / PNG, a
    header announcing more than `max_pixels` (checked before decoding), or data that does
    not decode.
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise TrackingInputError(f"expected encoded image bytes, got {type(data).__name__}")
    data = bytes(data)
    if not data:
        raise TrackingInputError("empty image")
    kind, width, height = image_size(data)
    if width <= 0 or height <= 0:
        raise TrackingInputError(f"{kind} header gives an empty image ({width}x{height})")
    if width * height > max_pixels:
        raise TrackingInputError(f"image too large: {width}x{height} = {width * height} "
                                 f"pixels > {max_pixels}")
    frame = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if frame is None or frame.size == 0:
        raise TrackingInputError(f"corrupt {kind}: it does not decode")
    if frame.shape[:2] != (height, width):
        raise TrackingInputError(f"corrupt {kind}: decoded {frame.shape[1]}x{frame.shape[0]}, "
                                 f"header says {width}x{height}")
    return frame


def check_frame(frame: np.ndarray, max_pixels: int = DEFAULT_MAX_PIXELS) -> np.ndarray:
    """A raw frame -> [H, W, 3] uint8 BGR (grey and BGRA are converted); clear errors else."""
    if not isinstance(frame, np.ndarray):
        raise TrackingInputError(f"expected a numpy frame, got {type(frame).__name__}")
    if frame.ndim == 2:
        frame = frame[:, :, None]
    if frame.ndim != 3 or frame.shape[2] not in (1, 3, 4):
        raise TrackingInputError(f"expected an [H, W, 3] BGR frame, got shape {frame.shape}")
    if frame.shape[0] == 0 or frame.shape[1] == 0:
        raise TrackingInputError(f"empty frame (shape {frame.shape})")
    if frame.shape[0] * frame.shape[1] > max_pixels:
        raise TrackingInputError(f"frame too large: {frame.shape[1]}x{frame.shape[0]} > "
                                 f"{max_pixels} pixels")
    if frame.dtype != np.uint8:
        raise TrackingInputError(f"expected a uint8 frame, got {frame.dtype}")
    if frame.shape[2] == 1:
        frame = cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)
    elif frame.shape[2] == 4:
        frame = cv2.cvtColor(frame, cv2.COLOR_BGRA2BGR)
    return np.ascontiguousarray(frame)
