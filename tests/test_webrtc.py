"""WebRTC (issue 16) with real aiortc peers on loopback against a real server: WHEP offer and
answer, decoded frames, a drive over the data channel that opens the mouth, DELETE, the
bit-rate cap. Refusals and limits are in test_webrtc_signalling.py, WHIP in test_webrtc_whip.py.
"""

from __future__ import annotations

import asyncio
import json

import cv2
import numpy as np
import pytest

from client.webrtc import WhepViewer
from protocol import Drive, Orbit, Ping, View
from protocol.stamp import read_stamp
from tests.server_fixtures import run_server, wait_until
from tests.test_server_rooms import create_room, invite, mouth_box

SIZE = 128
NO_DRIVE = 2**24 - 1  # the stamp of a frame before any drive (seq -1)
TIMEOUT_S = 30.0
pytest.importorskip("aiortc")


@pytest.fixture(scope="module")
def srv(tmp_path_factory):
    with run_server(tmp_path_factory.mktemp("webrtc"), default_width=SIZE, default_height=SIZE,
                    default_max_fps=30) as running:
        yield running


def peers(srv) -> int:
    return len(srv.ctx.webrtc_peers)


def viewer(srv, room_id: str, token: str, **kwargs) -> WhepViewer:
    return WhepViewer(srv.url, room_id, token, timeout_s=TIMEOUT_S, **kwargs)


def test_whep_answers_with_every_candidate_and_frames_decode(srv):
    room = create_room(srv)
    watch = invite(srv, room["id"], "watch")

    async def run():
        async with viewer(srv, room["id"], watch["token"], width=SIZE, height=SIZE) as v:
            assert v.location.startswith(f"/v1/rooms/{room['id']}/whep/")
            rgb, _ = await v.next_frame()
            welcome = await v.welcome()
            v.send(Ping(t=1.5))
            pong = await v.message(lambda m: m.type == "pong")
            return v.codec, rgb, welcome, pong, peers(srv)

    codec, rgb, welcome, pong, open_peers = asyncio.run(run())
    assert codec.lower() == "video/vp8"  # aiortc offers VP8 first
    assert rgb.shape == (SIZE, SIZE, 3) and rgb.dtype == np.uint8
    # The avatar on the white background: a dark enough, varied picture.
    assert rgb.std() > 10 and (rgb.mean(axis=2) < 200).mean() > 0.05
    assert welcome.room.id == room["id"] and welcome.room.role == "watch"
    assert pong.t == 1.5 and open_peers == 1
    wait_until(lambda: peers(srv) == 0, TIMEOUT_S, what="the peer to be freed")
    assert not srv.ctx.sessions


@pytest.mark.parametrize("codec", ["h264", "vp8"])
def test_the_offers_codec_preference_wins(srv, codec):
    room = create_room(srv)
    watch = invite(srv, room["id"], "watch")

    async def run():
        async with viewer(srv, room["id"], watch["token"], codec=codec) as v:
            rgb, _ = await v.next_frame()
            return v.codec, rgb

    negotiated, rgb = asyncio.run(run())
    assert negotiated.lower() == f"video/{codec}"
    assert rgb.shape == (SIZE, SIZE, 3) and rgb.std() > 10


async def frame_stamped(v: WhepViewer, seq: int, count: int = 3,
                        limit: int = 200) -> np.ndarray:
    """The ``count``-th decoded frame stamped ``seq`` (the encoder settles on a still
    picture), within ``limit`` frames."""
    seen = 0
    for _ in range(limit):
        rgb, _ = await v.next_frame()
        if read_stamp(rgb) == seq:
            seen += 1
            if seen == count:
                return rgb.astype(np.float64)
    raise AssertionError(f"no {count} frames stamped {seq} in {limit}")


def test_a_drive_over_the_data_channel_opens_the_decoded_mouth(srv):
    room = create_room(srv)
    head = srv.ctx.session_models("demo")[0].body_model.joint_template[15]
    face = View(orbit=Orbit(target=tuple(float(v) for v in head), distance=0.8))
    angle = 0.5

    async def run():
        # The owner's token performs seat 0 (the default) over the data channel.
        async with viewer(srv, room["id"], srv.token, stamp=True) as v:
            await v.wait_open()
            welcome = await v.welcome()
            v.send(face)
            v.send(Drive(seq=1, smplx={"jaw_pose": np.array([0.0, 0.0, 0.0])}))
            closed = await frame_stamped(v, 1)
            v.send(Drive(seq=2, smplx={"jaw_pose": np.array([angle, 0.0, 0.0])}))
            opened = await frame_stamped(v, 2)
            return welcome, closed, opened

    welcome, closed, opened = asyncio.run(run())
    assert welcome.room.role == "perform" and welcome.room.seat == 0
    x0, y0, x1, y1 = mouth_box(srv, face, SIZE, SIZE, angle)
    diff = np.abs(closed - opened).sum(axis=2)  # [H, W]
    diff[:8] = 0  # the stamp strip
    inside = diff[y0:y1, x0:x1]
    outside = (diff.sum() - inside.sum()) / (diff.size - inside.size)
    assert inside.mean() > 5, (inside.mean(), (x0, y0, x1, y1))  # the mouth opened
    assert inside.mean() > 4 * outside, (inside.mean(), outside)  # codec noise elsewhere


