"""What the page's status and feedback need from the server (issue 26): the avatar's
expression names in the welcome, display names in presence (given, validated, or the default
"performer" / "viewer N"; never internal ids), and a ``tracked`` answer to each webcam image
that says whether a person was found."""

from __future__ import annotations

import asyncio

import cv2
import numpy as np
import pytest
import websockets

from avatar_core.synth.humanoid.build import EXPRESSION_NAMES
from protocol import Hello, Image, encode
from tests.server_fixtures import (
    is_type,
    recv_until,
    server_fixture,  # noqa: F401 (the `server` fixture)
    stream,
)
from tests.test_server_rooms import create_room, invite, join, room_url
from tests.test_track_drive import astronaut_jpeg
from tests.track_models import needs_models


def test_the_welcome_names_the_avatars_expressions(server):  # noqa: F811
    async def run():
        async with stream(server) as ws:
            return ws.welcome.avatar.expression_names
    names = asyncio.run(run())
    # The demo stands on the synthetic family, whose rig names its ten expressions.
    assert names == list(EXPRESSION_NAMES) and len(names) == 10


def test_presence_shows_given_names_and_numbered_defaults(server):  # noqa: F811
    room = create_room(server)
    watch = invite(server, room["id"], "watch")

    async def run():
        async with join(server, room["id"], server.token, client="telesplat-web") as performer, \
                join(server, room["id"], watch["token"], client="telesplat-web") as first, \
                join(server, room["id"], watch["token"], name="  Zoë   Li ") as second, \
                join(server, room["id"], watch["token"]) as third:
            assert (first.welcome.room.role, second.welcome.room.role) == ("watch", "watch")
            assert third.welcome.room.role == "watch"
            seen: list = []
            last = await recv_until(performer, lambda m: m.type == "presence"
                                    and m.viewers == 3, timeout=30, seen=seen)
            return last, [m.who for m in seen if m.type == "presence" and m.event == "join"]
    presence, joined = asyncio.run(run())
    assert joined[-2:] == ["viewer 1", "Zoë Li"], joined
    # The software name (client) is never shown; the default is a human one.
    assert presence.seats[0].performer == "performer"
    assert presence.who == "viewer 2"  # the third viewer: "viewer 1" and "Zoë Li" are taken


def test_a_bad_display_name_is_refused_with_the_reason(server):  # noqa: F811
    room = create_room(server)

    async def run():
        async with websockets.connect(room_url(server, room["id"])) as ws:
            # As sent raw: Hello() itself refuses it before it could be sent.
            await ws.send(encode({"type": "hello", "token": server.token,
                                  "name": "<script>x</script>"}))
            return await recv_until(ws, is_type("error"))
    err = asyncio.run(run())
    assert err.code == "invalid" and "name" in err.message and "letters, digits" in err.message
    with pytest.raises(ValueError):
        Hello(name="x" * 33)


def _blank_jpeg() -> bytes:
    ok, buf = cv2.imencode(".jpg", np.full((480, 640, 3), 128, np.uint8))
    assert ok
    return buf.tobytes()


@needs_models
def test_each_tracked_image_says_whether_a_person_was_found(server):  # noqa: F811
    async def run():
        async with stream(server) as ws:
            await ws.send(encode(Image(seq=1, data=_blank_jpeg())))
            empty = await recv_until(ws, is_type("tracked"), timeout=60)
            await ws.send(encode(Image(seq=2, data=astronaut_jpeg())))
            person = await recv_until(ws, is_type("tracked", seq=2), timeout=60)
            return empty, person
    empty, person = asyncio.run(run())
    assert (empty.seq, empty.found) == (1, False) and not any(empty.seen.values())
    assert person.found and person.seen["face"], person


def test_the_python_client_joins_under_its_name(server):  # noqa: F811
    from client import StreamClient

    room = create_room(server)
    watch = invite(server, room["id"], "watch")

    async def run():
        client = await StreamClient.connect(server.url, token=server.token, room=room["id"],
                                            name="Eve", timeout=30)
        try:
            async with join(server, room["id"], watch["token"]) as viewer:
                return await recv_until(viewer, is_type("presence"))
        finally:
            await client.close()
    presence = asyncio.run(run())
    assert presence.seats[0].performer == "Eve" and presence.who == "viewer 1"
