"""A peer's audio: a performer's Opus in, each seat's Opus out, never decoded.

Out: :class:`VoiceTrack` is an aiortc track whose ``recv`` returns encoded ``av.Packet``s
(aiortc's documented way to send pre-encoded media: its sender then only packs them, as for
``MediaPlayer(decode=False)``), taken from a listener of the seat's voice
(server/rooms/voice.py). A seat with no voice leaves the track waiting: nothing is sent.

In: aiortc decodes every received audio packet and has no hook for the encoded ones, so the
audio receiver's RTP handler is replaced on that one receiver instance (as
server/webrtc/encoders.py does for an encoder): each RTP packet's payload goes to the seat's
voice, which checks and forwards it; nothing reaches aiortc's decoder. A peer that may not
publish (a viewer) gets a handler that drops and counts whatever arrives.
"""

from __future__ import annotations

import fractions
import logging
from typing import Any

import av
from aiortc import MediaStreamTrack
from aiortc import sdp as aiortc_sdp
from aiortc.mediastreams import MediaStreamError

from ..rooms.voice import CLOCK_RATE, Listener, SeatVoice, VoicePacket
from ..stream.capture_clock import ArrivalClock
from .publisher_clock import TrackReports
from .sender_clock import CaptureEpoch, CaptureStamps

log = logging.getLogger(__name__)

OPUS = "audio/opus"
TIME_BASE = fractions.Fraction(1, CLOCK_RATE)
RTP_HANDLER = "_handle_rtp_packet"  # RTCRtpReceiver's entry for each routed RTP packet


class VoiceTrack(MediaStreamTrack):
    """A seat's voice out. Timestamps (48 kHz) follow the seat's media time, so they stay
    continuous; with a :class:`~.sender_clock.CaptureEpoch` they start at the first packet's
    capture instant and each one's own capture instant is kept for the sender reports."""

    kind = "audio"

    def __init__(self, listener: Listener, position: int,
                 epoch: CaptureEpoch | None = None) -> None:
        super().__init__()
        self.listener = listener
        self.position = position  # the seat's place in the room (and in each frame's seats)
        self.sent = 0
        self.epoch = epoch
        self.stamps = None if epoch is None else CaptureStamps()
        self._shift: int | None = None  # media time -> ticks since the epoch

    async def recv(self) -> av.Packet:
        packet = await self.listener.next()
        if packet is None or self.readyState != "live":
            raise MediaStreamError
        out = av.Packet(packet.payload)
        out.pts, out.time_base = self._pts(packet), TIME_BASE
        self.sent += 1
        return out

    def _pts(self, packet: VoicePacket) -> int:
        if self.epoch is None:
            return packet.media_ts
        at = packet.arrived if packet.captured_at is None else packet.captured_at
        if self._shift is None:
            self._shift = max(0, self.epoch.ticks(at, CLOCK_RATE)) - packet.media_ts
        pts = packet.media_ts + self._shift
        self.stamps.note(pts, at)
        return pts

    def stop(self) -> None:
        super().stop()
        self.listener.close()


def opus_payload_type(answer_sdp: str, mid: str) -> int | None:
    """The Opus payload type negotiated on m-line ``mid``."""
    for media in aiortc_sdp.SessionDescription.parse(answer_sdp).media:
        if media.rtp.muxId == mid:
            return next((c.payloadType for c in media.rtp.codecs
                         if c.mimeType.lower() == OPUS), None)
    return None


def publish_voice(receiver: Any, voice: SeatVoice, publisher: object, payload_type: int,
                  reports: TrackReports | None = None, clock: ArrivalClock | None = None
                  ) -> None:
    """``receiver``'s Opus RTP payloads go to ``voice`` (checked there), undecoded. With the
    track's sender ``reports`` each packet carries its capture time on the publisher's clock,
    put on this server's by ``clock`` (the one the publisher's drives use)."""
    async def handle(packet: Any, arrival_time_ms: int = 0) -> None:
        if packet.payload_type != payload_type:
            voice.counts["garbage"] += 1  # not the negotiated Opus (aiortc would drop it too)
            return
        level = packet.extensions.audio_level  # RFC 6464: (voice activity, -dBov) when sent
        t_capture = None if reports is None else reports.capture_time(packet.timestamp)
        voice.publish(publisher, packet.payload, packet.timestamp, None, t_capture,
                      None if level is None else -float(level[1]), clock)

    setattr(receiver, RTP_HANDLER, handle)


def refuse_voice(receiver: Any, metrics: Any, counts: dict[str, int]) -> None:
    """Whatever audio ``receiver`` gets is dropped and counted (the peer may not publish)."""
    async def handle(packet: Any, arrival_time_ms: int = 0) -> None:
        counts["refused"] = counts.get("refused", 0) + 1
        if metrics is not None:
            metrics.voice_packets.labels("refused").inc()

    setattr(receiver, RTP_HANDLER, handle)
