"""The Python client's room pieces: URLs, the hello, CLI arguments and REST request shapes
(no server), then a real server on 127.0.0.1: `watch --room` records the frames a viewer gets
while a performer drives the seat."""

from __future__ import annotations

import asyncio
import importlib.util
import json
import time

import numpy as np
import pytest

from client import RestClient, StreamClient, decode_image
from client.cli import build_parser
from client.cli import main as cli_main
from client.stream import room_hello, stream_url
from client.watch import frame_record, parse_view
from protocol import Frame, Hello
from tests.server_fixtures import server_fixture  # noqa: F401 (the `server` fixture)


def test_stream_url_for_a_room_has_the_room_and_no_avatar_or_token():
    assert stream_url("http://h:1", room="r 1") == "ws://h:1/v1/stream?room=r+1"
    assert stream_url("https://h/base/", room="abc") == "wss://h/base/v1/stream?room=abc"
    with pytest.raises(ValueError, match="exactly one"):
        stream_url("http://h", "demo", room="abc")
    with pytest.raises(ValueError, match="exactly one"):
        stream_url("http://h")


def test_plain_hello_is_unchanged_and_role_needs_a_room():
    assert room_hello("c").model_dump(exclude_none=True) == Hello(client="c").model_dump(
        exclude_none=True)
    with pytest.raises(ValueError, match="rooms only"):
        room_hello("c", role="watch")
    with pytest.raises(ValueError, match="rooms only"):
        room_hello("c", name="Ann")
    with pytest.raises(ValueError, match="role must be"):
        room_hello("c", room="r", role="drive")


def test_room_hello_carries_role_and_seat():
    hello = room_hello("c", room="r", role="perform", seat=2)
    assert (hello.role, hello.seat, hello.client) == ("perform", 2, "c")
    assert room_hello("c", room="r").role is None  # the token's scope decides
    assert room_hello("c", room="r", name=" Ann  Lee").name == "Ann Lee"  # shown in presence
    with pytest.raises(ValueError, match="letters, digits"):
        room_hello("c", room="r", name="<b>")


def test_cli_drive_and_watch_room_arguments(capsys):
    args = build_parser().parse_args(["drive", "--room", "r1", "--seat", "1", "--video", "a.mp4",
                                      "--token", "t"])
    assert (args.room, args.seat, args.avatar, str(args.video)) == ("r1", 1, None, "a.mp4")
    args = build_parser().parse_args(["watch", "--room", "r1", "--out", "o", "--seconds", "2.5",
                                      "--view", "30,-10,2.2", "--frames", "9"])
    assert (args.room, args.seconds, args.frames) == ("r1", 2.5, 9)
    assert parse_view(args.view) == {"yaw_deg": 30.0, "pitch_deg": -10.0, "distance": 2.2}
    for bad in ("30,0", "a,b,c"):
        with pytest.raises(ValueError, match="--view"):
            parse_view(bad)
    # drive needs exactly one of --avatar / --room, and --seat only with --room
    assert cli_main(["drive", "--video", "a.mp4"]) == 2
    assert cli_main(["drive", "--avatar", "demo", "--room", "r", "--video", "a.mp4"]) == 2
    assert cli_main(["drive", "--avatar", "demo", "--seat", "0", "--video", "a.mp4"]) == 2
    assert "--room" in capsys.readouterr().err


def test_frame_record_is_one_json_line():
    frame = Frame(seq=7, frame=3, codec="jpeg", width=4, height=2, data=b"xyz")
    record = frame_record(frame, 0, "00000.jpg", 0.123456)
    assert json.loads(json.dumps(record)) == record
    assert (record["seq"], record["frame"], record["bytes"], record["received_s"]) == (
        7, 3, 3, 0.1235)
    assert set(record["timings"]) >= {"pose", "render"}


def test_rest_client_room_requests():
    import httpx

    from client.rest import RestClient

    seen = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        path, method = request.url.path, request.method
        if method == "POST" and path == "/v1/rooms":
            return httpx.Response(201, json={"id": "r1", "seats": []})
        if method == "GET" and path == "/v1/rooms":
            return httpx.Response(200, json={"rooms": [{"id": "r1"}]})
        if method == "POST" and path == "/v1/rooms/r1/invitations":
            return httpx.Response(201, json={"id": "i1", "token": "tsr_x",
                                             "link": "/?room=r1#token=tsr_x"})
        if method == "GET" and path == "/v1/rooms/r1/invitations":
            return httpx.Response(200, json={"invitations": [{"id": "i1"}]})
        if method == "DELETE":
            return httpx.Response(204)
        return httpx.Response(404, json={"detail": "no such room"})

    with RestClient("http://test:9", "tok", transport=httpx.MockTransport(handler)) as api:
        api.create_room([{"avatar": "demo"}], name="stage")
        assert json.loads(seen[-1].content) == {"name": "stage", "seats": [{"avatar": "demo"}]}
        api.create_room()
        assert json.loads(seen[-1].content) == {}
        assert api.rooms() == [{"id": "r1"}]
        invitation = api.invite("r1", "perform", seat=1, ttl_s=60)
        assert json.loads(seen[-1].content) == {"scope": "perform", "seat": 1, "ttl_s": 60}
        assert api.link(invitation["link"]) == "http://test:9/?room=r1#token=tsr_x"
        api.invite("r1", "watch")
        assert json.loads(seen[-1].content) == {"scope": "watch"}
        assert api.invitations("r1") == [{"id": "i1"}]
        api.revoke_invitation("r1", "i1")
        assert (seen[-1].method, seen[-1].url.path) == ("DELETE", "/v1/rooms/r1/invitations/i1")
        api.delete_room("r1")
        assert seen[-1].url.path == "/v1/rooms/r1"
        with pytest.raises(Exception, match="404.*no such room"):
            api.room("nope")


