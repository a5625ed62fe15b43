"""H.264 through PyAV: one stateful encoder per participant, made at its first frame and made
again when the frame size changes (:class:`H264Stream`); the decoder the clients and tests use.
"""

from __future__ import annotations

import functools
import threading
from fractions import Fraction

import av
import numpy as np

from .choice import H264_CPU, H264_GPU, EncodeError, active_encoders


class H264Encoder:
    """One H.264 stream (Annex B, baseline-like: no B-frames, zero latency).

    Each ``encode`` call returns the packet bytes of exactly that frame (the encoder is set to
    emit one packet per frame with no reordering delay) and whether it is a keyframe. A
    keyframe is forced on the first frame, every ``gop`` frames, and on ``force_keyframe()``.
    """

    def __init__(self, width: int, height: int, *, fps: float = 30.0, gop: int = 60,
                 crf: int = 28, codec: str | None = None) -> None:
        if width % 2 or height % 2:
            raise EncodeError(f"H.264 needs even frame sizes, got {width}x{height}")
        self.width, self.height, self.gop = width, height, gop
        self.codec = active_encoders().h264 if codec is None else codec
        if self.codec not in (H264_CPU, H264_GPU):
            raise EncodeError(f"unknown H.264 encoder {self.codec!r}")
        self._ctx = av.CodecContext.create(self.codec, "w")
        self._ctx.width, self._ctx.height = width, height
        self._ctx.pix_fmt = "yuv420p"
        self._ctx.time_base = Fraction(1, 1000)
        self._ctx.framerate = Fraction(round(fps * 1000), 1000)
        self._ctx.gop_size = gop
        self._ctx.max_b_frames = 0
        if self.codec == H264_CPU:
            self._ctx.options = {"preset": "ultrafast", "tune": "zerolatency", "crf": str(crf),
                                 "repeat-headers": "1"}  # SPS/PPS on every keyframe
        else:  # NVENC: lowest latency, no lookahead; forced keyframes are IDR (with SPS/PPS)
            self._ctx.options = {"preset": "p1", "tune": "ull", "zerolatency": "1",
                                 "delay": "0", "forced-idr": "1", "rc": "constqp",
                                 "qp": str(crf)}
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


class H264Stream:
    """One participant's H.264 stream (stateful: never shared): opened at its first frame,
    opened again when the frame size changes; ``restart`` asks a keyframe of the next frame
    (the participant comes back from another codec, its decoder starts afresh)."""

    def __init__(self) -> None:
        self._encoder: H264Encoder | None = None
        self.lock = threading.Lock()  # one encode at a time; close waits for it

    def restart(self) -> None:
        if self._encoder is not None:
            self._encoder.force_keyframe()

    def encode(self, rgb: np.ndarray, fps: float) -> tuple[bytes, bool]:
        h, w = rgb.shape[:2]
        enc = self._encoder
        if enc is None or (enc.width, enc.height) != (w, h):
            if enc is not None:
                enc.close()
            enc = self._encoder = H264Encoder(w, h, fps=fps)
        return enc.encode(rgb)

    def close(self) -> None:
        if self._encoder is not None:
            self._encoder.close()
            self._encoder = None


@functools.cache
def probe_nvenc() -> bool:
    """PyAV lists ``h264_nvenc`` and one tiny frame encodes with it (cached: PyAV's FFmpeg
    lists NVENC even where no NVIDIA driver is, and only opening it tells)."""
    if H264_GPU not in av.codecs_available:
        return False
    try:
        enc = H264Encoder(64, 64, codec=H264_GPU)
        try:
            enc.encode(np.zeros((64, 64, 3), np.uint8))
        finally:
            enc.close()
        return True
    except Exception:  # noqa: BLE001 - no driver, no device, a busy one: libx264
        return False
