"""A performer's microphone for tests: an aiortc audio track of silence with clicks.

:class:`ClickTrack` sends 20 ms frames of 48 kHz mono s16 in real time (paced like aiortc's
``AudioStreamTrack``), a 5 ms burst at full scale every ``click_every`` frames, and records the
time.monotonic() each click frame was handed to the encoder (``clicks``) and its media time,
the instant a sound card would have captured it (``click_media``: the two differ when the
event loop stalls). Hostile RTP for a peer's audio m-line is written with
:func:`send_raw_rtp`.
"""

from __future__ import annotations

import asyncio
import fractions
import time
from collections.abc import Callable

import numpy as np

RATE = 48_000
FRAME_SAMPLES = 960  # 20 ms
CLICK_SAMPLES = 240  # 5 ms
CLICK_LEVEL = 0.3    # a decoded frame louder than this (peak, in [0, 1]) holds a click


def click_track(click_every: int = 10, on_click=None):
    """``on_click()``: called as each click frame is handed to the encoder."""
    from aiortc import MediaStreamTrack

    class ClickTrack(MediaStreamTrack):
        kind = "audio"

        def __init__(self) -> None:
            super().__init__()
            self.sent = 0
            self.clicks: list[float] = []
            self.click_media: list[float] = []  # each click's media time (its due instant)
            self._start: float | None = None

        async def recv(self):
            import av

            if self._start is None:
                self._start = time.monotonic()
            due = self._start + self.sent * FRAME_SAMPLES / RATE
            await asyncio.sleep(max(0.0, due - time.monotonic()))
            samples = np.zeros((1, FRAME_SAMPLES), np.int16)
            if self.sent % click_every == click_every - 1:
                samples[0, :CLICK_SAMPLES] = 30000
                self.clicks.append(time.monotonic())
                self.click_media.append(due)  # when a sound card would have captured it
                if on_click is not None:
                    on_click()
            frame = av.AudioFrame.from_ndarray(samples, format="s16", layout="mono")
            frame.sample_rate = RATE
            frame.pts = self.sent * FRAME_SAMPLES
            frame.time_base = fractions.Fraction(1, RATE)
            self.sent += 1
            return frame

    return ClickTrack()


def peak(frame) -> float:
    """A decoded audio frame's peak level in [0, 1]."""
    samples = frame.to_ndarray()
    scale = 32768.0 if samples.dtype == np.int16 else 1.0
    return float(np.abs(samples).max()) / scale


async def send_raw_rtp(pc, payload_type: int, payloads: list[bytes],
                       ssrc: int = 0x5EED) -> None:
    """Each payload as an RTP packet of its own SSRC, straight onto ``pc``'s (bundled,
    connected) DTLS transport: what a hostile client can do whatever the SDP says."""
    from aiortc.rtp import RtpPacket

    transport = next(t.sender.transport for t in pc.getTransceivers() if t.kind == "video")
    for i, payload in enumerate(payloads):
        packet = RtpPacket(payload_type=payload_type, sequence_number=i,
                           timestamp=i * FRAME_SAMPLES, ssrc=ssrc, payload=payload)
        await transport._send_rtp(packet.serialize(transport._rtp_header_extensions_map))


def note_rtp_arrivals(v) -> dict[str, Callable[[int], float | None]]:
    """Each track's RTP arrival times, looked up by a decoded frame's pts (None: its packets
    were not seen): when a frame or a click reached viewer ``v`` (a WhepViewer), before its
    decoding (a viewer sharing its process with the server decodes at wandering times).
    Keyed by the RTP timestamp itself and looked up through aiortc's own pts origin
    (protocol.rtp_receiver.frame_rtp_timestamp): counted from the first packet seen instead,
    a packet before this hook would shift every key, and on the capture clock frames one tick
    apart would then pair with others seconds away."""
    from protocol.rtp_receiver import frame_rtp_timestamp

    arrivals: dict[str, dict[int, float]] = {"audio": {}, "video": {}}
    lookups = {}
    for receiver in v.pc.getReceivers():
        kind, original = receiver.track.kind, receiver._handle_rtp_packet

        async def note(packet, arrival_time_ms=0, kind=kind, original=original):
            arrivals[kind].setdefault(packet.timestamp, time.monotonic())
            await original(packet, arrival_time_ms=arrival_time_ms)

        def lookup(pts: int, kind=kind, receiver=receiver) -> float | None:
            return arrivals[kind].get(frame_rtp_timestamp(receiver, pts))

        receiver._handle_rtp_packet = note
        lookups[kind] = lookup
    return lookups