# -- against a real server ----------------------------------------------------------------

needs_rooms = pytest.mark.skipif(importlib.util.find_spec("server.routers.rooms") is None,
                                 reason="the server has no rooms yet")


@needs_rooms
def test_watch_room_records_what_the_performer_drives(server, tmp_path):  # noqa: F811
    with RestClient(server.url, server.token) as api:
        room = api.create_room(name="watch test")
        watch = api.invite(room["id"], "watch")
    assert watch["token"].startswith("tsr_") and watch["link"].startswith("/?room=")
    out = tmp_path / "watched"
    argv = ["watch", "--room", room["id"], "--out", str(out), "--frames", "4", "--seconds",
            "120", "--size", "96", "--server", server.url, "--token", watch["token"]]

    async def run():
        async with await StreamClient.connect(server.url, token=server.token, room=room["id"],
                                              role="perform", seat=0) as performer:
            assert (performer.room.role, performer.room.seat) == ("perform", 0)
            recorder = asyncio.create_task(asyncio.to_thread(cli_main, argv))
            await performer.wait_presence(lambda p: p.viewers >= 1, timeout=60)
            for i in range(400):  # bounded; ends once the recorder has its frames
                if recorder.done():
                    break
                seq = await performer.drive(jaw_pose=[min(0.5, 0.1 * (i + 1)), 0.0, 0.0])
                await performer.wait_frame(seq, timeout=30)
            return await recorder

    assert asyncio.run(run()) == 0
    records = [json.loads(line) for line in (out / "frames.jsonl").read_text().splitlines()]
    assert [r["index"] for r in records] == [0, 1, 2, 3]
    images = [decode_image((out / r["file"]).read_bytes()) for r in records]
    assert all(image.shape == (96, 96, 3) for image in images)
    assert all(r["codec"] == "jpeg" and r["bytes"] > 0 for r in records)
    saved = [(r["seq"], (out / r["file"]).read_bytes()) for r in records]
    assert all(a != b for a, b in zip(saved, saved[1:], strict=False)), "saved twice"
    # The viewer's first frame shows the seat at rest, its last one the driven jaw.
    assert np.abs(images[0].astype(int) - images[-1]).mean() > 0.1


@needs_rooms
def test_a_viewers_drive_is_forbidden_and_its_session_goes_on(server):  # noqa: F811
    with RestClient(server.url, server.token) as api:
        room = api.create_room()
        token = api.invite(room["id"], "watch")["token"]

    async def run():
        async with await StreamClient.connect(server.url, token=token, room=room["id"]) as viewer:
            assert viewer.room is not None and viewer.room.role == "watch"
            presence = await viewer.wait_presence(lambda p: p.viewers >= 1, timeout=30)
            assert presence.room == room["id"] and presence.seats[0].performer is None
            seq = await viewer.drive(jaw_pose=[0.3, 0.0, 0.0])
            await _poll(lambda: viewer.errors_for(seq), 30, "the refusal of the drive")
            assert viewer.errors_for(seq)[0].code == "forbidden"
            assert viewer.closed is None  # still watching
            assert 0 < await viewer.ping() < 30

    asyncio.run(run())


async def _poll(predicate, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():  # bounded by the deadline
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out after {timeout} s waiting for {what}")
        await asyncio.sleep(0.01)


@needs_rooms
def test_drive_room_performs_a_seat_from_a_video(server, tmp_path):  # noqa: F811
    from tests.test_track_drive import _astronaut_video
    from tests.track_models import models_available

    if not models_available():
        pytest.skip("MediaPipe ONNX models not fetched (telesplat track fetch-models)")
    video = tmp_path / "clip.avi"
    _astronaut_video(video, frames=2)
    with RestClient(server.url, server.token) as api:
        room = api.create_room()
        perform = api.invite(room["id"], "perform", seat=0)
        watch = api.invite(room["id"], "watch")
    out = tmp_path / "performed"
    argv = ["drive", "--server", server.url, "--token", perform["token"], "--room", room["id"],
            "--seat", "0", "--video", str(video), "--out", str(out), "--quiet"]

    async def run():
        async with await StreamClient.connect(server.url, token=watch["token"],
                                              room=room["id"]) as viewer:
            assert await asyncio.to_thread(cli_main, argv) == 0
            # The performer came and went: the seat holds its last pose.
            presence = await viewer.wait_presence(lambda p: p.seats[0].holding, timeout=30)
            assert presence.seats[0].performer is None

    asyncio.run(run())
    assert len(list(out.iterdir())) == 2
