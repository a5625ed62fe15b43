"""The published video's jitter buffer (server/webrtc/jitter.py) against its twin, aiortc's own:
the same frames in the same order, each released at its marked last packet instead of at the
next frame's first; gaps, reordering and loss handled as aiortc does."""

from __future__ import annotations

import asyncio

import pytest

pytest.importorskip("aiortc")

from aiortc.jitterbuffer import JitterBuffer  # noqa: E402
from aiortc.rtp import RtpPacket  # noqa: E402

from server.webrtc.jitter import RECEIVER_JITTER_BUFFER, MarkerJitterBuffer, release_on_marker  # noqa: E402
from server.webrtc.publisher_clock import (  # noqa: E402
    TIMESTAMP_MAPPER,
    PublisherClock,
    frame_rtp_timestamp,
)

TICKS = 3000  # 90 kHz at 30 fps


def packets(frames: int, per_frame: int, first_seq: int = 0) -> list[RtpPacket]:
    out = []
    for f in range(frames):
        for k in range(per_frame):
            p = RtpPacket(sequence_number=(first_seq + f * per_frame + k) % 2**16,
                          timestamp=f * TICKS, marker=int(k == per_frame - 1))
            p._data = bytes([f % 256, k])
            out.append(p)
    return out


def feed(buffer: JitterBuffer, arriving: list[RtpPacket]) -> list[tuple[int, int, bytes]]:
    """(index of the packet that released it, timestamp, data) of each frame released."""
    out = []
    for i, packet in enumerate(arriving):
        _, frame = buffer.add(packet)
        if frame is not None:
            out.append((i, frame.timestamp, frame.data))
    return out


def frames_of(released):
    return [(t, d) for _, t, d in released]


@pytest.mark.parametrize("per_frame", [1, 3])
def test_each_frame_leaves_at_its_last_packet_with_the_same_bytes(per_frame):
    arriving = packets(6, per_frame, first_seq=65530)  # across the sequence number's wrap
    ours = feed(MarkerJitterBuffer(), arriving)
    theirs = feed(JitterBuffer(capacity=512, is_video=True), arriving)
    assert frames_of(theirs) == frames_of(ours)[:-1]  # aiortc still holds the last one
    assert [i for i, _, _ in ours] == [f * per_frame + per_frame - 1 for f in range(6)]
    assert [i for i, _, _ in theirs] == [(f + 1) * per_frame for f in range(5)]


def test_a_frame_reordered_inside_leaves_when_its_gap_fills():
    arriving = packets(3, 3)
    arriving[3:6] = [arriving[3], arriving[5], arriving[4]]  # frame 1: marker before middle
    ours = feed(MarkerJitterBuffer(), arriving)
    assert [i for i, _, _ in ours] == [2, 5, 8]
    assert frames_of(ours) == frames_of(feed(MarkerJitterBuffer(), packets(3, 3)))


def test_a_lost_packet_holds_its_frame_as_aiortc_does():
    arriving = packets(4, 3)
    del arriving[4]  # frame 1's middle packet
    ours = feed(MarkerJitterBuffer(), arriving)
    theirs = feed(JitterBuffer(capacity=512, is_video=True), arriving)
    assert frames_of(ours) == [(0, bytes([0, 0]) + bytes([0, 1]) + bytes([0, 2]))]
    assert frames_of(theirs) == frames_of(ours)  # neither passes a frame with a hole on


def test_without_markers_it_is_aiortcs_buffer():
    arriving = packets(5, 2)
    for p in arriving:
        p.marker = 0
    ours = feed(MarkerJitterBuffer(), arriving)
    assert ours == feed(JitterBuffer(capacity=512, is_video=True), arriving)


def test_aiortcs_receiver_has_what_the_server_replaces():
    from aiortc import RTCPeerConnection

    async def run():
        pc = RTCPeerConnection()
        receiver = pc.addTransceiver("video", direction="recvonly").receiver
        try:
            assert release_on_marker(receiver)
            assert isinstance(getattr(receiver, RECEIVER_JITTER_BUFFER), MarkerJitterBuffer)
            assert hasattr(receiver, TIMESTAMP_MAPPER)
            assert PublisherClock().track(90_000).watch(receiver)  # its RTCP handler is there
            assert frame_rtp_timestamp(receiver, 0) is None  # no frame decoded yet
        finally:
            await pc.close()

    asyncio.run(run())
