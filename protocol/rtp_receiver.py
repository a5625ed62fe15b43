"""A published video frame released at its last packet, not at the next frame's first.

aiortc's video ``JitterBuffer`` hands a frame to the decoder only when a packet of the next
frame arrives, so each WHIP webcam frame waited one frame interval before it was tracked
(measured with tests/test_webrtc_publisher_clock.py's publisher: arrival less capture 398-422 ms
at 2.5 frames a second, 108-117 ms at 10). RTP marks a frame's last packet with the marker bit
(RFC 7741 for VP8, RFC 6184 for H.264): :class:`MarkerJitterBuffer` releases a frame as soon as
its packets are all in, from the first one kept to the marked one. Reordering, loss and the
picture-loss requests stay aiortc's (the base class); without a marker it behaves as before.
"""

from __future__ import annotations

import logging
from typing import Any

from aiortc.jitterbuffer import JitterBuffer, JitterFrame

log = logging.getLogger(__name__)

# aiortc 1.16's RTCRtpReceiver keeps its buffer here (tests/test_webrtc_jitter.py fails if
# it moves)
RECEIVER_JITTER_BUFFER = "_RTCRtpReceiver__jitter_buffer"
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
