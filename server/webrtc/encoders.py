"""aiortc's video encoders with the target bit rate clamped to our settings.

aiortc's encoders follow the receiver's estimate (REMB) through ``target_bitrate``, clamped to
module constants (VP8 250 k..1.5 M, H.264 500 k..3 M bit/s) shared by every peer in the
process. There is no public hook for the encoder a sender makes, so each sender gets its own
clamped encoder put in its (name-mangled) encoder slot before its first frame: per instance,
no aiortc global changes. If aiortc's internals moved, the peer keeps aiortc's own encoder and
bounds, and a warning says so.

The codec itself counts the time of sending, whatever the frame's RTP timestamp says: libvpx and
x264 budget each frame's bits by the time since the last one, and on the capture clock
(server/webrtc/sender_clock.py) consecutive frames can be one tick or seconds apart (measured:
VP8 at 64 px spent 209 instead of 634 bytes a frame, 1.4 dB less; bench/encoder_clock.py). The
RTP timestamp on the wire stays the frame's own, read before encoding (aiortc's H.264 encoder
reads it after the codec rebased the frame to 1/30 s: 3000 ticks came back as 2999).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

from aiortc.codecs.base import Encoder
from aiortc.codecs.h264 import H264Encoder
from aiortc.codecs.vpx import Vp8Encoder
from aiortc.mediastreams import VIDEO_CLOCK_RATE, VIDEO_TIME_BASE, convert_timebase

log = logging.getLogger(__name__)

SENDER_ENCODER_SLOT = "_RTCRtpSender__encoder"  # RTCRtpSender.__encoder, made on first frame


def _clamped(base: type[Encoder]) -> type:
    private = f"_{base.__name__}__target_bitrate"  # the base reads it for the VBV buffer size

    class Clamped(base):
        def __init__(self, low: int, high: int,
                     clock: Callable[[], float] = time.monotonic) -> None:
            super().__init__()
            self.bitrate_range = (low, high)
            self.target_bitrate = getattr(self, private)  # aiortc's start value, clamped
            self._clock = clock
            self._start: float | None = None
            self._codec_pts = -1

        def encode(self, frame: Any, force_keyframe: bool = False) -> tuple[list[bytes], int]:
            """``frame`` encoded as if it were stamped with its sending time; the RTP
            timestamp returned is its own."""
            timestamp = convert_timebase(frame.pts, frame.time_base, VIDEO_TIME_BASE)
            now = self._clock()
            self._start = now if self._start is None else self._start
            self._codec_pts = max(round((now - self._start) * VIDEO_CLOCK_RATE),
                                  self._codec_pts + 1)
            frame.pts, frame.time_base = self._codec_pts, VIDEO_TIME_BASE
            payloads, _ = super().encode(frame, force_keyframe)
            return payloads, timestamp

        @property
        def target_bitrate(self) -> int:
            return self._clamped_target

        @target_bitrate.setter
        def target_bitrate(self, bitrate: int) -> None:
            low, high = self.bitrate_range
            self._clamped_target = max(low, min(int(bitrate), high))
            setattr(self, private, self._clamped_target)

    Clamped.__name__ = Clamped.__qualname__ = f"Clamped{base.__name__}"
    return Clamped


ClampedVp8Encoder = _clamped(Vp8Encoder)
ClampedH264Encoder = _clamped(H264Encoder)
ENCODERS = {"video/vp8": ClampedVp8Encoder, "video/h264": ClampedH264Encoder}


def install_encoder(sender: Any, mime_type: str, low: int, high: int) -> Any | None:
    """Give ``sender`` a clamped encoder for ``mime_type``; the encoder, or None when aiortc
    keeps its own (an unknown codec, or a sender without the slot)."""
    factory = ENCODERS.get(mime_type.lower())
    if factory is None:
        return None
    if getattr(sender, SENDER_ENCODER_SLOT, "missing") is not None:
        log.warning("aiortc's RTCRtpSender has no empty encoder slot: the bit rate stays "
                    "within aiortc's own bounds, not webrtc_min/max_bitrate")
        return None
    encoder = factory(low, high)
    setattr(sender, SENDER_ENCODER_SLOT, encoder)
    return encoder


H264_START_CODE = b"\x00\x00\x00\x01"


class RawVp8Encoder(ClampedVp8Encoder):
    """Each frame's whole VP8 bitstream as its one payload, for a fan-out (server/webrtc/
    fanout.py): every viewer's sender packs it with aiortc's ``pack``, under its own picture
    ids."""

    @classmethod
    def _packetize(cls, buffer: bytes, picture_id: int) -> list[bytes]:
        return [buffer] if buffer else []  # empty: the rate control dropped the frame

    @staticmethod
    def is_keyframe(data: bytes) -> bool:
        return not data[0] & 1  # the frame tag's inverted key-frame bit (RFC 6386, 9.1)


class RawH264Encoder(ClampedH264Encoder):
    """Each frame's NAL units in one Annex B bitstream (what aiortc's ``pack`` splits)."""

    @classmethod
    def _packetize(cls, packages: Any) -> list[bytes]:
        units = [u for u in packages if u]
        return [b"".join(H264_START_CODE + u for u in units)] if units else []

    @staticmethod
    def is_keyframe(data: bytes) -> bool:
        return any(u and u[0] & 0x1F == 5 for u in H264Encoder._split_bitstream(data))  # IDR


RAW_ENCODERS = {"video/vp8": RawVp8Encoder, "video/h264": RawH264Encoder}
