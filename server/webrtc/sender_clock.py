"""A peer's RTP timestamps and RTCP sender reports on the performer's capture clock.

A browser lip-syncs two tracks of one MediaStream by their RTCP sender reports: each pairs an
RTP timestamp with an NTP time, and the receiver plays both tracks so that media of the same
NTP time play together. aiortc pairs the last packet sent with the NTP time *of sending*, so
each report says its media was captured when it was sent; the picture (tracking, posing,
rendering, encoding) and the voice (a delay buffer) are sent after different delays, and the
browser then plays them that far apart.

With ``webrtc_sender_clock = capture`` both tracks are stamped on one per-peer
:class:`CaptureEpoch` instead: a video frame's RTP timestamp (90 kHz) is the capture instant of
the drive it shows, a voice packet's (48 kHz) follows its media time from its capture instant,
both on this server's monotonic clock (server/stream/capture_clock.py), and each sender report
pairs the RTP timestamp it names with the NTP time of that capture instant. Each track keeps
the capture instant of every timestamp it handed out lately (:class:`CaptureStamps`);
:func:`report_capture_clock` rewrites the sender's reports from them. ``send`` keeps aiortc's
reports (to measure both side by side: docs/benchmarks.md).
"""

from __future__ import annotations

import collections
import logging
import time
from dataclasses import dataclass
from typing import Any, Protocol

from aiortc import clock as aiortc_clock
from aiortc.rtp import RtcpSrPacket

from protocol.rtp_receiver import RTP_WRAP

log = logging.getLogger(__name__)

STAMPS_KEPT = 512  # timestamps a track remembers (>= 10 s of audio, 17 s of 30 fps video;
#                    a report names one sent within its last 0.5-1.5 s)

# aiortc's RTCRtpSender, used here only (aiortc 1.16; tests/test_sender_clock.py fails if they
# move): the RTP timestamp of the last packet sent, the report's "last SR" for its RTT, the
# coroutine that fetches the next encoded frame and the one that sends an RTCP compound.
SENDER_LAST_RTP = "_RTCRtpSender__rtp_timestamp"
SENDER_LSR = "_RTCRtpSender__lsr"
SENDER_NEXT_FRAME = "_next_encoded_frame"
SENDER_SEND_RTCP = "_send_rtcp"


@dataclass(frozen=True)
class CaptureEpoch:
    """One peer's zero: a monotonic instant and its NTP time (both tracks count from it)."""

    monotonic: float
    ntp: int  # 64-bit NTP (32.32) of ``monotonic``

    @classmethod
    def now(cls) -> CaptureEpoch:
        return cls(time.monotonic(), aiortc_clock.current_ntp_time())

    def ticks(self, at: float, rate: int) -> int:
        """``at`` (monotonic) in ``rate`` Hz ticks since the epoch."""
        return round((at - self.monotonic) * rate)

    def ntp_of(self, at: float) -> int:
        """The 64-bit NTP time of ``at`` (monotonic)."""
        return (self.ntp + round((at - self.monotonic) * 2**32)) % 2**64


class CaptureStamps:
    """The capture instant (monotonic) of each RTP timestamp a track handed out lately, by
    its value modulo 2^32 (what the sender puts on the wire less its random origin)."""

    def __init__(self, kept: int = STAMPS_KEPT) -> None:
        self._at: collections.OrderedDict[int, float] = collections.OrderedDict()
        self._kept = kept

    def note(self, pts: int, captured_at: float) -> None:
        key = pts % RTP_WRAP
        self._at[key] = captured_at
        self._at.move_to_end(key)
        while len(self._at) > self._kept:
            self._at.popitem(last=False)

    def captured_at(self, pts: int) -> float | None:
        return self._at.get(pts % RTP_WRAP)


class StampedTrack(Protocol):
    stamps: CaptureStamps | None


def report_capture_clock(sender: Any, track: StampedTrack, epoch: CaptureEpoch) -> bool:
    """Make ``sender``'s RTCP sender reports pair their RTP timestamp with the NTP time of its
    capture instant (``track.stamps``), not of its sending. False (aiortc's reports stay, a
    warning says so) when aiortc's sender no longer has what this reads.

    aiortc adds a random origin to the timestamps a track gives (a local of its RTP loop): it
    is learned once, when the sender fetches its second frame, as the RTP timestamp of the
    last packet sent (all of the first frame's) less that frame's timestamp. A report that
    names a timestamp not (yet) known is not sent: the next one, 0.5-1.5 s later, is."""
    missing = [name for name in (SENDER_LAST_RTP, SENDER_LSR, SENDER_NEXT_FRAME,
                                 SENDER_SEND_RTCP) if not hasattr(sender, name)]
    if missing or track.stamps is None:
        log.warning("aiortc's RTCRtpSender lacks %s: its sender reports stay on the send "
                    "time (webrtc_sender_clock = capture is not in effect)",
                    missing or "a track with capture stamps")
        return False
    fetch, send_rtcp = getattr(sender, SENDER_NEXT_FRAME), getattr(sender, SENDER_SEND_RTCP)
    learned: dict[str, int] = {}  # "last": the last frame's timestamp; "origin"

    async def next_encoded_frame(codec: Any) -> Any:
        if "origin" not in learned and "last" in learned:
            learned["origin"] = (getattr(sender, SENDER_LAST_RTP) - learned["last"]) % RTP_WRAP
        encoded = await fetch(codec)
        if encoded is not None:
            learned["last"] = encoded.timestamp
        return encoded

    async def send_reports(packets: list[Any]) -> None:
        for packet in packets:
            if not isinstance(packet, RtcpSrPacket) or not packet.sender_info.packet_count:
                continue
            at = (None if "origin" not in learned else track.stamps.captured_at(
                packet.sender_info.rtp_timestamp - learned["origin"]))
            if at is None:
                return  # not mapped yet: no report rather than one on the send time
            packet.sender_info.ntp_timestamp = epoch.ntp_of(at)
            # the receiver echoes this report's middle 32 bits: aiortc's RTT matches on them
            setattr(sender, SENDER_LSR, (packet.sender_info.ntp_timestamp >> 16) & 0xFFFFFFFF)
        await send_rtcp(packets)

    setattr(sender, SENDER_NEXT_FRAME, next_encoded_frame)
    setattr(sender, SENDER_SEND_RTCP, send_reports)
    return True
