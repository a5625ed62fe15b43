"""Frame encoders: JPEG (quality drops while the view moves), PNG with alpha, 16-bit depth PNG,
and H.264 through PyAV (one stateful encoder per session, re-created on a size change).

Inputs are uint8 RGB ``[H, W, 3]`` (alpha ``[H, W]`` uint8, depth ``[H, W]`` float metres).
"""

from __future__ import annotations

from fractions import Fraction

import av
import cv2
import numpy as np

DEPTH_MAX_MM = 65535  # 65.535 m: deeper is clipped; 0 means no surface


class EncodeError(RuntimeError):
    pass


def encode_jpeg(rgb: np.ndarray, quality: int) -> bytes:
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


class H264Encoder:
    """One H.264 stream (Annex B, baseline-like: no B-frames, zero latency).

    Each ``encode`` call returns the packet bytes of exactly that frame (the encoder is set to
    emit one packet per frame with no reordering delay) and whether it is a keyframe. A
    keyframe is forced on the first frame, every ``gop`` frames, and on ``force_keyframe()``.
    """

    def __init__(self, width: int, height: int, *, fps: float = 30.0, gop: int = 60,
                 crf: int = 28) -> None:
        if width % 2 or height % 2:
            raise EncodeError(f"H.264 needs even frame sizes, got {width}x{height}")
        self.width, self.height, self.gop = width, height, gop
        self._ctx = av.CodecContext.create("libx264", "w")
        self._ctx.width, self._ctx.height = width, height
        self._ctx.pix_fmt = "yuv420p"
        self._ctx.time_base = Fraction(1, 1000)
        self._ctx.framerate = Fraction(round(fps * 1000), 1000)
        self._ctx.gop_size = gop
        self._ctx.max_b_frames = 0
        self._ctx.options = {"preset": "ultrafast", "tune": "zerolatency", "crf": str(crf),
                             "repeat-headers": "1"}  # SPS/PPS on every keyframe
        self._ctx.open()
        self._count = 0
        self._force = True

    def force_keyframe(self) -> None:
        self._force = True

    def encode(self, rgb: np.ndarray) -> tuple[bytes, bool]:
        """uint8 RGB [H, W, 3] -> (Annex B bytes of this frame, keyframe)."""
        if rgb.shape[:2] != (self.height, self.width):
            raise EncodeError(f"frame {rgb.shape[1]}x{rgb.shape[0]} does not match the "
                              f"encoder's {self.width}x{self.height}")
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
        frame.pts = self._count
        key = self._force or self._count % self.gop == 0
        frame.pict_type = av.video.frame.PictureType.I if key else \
            av.video.frame.PictureType.NONE
        self._force = False
        self._count += 1
        packets = self._ctx.encode(frame)
        data = b"".join(bytes(p) for p in packets)
        return data, key or any(p.is_keyframe for p in packets)

    def close(self) -> None:
        try:
            self._ctx.close()
        except Exception:  # noqa: BLE001 - closing a codec must never break a teardown
            pass


class H264Decoder:
    """Decodes the stream of :class:`H264Encoder` (tests and Python clients)."""

    def __init__(self) -> None:
        self._ctx = av.CodecContext.create("h264", "r")

    def decode(self, data: bytes) -> list[np.ndarray]:
        """uint8 RGB frames [H, W, 3] decoded from one frame's bytes."""
        # One packet per frame (see H264Encoder): no parser, which would hold the last one back.
        return [f.to_ndarray(format="rgb24") for f in self._ctx.decode(av.Packet(data))]
