"""The Python client's room pieces: URLs, the hello, CLI arguments and REST request shapes
(no server), then a real server on 127.0.0.1: `watch --room` records the frames a viewer gets
while a performer drives the seat."""

from __future__ import annotations

import json

import pytest

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
    with pytest.raises(ValueError, match="role must be"):
        room_hello("c", room="r", role="drive")


def test_room_hello_carries_role_and_seat():
    hello = room_hello("c", room="r", role="perform", seat=2)
    assert (hello.role, hello.seat, hello.client) == ("perform", 2, "c")
    assert room_hello("c", room="r").role is None  # the token's scope decides


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
