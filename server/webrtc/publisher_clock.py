"""A WHIP publisher's capture times, read from its own RTCP sender reports.

A browser stamps its webcam and its microphone on one clock: each track's RTCP sender report
pairs an RTP timestamp with the NTP time of the same instant (RFC 3550 6.4.1), which is how a
receiver lip-syncs them. The server reads those reports here so that a published frame's
tracked drive and a published voice packet carry capture times (``t_capture``) on that one
clock, as a WebSocket performer's stamps do: a WebSocket viewer then syncs a WHIP performer
too, and the WebRTC senders' capture clock (sender_clock.py) gets the frame's capture instant,
not its arrival after the jitter buffer and the decoder.

Only a peer that publishes its webcam stamps its voice this way: a WHEP performer's drives
come over its data channel stamped on a clock of its own, which its voice's stamps must share
to be synced, so its RTP voice stays unstamped (its arrival stands in, as before).

Times are seconds since a per-peer origin (the first report's NTP second, less
``ORIGIN_MARGIN_S``) so that they fit the protocol's ``CaptureTime``. Until a track's first
report arrives its times are None (its arrival stands in, as before). A publisher controls its
reports: a time outside ``CaptureTime`` (0 to ``MAX_CAPTURE_TIME``) is None; nothing raises.
"""

from __future__ import annotations

from typing import Any

from protocol.messages import MAX_CAPTURE_TIME
from protocol.rtp_receiver import RTP_WRAP, frame_rtp_timestamp

NTP_FRACTION = 2**32  # NTP's 32.32 fixed point
ORIGIN_MARGIN_S = 3600.0  # media stamped up to this long before the first report stays >= 0
RTCP_HANDLER = "_handle_rtcp_packet"  # RTCRtpReceiver's entry for each routed RTCP packet


def signed_ticks(a: int, b: int) -> int:
    """``a - b`` for 32-bit RTP timestamps, wrap-safe: in [-2**31, 2**31)."""
    return (a - b + 2**31) % RTP_WRAP - 2**31


class PublisherClock:
    """One peer's tracks on its sender-report clock (one origin for all of them)."""

    def __init__(self) -> None:
        self.origin: float | None = None  # NTP seconds of time 0
        self.refused = 0                  # reports without a usable NTP time

    def track(self, clock_rate: int) -> TrackReports:
        return TrackReports(self, clock_rate)

    def watch(self, receiver: Any, clock_rate: int) -> TrackReports | None:
        """The reports of ``receiver``'s track, read as aiortc routes them; None if aiortc
        moved its handler (no capture times then)."""
        reports = self.track(clock_rate)
        return reports if reports.watch(receiver) else None

    def note(self, ntp_timestamp: int) -> float | None:
        """A report's NTP time (64-bit) as seconds since the origin; None if unusable."""
        seconds = ntp_timestamp / NTP_FRACTION
        if seconds <= 0:  # a sender without a wall clock
            self.refused += 1
            return None
        if self.origin is None:
            self.origin = float(int(seconds)) - ORIGIN_MARGIN_S
        return seconds - self.origin


class TrackReports:
    """One received track's last sender report: its RTP timestamps as capture times."""

    def __init__(self, clock: PublisherClock, clock_rate: int) -> None:
        self.clock, self.clock_rate = clock, clock_rate
        self._last: tuple[int, float] | None = None  # (RTP timestamp, its time)
        self.receiver: Any = None  # the aiortc receiver watched

    def note(self, rtp_timestamp: int, ntp_timestamp: int) -> None:
        at = self.clock.note(ntp_timestamp)
        if at is not None:
            self._last = (rtp_timestamp % RTP_WRAP, at)

    def capture_time(self, rtp_timestamp: int | None) -> float | None:
        """When the media of ``rtp_timestamp`` was captured (seconds on the peer's clock)."""
        if self._last is None or rtp_timestamp is None:
            return None
        rtp, at = self._last
        t = at + signed_ticks(rtp_timestamp % RTP_WRAP, rtp) / self.clock_rate
        return t if 0.0 <= t <= MAX_CAPTURE_TIME else None

    def frame_capture_time(self, pts: int | None) -> float | None:
        """When the frame the watched receiver decoded with ``pts`` was captured."""
        return self.capture_time(frame_rtp_timestamp(self.receiver, pts))

    def watch(self, receiver: Any) -> bool:
        """Take ``receiver``'s sender reports (aiortc routes them by SSRC) before aiortc does;
        False (no capture times, nothing else changed) if aiortc moved its handler."""
        from aiortc.rtp import RtcpSrPacket

        original = getattr(receiver, RTCP_HANDLER, None)
        if original is None:
            return False
        self.receiver = receiver

        async def handle(packet: Any) -> None:
            if isinstance(packet, RtcpSrPacket):
                info = packet.sender_info
                self.note(info.rtp_timestamp, info.ntp_timestamp)
            await original(packet)

        setattr(receiver, RTCP_HANDLER, handle)
        return True
