"""A WHEP viewer behind a slow link: a UDP relay written here sits between the two aiortc
peers (both candidates rewritten to it) and shapes the server -> viewer direction to
150 kbit/s (below the encoder's start rate) with a bounded queue (tail drop), like a slow
access link. The stream keeps delivering fresh frames (newer drive stamps keep arriving)
instead of stalling, and the encoder's target comes down with the receiver's estimate."""

from __future__ import annotations

import asyncio
import collections
import re

import httpx
import numpy as np
import pytest

from protocol import Drive, Orbit, View, encode
from protocol.stamp import read_stamp
from tests.server_fixtures import run_server
from tests.test_server_rooms import create_room

pytest.importorskip("aiortc")

SIZE = 256
TIMEOUT_S = 30.0
LINK_BITS_PER_S = 150_000  # below the encoder's start rate (aiortc VP8: 500 kbit/s)
QUEUE_S = 0.25  # the link's buffer: packets that would wait longer are dropped
NO_DRIVE = 2**24 - 1
CANDIDATE = re.compile(r"^a=candidate:\S+ 1 udp \d+ (\d+\.\d+\.\d+\.\d+) (\d+) typ host",
                       re.MULTILINE)


class Shaper:
    """Sends datagrams through ``transport`` at ``rate`` bit/s, FIFO, dropping what would wait
    more than QUEUE_S."""

    def __init__(self, rate: float) -> None:
        self.rate = rate
        self.free_at = 0.0
        self.sent = self.dropped = 0
        self.queued: collections.deque[asyncio.TimerHandle] = collections.deque()  # FIFO

    def send(self, transport, data: bytes, addr) -> None:
        loop = asyncio.get_running_loop()
        now = loop.time()
        start = max(now, self.free_at)
        if start - now > QUEUE_S:
            self.dropped += 1
            return
        self.free_at = start + len(data) * 8 / self.rate
        self.sent += 1
        handle = loop.call_at(self.free_at, self._send_now, transport, data, addr)
        self.queued.append(handle)

    def _send_now(self, transport, data: bytes, addr) -> None:
        self.queued.popleft()  # this one: they fire in the order they were queued
        if not transport.is_closing():
            transport.sendto(data, addr)

    def close(self) -> None:
        """Drops what still waits (no send on a closed socket after the test)."""
        for handle in self.queued:
            handle.cancel()
        self.queued.clear()


class Relay:
    """Two UDP sockets: ``client_side`` (the viewer's idea of the server) and ``server_side``
    (the server's idea of the viewer)."""

    def __init__(self, shaper: Shaper) -> None:
        self.shaper = shaper
        self.client_addr = self.server_addr = None
        self.client_side = self.server_side = None

    async def open(self, host: str) -> None:
        loop = asyncio.get_running_loop()
        relay = self

        class ClientSide(asyncio.DatagramProtocol):
            def datagram_received(self, data, addr):
                relay.client_addr = addr  # the viewer -> the server, unshaped
                relay.server_side.sendto(data, relay.server_addr)

        class ServerSide(asyncio.DatagramProtocol):
            def datagram_received(self, data, addr):
                relay.shaper.send(relay.client_side, data, relay.client_addr)

        self.client_side, _ = await loop.create_datagram_endpoint(ClientSide,
                                                                  local_addr=(host, 0))
        self.server_side, _ = await loop.create_datagram_endpoint(ServerSide,
                                                                  local_addr=(host, 0))

    def port(self, side) -> int:
        return side.get_extra_info("sockname")[1]

    def close(self) -> None:
        self.shaper.close()
        for side in (self.client_side, self.server_side):
            if side is not None:
                side.close()


def record_handed_stamps(track) -> list[int | None]:
    """The stamp of each frame the server's ``track`` is handed, in order (the track itself
    is unchanged: this wraps its ``deliver``)."""
    handed: list[int | None] = []
    deliver = track.deliver

    async def noting(rgb, captured_at=None):
        handed.append(read_stamp(rgb))
        await deliver(rgb, captured_at)

    track.deliver = noting
    return handed


def only_candidate(sdp: str, host: str, port: int) -> str:
    """``sdp`` with its candidates replaced by one host candidate at host:port."""
    lines = [line for line in sdp.split("\r\n") if not line.startswith("a=candidate:")]
    out = []
    for line in lines:
        if line == "a=end-of-candidates":
            out.append(f"a=candidate:1 1 udp 2130706431 {host} {port} typ host")
        out.append(line)
    return "\r\n".join(out)


