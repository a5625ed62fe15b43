"""What both ends do with an aiortc RTP receiver: release a video frame at its last packet,
and tell a decoded frame's RTP timestamp.

aiortc's video ``JitterBuffer`` hands a frame to the decoder only when a packet of the next
frame arrives, so every frame waits one frame interval: each WHIP webcam frame before it was
tracked (measured with tests/test_webrtc_publisher_clock.py's publisher: arrival less capture
398-422 ms at 2.5 frames a second, 108-117 ms at 10), and each frame a Python WHEP viewer
(client/webrtc.py) decodes. RTP marks a frame's last packet with the marker bit (RFC 7741 for
VP8, RFC 6184 for H.264), and browsers go by it: :class:`MarkerJitterBuffer` releases a frame
as soon as its packets are all in, from the first one kept to the marked one. Reordering,
loss and the picture-loss requests stay aiortc's (the base class); without a marker it
behaves as before.

:func:`frame_rtp_timestamp` maps a decoded frame's pts back to its RTP timestamp (the server
reads a WHIP publisher's capture times by it, a client its sender reports).

It lives in ``protocol`` because both ends receive RTP (the server a WHIP webcam, the client a
WHEP stream) and the client may not import the server; it is the one protocol module that
imports aiortc, and ``protocol`` itself does not import it.
"""

from __future__ import annotations

import logging
from typing import Any

from aiortc.jitterbuffer import JitterBuffer, JitterFrame

log = logging.getLogger(__name__)

# aiortc 1.16's RTCRtpReceiver keeps its buffer here (tests/test_webrtc_jitter.py fails if
# it moves)
RECEIVER_JITTER_BUFFER = "_RTCRtpReceiver__jitter_buffer"
TIMESTAMP_MAPPER = "_RTCRtpReceiver__timestamp_mapper"  # RTP timestamp -> a frame's pts
RTP_WRAP = 2**32
VIDEO_CAPACITY = 512  # packets, as aiortc's own video buffer


class MarkerJitterBuffer(JitterBuffer):
    def __init__(self, capacity: int = VIDEO_CAPACITY) -> None:
        super().__init__(capacity=capacity, is_video=True)

    def _remove_frame(self, sequence_number: int) -> JitterFrame | None:
        packets: list[Any] = []
        for count in range(self.capacity):
            packet = self._packets[(self._origin + count) % self.capacity]
            if packet is None or (packets and packet.timestamp != packets[0].timestamp):
                break  # a gap, or the next frame: the base class decides
            packets.append(packet)
            if packet.marker:  # the frame's last packet, and none missing before it
                self.remove(count + 1)
                return JitterFrame(data=b"".join(p._data for p in packets),
                                   timestamp=packet.timestamp)
        return super()._remove_frame(sequence_number)


def release_on_marker(receiver: Any) -> bool:
    """Give ``receiver`` (an aiortc video receiver, before its first packet) a
    :class:`MarkerJitterBuffer`; False (and aiortc's buffer kept) if aiortc moved it."""
    if not isinstance(getattr(receiver, RECEIVER_JITTER_BUFFER, None), JitterBuffer):
        log.warning("aiortc's receiver has no %s: frames wait for the next one",
                    RECEIVER_JITTER_BUFFER)
        return False
    setattr(receiver, RECEIVER_JITTER_BUFFER, MarkerJitterBuffer())
    return True


def frame_rtp_timestamp(receiver: Any, pts: int | None) -> int | None:
    """The RTP timestamp of the frame ``receiver`` decoded with ``pts``: aiortc counts a
    track's pts from the first frame it decoded, which need not be the first packet a hook
    saw. None before its first frame, without a pts, or if aiortc moved it."""
    origin = getattr(getattr(receiver, TIMESTAMP_MAPPER, None), "_origin", None)
    return None if origin is None or pts is None else (pts + origin) % RTP_WRAP
