"""Still-image encoders: JPEG (OpenCV, or nvJPEG on a CUDA tensor), PNG with alpha, 16-bit depth
PNG. Inputs are uint8 RGB ``[H, W, 3]`` (alpha ``[H, W]`` uint8, depth ``[H, W]`` float metres).
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from .choice import JPEG_GPU, EncodeError, active_encoders

DEPTH_MAX_MM = 65535  # 65.535 m: deeper is clipped; 0 means no surface


def frame_rgb(rgb: Any, codec: str, alpha: bool) -> Any:
    """The picture as the encoder of ``codec`` takes it, from a float tensor [H, W, 3]: a
    uint8 CUDA tensor where nvJPEG encodes it (no host copy of the image), else uint8 numpy."""
    from avatar_core.render.types import to_uint8

    if (codec == "jpeg" and not alpha and rgb.is_cuda
            and active_encoders().jpeg == JPEG_GPU):
        return (rgb.clamp(0, 1) * 255).round().byte()
    return to_uint8(rgb)


def _encode_jpeg_gpu(rgb: Any, quality: int) -> bytes:
    """uint8 CUDA tensor [H, W, 3] -> JPEG bytes, encoded by nvJPEG."""
    import torchvision.io

    data = torchvision.io.encode_jpeg(rgb.permute(2, 0, 1).contiguous(), quality=int(quality))
    return data.cpu().numpy().tobytes()


def encode_jpeg(rgb: Any, quality: int) -> bytes:
    """uint8 RGB [H, W, 3]: numpy (OpenCV) or a CUDA tensor from :func:`frame_rgb` (nvJPEG)."""
    if not isinstance(rgb, np.ndarray):
        return _encode_jpeg_gpu(rgb, quality)
    ok, buf = cv2.imencode(".jpg", rgb[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise EncodeError("JPEG encoding failed")
    return buf.tobytes()


def encode_png(rgb: np.ndarray, alpha: np.ndarray | None = None) -> bytes:
    """RGB, or RGBA when ``alpha`` is given. Compression 1: fast, still lossless."""
    bgr = rgb[..., ::-1]
    img = bgr if alpha is None else np.dstack([bgr, alpha])  # [H, W, 3|4]
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise EncodeError("PNG encoding failed")
    return buf.tobytes()


def encode_depth_png(depth_m: np.ndarray) -> bytes:
    """Depth in metres [H, W] -> 16-bit grey PNG in millimetres (0: no surface)."""
    mm = np.clip(np.nan_to_num(depth_m, nan=0.0) * 1000.0, 0, DEPTH_MAX_MM)
    ok, buf = cv2.imencode(".png", np.round(mm).astype(np.uint16),
                           [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise EncodeError("depth PNG encoding failed")
    return buf.tobytes()


def decode_depth_png(data: bytes) -> np.ndarray:
    """The inverse of :func:`encode_depth_png`: metres [H, W] float32."""
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    return img.astype(np.float32) / 1000.0
