"""WHIP ingest with real aiortc peers: a published webcam track (a photograph of a face) is
tracked server-side and drives the performer's seat; the same peer watches the room and talks
over the data channel."""

from __future__ import annotations

import asyncio
import fractions
import time

import httpx
import numpy as np
import pytest

from tests.server_fixtures import run_server, wait_until
from tests.test_server_rooms import create_room

pytest.importorskip("aiortc")
pytest.importorskip("onnxruntime")

SIZE = 64
TIMEOUT_S = 60.0  # the first image loads the landmark models
WEBCAM_FPS = 10


@pytest.fixture(scope="module")
def srv(tmp_path_factory):
    with run_server(tmp_path_factory.mktemp("whip"), default_width=SIZE,
                    default_height=SIZE) as running:
        yield running


def face_frames() -> np.ndarray:
    """[2, H, W, 3] uint8: scikit-image's astronaut, and the same photo shifted (a moving
    face), so consecutive frames differ."""
    from skimage.data import astronaut

    photo = astronaut()[:384, 64:448]  # [384, 384, 3]: head and shoulders
    return np.stack([photo, np.roll(photo, 8, axis=1)])


class Webcam:
    """An aiortc video track of the face photo at WEBCAM_FPS."""

    def __new__(cls):
        from aiortc import VideoStreamTrack

        class _Track(VideoStreamTrack):
            def __init__(self) -> None:
                super().__init__()
                self.images = face_frames()
                self.sent = 0

            async def recv(self):
                import av

                await asyncio.sleep(1 / WEBCAM_FPS)
                frame = av.VideoFrame.from_ndarray(self.images[self.sent % 2], format="rgb24")
                frame.pts = self.sent * (90000 // WEBCAM_FPS)
                frame.time_base = fractions.Fraction(1, 90000)
                self.sent += 1
                return frame

        return _Track()


def test_a_published_webcam_drives_the_performers_seat(srv):
    room = create_room(srv)
    live_seat = {}

    async def run():
        from aiortc import RTCConfiguration, RTCPeerConnection, RTCSessionDescription

        from protocol import decode_server

        pc = RTCPeerConnection(RTCConfiguration(iceServers=[]))
        webcam = Webcam()
        pc.addTransceiver(webcam, direction="sendonly")
        pc.addTransceiver("video", direction="recvonly")  # watch the room too
        channel = pc.createDataChannel("telesplat")
        messages: asyncio.Queue = asyncio.Queue()
        channel.on("message", lambda data: messages.put_nowait(decode_server(data)))
        watched: asyncio.Future = asyncio.get_running_loop().create_future()
        pc.on("track", lambda track: watched.done() or watched.set_result(track))
        await pc.setLocalDescription(await pc.createOffer())
        async with httpx.AsyncClient(base_url=srv.url, timeout=TIMEOUT_S) as http:
            r = await http.post(f"/v1/rooms/{room['id']}/whip", content=pc.localDescription.sdp,
                                headers={**srv.headers(), "Content-Type": "application/sdp"})
            assert r.status_code == 201, r.text
            location = r.headers["location"]
            assert location.startswith(f"/v1/rooms/{room['id']}/whip/")
            await pc.setRemoteDescription(RTCSessionDescription(r.text, "answer"))
            welcome = await asyncio.wait_for(messages.get(), TIMEOUT_S)
            frame = await asyncio.wait_for(
                (await asyncio.wait_for(watched, TIMEOUT_S)).recv(), TIMEOUT_S)
            seat = srv.ctx.rooms.get(room["id"]).live.seats[0]
            live_seat["seat"] = seat
            start = seat.drive.version
            # Tracked images drive the seat: its version moves on, its seq is the frame count.
            deadline = time.monotonic() + TIMEOUT_S
            while seat.drive.version < start + 3 and time.monotonic() < deadline:
                await asyncio.sleep(0.05)
            versions = seat.drive.version - start
            families = {k: sorted(v) for k, v in seat.drive.families.items() if v}
            sent = webcam.sent
            r = await http.delete(location, headers=srv.headers())
            assert r.status_code == 204
        await pc.close()
        return welcome, frame, versions, families, seat.drive.seq, sent

    welcome, frame, versions, families, seq, sent = asyncio.run(run())
    assert welcome.type == "welcome" and welcome.room.role == "perform"
    assert frame.width == SIZE and frame.height == SIZE
    assert versions >= 3, versions
    assert "smplx" in families and "global_orient" in families["smplx"], families
    # Latest wins: the seat saw at most as many tracked images as frames were published.
    assert 1 <= seq <= sent
    wait_until(lambda: len(srv.ctx.webrtc_peers) == 0, TIMEOUT_S, what="the peer freed")
    assert live_seat["seat"].performer is None