def test_a_viewers_drive_and_garbage_get_errors_and_the_peer_goes_on(srv):
    room = create_room(srv)
    watch = invite(srv, room["id"], "watch")

    async def run():
        async with viewer(srv, room["id"], watch["token"]) as v:
            await v.wait_open()
            await v.welcome()
            v.send(Drive(seq=5, smplx={"jaw_pose": np.array([0.3, 0.0, 0.0])}))
            error = await v.message(lambda m: m.type == "error")
            v.channel.send(b"\xc1 not msgpack")  # garbage, then text: errors, nothing else
            garbage = await v.message(lambda m: m.type == "error")
            v.channel.send("a text message")
            text = await v.message(lambda m: m.type == "error")
            v.send(Ping(t=2.0))
            pong = await v.message(lambda m: m.type == "pong")
            rgb, _ = await v.next_frame()
            return error, garbage, text, pong, rgb

    error, garbage, text, pong, rgb = asyncio.run(run())
    assert error.code == "forbidden" and error.answers.seq == 5
    assert garbage.code == "bad_message" and text.code == "bad_message", (garbage, text)
    assert pong.t == 2.0 and rgb.shape == (SIZE, SIZE, 3)


def test_under_a_bit_rate_cap_fresh_frames_keep_arriving(tmp_path):
    """webrtc_max_bitrate = 500 kbit/s while the avatar moves all the time: the encoder's
    target stays within the cap whatever the receiver estimates, and the picture keeps
    following the drives (newer stamps keep arriving) instead of stalling."""
    cap, floor = 500_000, 100_000
    windows, per_window = 3, 8

    async def run(server):
        room = await asyncio.to_thread(create_room, server)
        async with WhepViewer(server.url, room["id"], server.token, stamp=True, fps=30,
                              timeout_s=TIMEOUT_S) as v:
            await v.wait_open()
            peer = next(iter(server.ctx.webrtc_peers.peers()))
            targets, stamps = [], []
            seq = 0

            async def drive() -> None:
                nonlocal seq
                while True:  # cancelled below; a new pose and view every 50 ms
                    seq += 1
                    v.send(Drive(seq=seq, smplx={"jaw_pose": np.array(
                        [0.4 * (seq % 2), 0.0, 0.0])}))
                    v.send(View(orbit=Orbit(yaw_deg=float(seq * 7 % 360))))
                    await asyncio.sleep(0.05)

            driver = asyncio.create_task(drive())
            try:
                for _ in range(windows):
                    window = []
                    for _ in range(per_window):
                        rgb, _ = await v.next_frame()
                        window.append(read_stamp(rgb))
                    stamps.append(window)
                    targets.append(peer.encoder.target_bitrate)
            finally:
                driver.cancel()
            inbound = [s for s in (await v.stats()).values() if s.type == "inbound-rtp"]
            return peer.encoder, targets, stamps, inbound[0].packetsReceived, seq

    with run_server(tmp_path, default_width=SIZE, default_height=SIZE, default_max_fps=30,
                    webrtc_max_bitrate=cap, webrtc_min_bitrate=floor) as server:
        encoder, targets, stamps, received, sent = asyncio.run(run(server))
    assert type(encoder).__name__ == "ClampedVp8Encoder"
    assert encoder.bitrate_range == (floor, cap)
    assert all(floor <= t <= cap for t in targets), targets
    # Every window has frames showing drives newer than the window before (no stall).
    newest = [max((s for s in window if s is not None and s != NO_DRIVE), default=0)
              for window in stamps]
    assert newest == sorted(newest) and newest[-1] > newest[0], stamps
    assert received > 0 and newest[-1] <= sent


def test_cli_watch_webrtc_records_decoded_frames(srv, tmp_path):
    from client.cli import main as cli_main

    room = create_room(srv)
    watch = invite(srv, room["id"], "watch")
    out = tmp_path / "rtc"
    argv = ["watch", "--webrtc", "--codec", "h264", "--stamp", "--room", room["id"],
            "--out", str(out), "--frames", "3", "--seconds", "120", "--size", "64",
            "--view", "20,0,2.5", "--server", srv.url, "--token", watch["token"]]
    assert cli_main(argv) == 0
    records = [json.loads(line) for line in (out / "frames.jsonl").read_text().splitlines()]
    assert [r["index"] for r in records] == [0, 1, 2]
    assert all(r["codec"].lower() == "video/h264" and (r["width"], r["height"]) == (64, 64)
               for r in records)
    assert all(r["seq"] == NO_DRIVE for r in records)  # stamped; nobody drove the seat
    image = cv2.imread(str(out / records[-1]["file"]))
    assert image.shape == (64, 64, 3) and image.std() > 10
    wait_until(lambda: peers(srv) == 0, TIMEOUT_S, what="the CLI's peer to be freed")
