"""aiortc's video encoders with the target bit rate clamped to our settings.

aiortc's encoders follow the receiver's estimate (REMB) through ``target_bitrate``, clamped to
module constants (VP8 250 k..1.5 M, H.264 500 k..3 M bit/s) shared by every peer in the
process. There is no public hook for the encoder a sender makes, so each sender gets its own
clamped encoder put in its (name-mangled) encoder slot before its first frame: per instance,
no aiortc global changes. If aiortc's internals moved, the peer keeps aiortc's own encoder and
bounds, and a warning says so.
"""

from __future__ import annotations

import logging
from typing import Any

from aiortc.codecs.h264 import H264Encoder
from aiortc.codecs.vpx import Vp8Encoder

log = logging.getLogger(__name__)

SENDER_ENCODER_SLOT = "_RTCRtpSender__encoder"  # RTCRtpSender.__encoder, made on first frame


def _clamped(base: type) -> type:
    private = f"_{base.__name__}__target_bitrate"  # the base reads it for the VBV buffer size

    class Clamped(base):
        def __init__(self, low: int, high: int) -> None:
            super().__init__()
            self.bitrate_range = (low, high)
            self.target_bitrate = getattr(self, private)  # aiortc's start value, clamped

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