def test_a_150_kbit_link_slows_the_stream_but_frames_keep_coming(tmp_path):
    from aiortc import RTCConfiguration, RTCPeerConnection, RTCSessionDescription

    min_windows, max_windows, per_window = 4, 12, 6

    async def run(server):
        room = await asyncio.to_thread(create_room, server)
        pc = RTCPeerConnection(RTCConfiguration(iceServers=[]))
        pc.addTransceiver("video", direction="recvonly")
        channel = pc.createDataChannel("telesplat")
        opened = asyncio.Event()
        channel.on("open", opened.set)
        track: asyncio.Future = asyncio.get_running_loop().create_future()
        pc.on("track", lambda t: track.done() or track.set_result(t))
        await pc.setLocalDescription(await pc.createOffer())
        offer = pc.localDescription.sdp
        host, client_port = CANDIDATE.search(offer).groups()
        shaper = Shaper(LINK_BITS_PER_S)
        relay = Relay(shaper)
        await relay.open(host)
        relay.client_addr = (host, int(client_port))
        async with httpx.AsyncClient(base_url=server.url, timeout=TIMEOUT_S) as http:
            r = await http.post(
                f"/v1/rooms/{room['id']}/whep", params={"width": SIZE, "height": SIZE,
                                                        "stamp": 1},
                content=only_candidate(offer, host, relay.port(relay.server_side)),
                headers={**server.headers(), "Content-Type": "application/sdp"})
            assert r.status_code == 201, r.text
            answer = r.text
            server_host, server_port = CANDIDATE.search(answer).groups()
            relay.server_addr = (server_host, int(server_port))
            await pc.setRemoteDescription(RTCSessionDescription(
                only_candidate(answer, host, relay.port(relay.client_side)), "answer"))
            await asyncio.wait_for(opened.wait(), TIMEOUT_S)
            video = await asyncio.wait_for(track, TIMEOUT_S)
            peer = server.ctx.webrtc_peers.peers()[0]
            start_rate = peer.encoder.target_bitrate
            handed = record_handed_stamps(peer.track)
            seq = 0

            async def drive() -> None:
                nonlocal seq
                while True:  # cancelled below; a new pose and view every 50 ms
                    seq += 1
                    channel.send(encode(Drive(seq=seq, smplx={"jaw_pose": np.array(
                        [0.4 * (seq % 2), 0.0, 0.0])})))
                    channel.send(encode(View(orbit=Orbit(yaw_deg=float(seq % 20)))))
                    await asyncio.sleep(0.05)

            driver = asyncio.create_task(drive())
            stamps, targets = [], []
            try:
                for count in range(max_windows):  # until the estimate came down
                    if count >= min_windows and targets[-1] < start_rate:
                        break
                    window = []
                    for _ in range(per_window):
                        frame = await asyncio.wait_for(video.recv(), TIMEOUT_S)
                        window.append(read_stamp(frame.to_ndarray(format="rgb24")))
                    stamps.append(window)
                    targets.append(peer.encoder.target_bitrate)
            finally:
                driver.cancel()
            await http.delete(r.headers["location"], headers=server.headers())
        await pc.close()
        relay.close()
        return stamps, targets, shaper, seq, start_rate, handed

    with run_server(tmp_path, default_width=SIZE, default_height=SIZE, default_max_fps=30,
                    webrtc_min_bitrate=50_000) as server:  # the floor below the link's rate
        stamps, targets, shaper, sent, start_rate, handed = asyncio.run(run(server))
    readable = [[s for s in w if s is not None and s != NO_DRIVE] for w in stamps]
    # The server hands its frames to the encoder in order (latest wins never goes back) ...
    handed = [s for s in handed if s != NO_DRIVE]  # frames before the first drive
    assert handed and handed == sorted(handed), handed
    # ... every stamp the viewer reads is one the server sent ...
    flat = [s for w in readable for s in w]
    assert set(flat) <= set(handed), (stamps, handed)
    # ... and fresh ones keep coming: the picture follows the drives through the slow link
    # (a window whose stamps all drowned in the codec's noise tells nothing either way).
    # Not asserted: each read frame newer than the last. One CI run of many read 17 then 16
    # (after an unreadable frame) while this relay dropped packets: a picture decoded
    # across a loss may show what an older reference frame held.
    newest = [max(w) for w in readable if w]
    assert len(newest) >= 3 and newest[-1] > newest[0], (stamps, targets)
    assert newest == sorted(newest), stamps
    assert newest[-1] <= sent
    assert shaper.sent > 0, "the media went through the relay"
    # The receiver's estimate (REMB) brought the encoder down to about the link's rate.
    assert start_rate > LINK_BITS_PER_S and targets[-1] < start_rate, targets
    print(f"link {LINK_BITS_PER_S} bit/s: dropped {shaper.dropped} of "
          f"{shaper.sent + shaper.dropped} packets; encoder targets {targets}; stamps {stamps}")
