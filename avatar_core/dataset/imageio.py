"""Image files of a dataset: cheap header reads (size, channels, bit depth without decoding),
decoding to the engine's arrays, and encoding (cv2, so RGB <-> BGR happens here only)."""

from __future__ import annotations

import os
import struct
import threading
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

__all__ = ["ImageHeader", "decode_gray", "decode_rgb", "encode", "read_header",
           "write_atomic"]

_PNG_SIG = b"\x89PNG\r\n\x1a\n"
_PNG_CHANNELS = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}  # colour type -> channels (3: palette)
# JPEG start-of-frame markers (C4 = DHT, C8 = JPG, CC = DAC are not frames).
_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_MAX_SEGMENTS = 4096  # a bound on the marker walk of a damaged JPEG


@dataclass(frozen=True)
class ImageHeader:
    kind: str       # "png" | "jpg"
    width: int
    height: int
    channels: int
    bit_depth: int
    palette: bool = False


def _png_header(f) -> ImageHeader:
    f.seek(0)
    head = f.read(33)
    if len(head) < 33 or head[12:16] != b"IHDR":
        raise ValueError("truncated PNG header")
    width, height, depth, colour = struct.unpack(">IIBB", head[16:26])
    if colour not in _PNG_CHANNELS:
        raise ValueError(f"unknown PNG colour type {colour}")
    return ImageHeader("png", width, height, _PNG_CHANNELS[colour], depth, colour == 3)


def _jpeg_header(f) -> ImageHeader:
    f.seek(2)  # after SOI
    for _ in range(_MAX_SEGMENTS):
        b = f.read(1)
        if b != b"\xff":
            break  # every segment starts with 0xFF
        while b == b"\xff":  # fill bytes before a marker
            b = f.read(1)
        if not b:
            break
        marker = b[0]
        if marker == 0x01 or 0xD0 <= marker <= 0xD8:  # stand-alone markers: no length
            continue
        size = f.read(2)
        if len(size) < 2:
            break
        (length,) = struct.unpack(">H", size)
        if marker in _SOF:
            body = f.read(6)
            if len(body) < 6:
                break
            depth, height, width, comps = struct.unpack(">BHHB", body)
            return ImageHeader("jpg", width, height, comps, depth)
        if marker == 0xDA:  # start of scan before any frame header
            break
        f.seek(length - 2, os.SEEK_CUR)
    raise ValueError("no JPEG frame header found")


def read_header(path: str | Path) -> ImageHeader:
    """Size, channels and bit depth from the first bytes of a PNG or JPEG file (no decode).
    Raises ValueError when the file is neither or is truncated."""
    with open(path, "rb") as f:
        sig = f.read(8)
        if sig == _PNG_SIG:
            return _png_header(f)
        if sig[:2] == b"\xff\xd8":
            return _jpeg_header(f)
    raise ValueError("not a PNG or JPEG file")


def _decode(path: str | Path, flags: int) -> np.ndarray:
    data = np.fromfile(str(path), dtype=np.uint8)  # imread cannot report why it failed
    img = cv2.imdecode(data, flags) if data.size else None
    if img is None:
        raise ValueError(f"cannot decode image {path}")
    return img


def decode_rgb(path: str | Path) -> np.ndarray:
    """uint8 [H, W, 3] RGB."""
    return cv2.cvtColor(_decode(path, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def decode_gray(path: str | Path) -> np.ndarray:
    """uint8 [H, W] of a single-channel 8-bit file (alpha or part labels, never converted)."""
    img = _decode(path, cv2.IMREAD_UNCHANGED)
    if img.ndim != 2 or img.dtype != np.uint8:
        raise ValueError(f"{path} must be 8-bit single-channel, got {img.dtype} {img.shape}")
    return img


def encode(image: np.ndarray, ext: str, *, jpeg_quality: int = 95) -> bytes:
    """RGB [H, W, 3] or single-channel [H, W] uint8 -> file bytes ("png" lossless)."""
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    params = [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality] if ext == "jpg" else []
    ok, buf = cv2.imencode(f".{ext}", np.ascontiguousarray(image), params)
    if not ok:
        raise ValueError(f"cannot encode a {image.shape} image as {ext}")
    return buf.tobytes()


def write_atomic(path: Path, data: bytes) -> None:
    """Write under a temporary name, then rename: a reader never sees half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)
