"""The video jitter buffer both ends use (protocol/rtp_receiver.py) against its twin, aiortc's
own: the same frames in the same order, each released at its marked last packet instead of at
the next frame's first; gaps, reordering and loss handled as aiortc does. The Python WHEP
viewer (client/webrtc.py) uses it too: on a real server its frames are decoded a frame
interval sooner than with aiortc's buffer."""

from __future__ import annotations

import asyncio

import pytest

pytest.importorskip("aiortc")

from aiortc.jitterbuffer import JitterBuffer  # noqa: E402
from aiortc.rtp import RtpPacket  # noqa: E402

from protocol.rtp_receiver import (  # noqa: E402
    RECEIVER_JITTER_BUFFER,
    TIMESTAMP_MAPPER,
    MarkerJitterBuffer,
    frame_rtp_timestamp,
    release_on_marker,
)
from server.webrtc.publisher_clock import PublisherClock  # noqa: E402

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


def test_a_whep_viewer_decodes_each_frame_at_its_last_packet(tmp_path):
    """Side by side on one server at 4 frames a second: the client's viewer decodes each frame
    well within the frame interval after the server's track was handed it; with aiortc's own
    buffer (``release_at_marker=False``) each waits about one interval more, for the next
    frame's first packet."""
    import time

    import numpy as np

    from client.webrtc import WhepViewer
    from protocol import Drive
    from protocol.stamp import read_stamp
    from tests.server_fixtures import run_server
    from tests.test_server_rooms import create_room

    fps, frames, size = 4.0, 6, 64
    interval = 1.0 / fps

    async def latencies(server, room: str, marker: bool) -> list[float]:
        async with WhepViewer(server.url, room, server.token, width=size, height=size,
                              stamp=True, release_at_marker=marker, timeout_s=30) as v:
            await v.wait_open()
            await v.welcome()
            peer = server.ctx.webrtc_peers.peers()[0]
            handed: dict[int | None, float] = {}
            deliver = peer.track.deliver

            async def noting(rgb, captured_at=None):
                handed.setdefault(read_stamp(rgb), time.monotonic())
                await deliver(rgb, captured_at)

            peer.track.deliver = noting

            async def drive() -> None:
                for seq in range(1, 10_000):  # cancelled below; a new pose every 50 ms
                    v.send(Drive(seq=seq, flame={"jaw_pose": np.array([0.4 * (seq % 2), 0, 0])}))
                    await asyncio.sleep(0.05)

            driver = asyncio.create_task(drive())
            out: list[float] = []
            try:
                for _ in range(frames + 2):
                    rgb, decoded = await v.next_frame()
                    at = handed.get(read_stamp(rgb))
                    if at is not None:
                        out.append(decoded - at)
            finally:
                driver.cancel()
            return out[2:]  # the first frames: the encoder and the decoder starting

    async def run(server):
        room = (await asyncio.to_thread(create_room, server))["id"]
        return await latencies(server, room, True), await latencies(server, room, False)

    with run_server(tmp_path, default_width=size, default_height=size,
                    default_max_fps=fps) as server:
        marked, stock = asyncio.run(run(server))
    print(f"handed -> decoded ms at {fps:g} fps: marker {np.round(np.array(marked) * 1e3)}; "
          f"aiortc's {np.round(np.array(stock) * 1e3)}")
    assert len(marked) >= frames // 2 and len(stock) >= frames // 2, (marked, stock)
    assert np.median(marked) < 0.5 * interval, marked
    assert np.median(stock) - np.median(marked) > 0.5 * interval, (marked, stock)
