"""Issue 25, findings 1 and 3, against a real uvicorn: every WebSocket entry keeps its
pre-auth limits until the credentials are VALID (a garbage Authorization header counts as
none), and one invitation cannot take every session slot (a per-invitation cap, capacity
kept for room owners and admins). Also: Ray's private cluster is refused without token auth.
"""

import asyncio
import contextlib
import time

import httpx
import pytest
import websockets

from protocol import Hello, encode
from tests.server_fixtures import (
    WS_TIMEOUT_S,
    is_type,
    recv_msg,
    recv_until,
    run_server,
    stream,
    wait_until,
)

HELLO_MAX = 4096
BIG = 1 << 20          # a 1 MiB first message: 256x the pre-auth limit
BURST = 48             # concurrent garbage-credential connections (the review's burst)
GARBAGE = {"Authorization": "Bearer tsk_garbage-not-a-token"}


@pytest.fixture(scope="module")
def srv(tmp_path_factory):
    with run_server(tmp_path_factory.mktemp("gate"), max_sessions=8, reserved_sessions=2,
                    max_sessions_per_invitation=3, hello_max_bytes=HELLO_MAX,
                    default_width=64, default_height=64) as running:
        yield running


def rest(srv, method: str, path: str, token: str | None = None, **kwargs) -> httpx.Response:
    with httpx.Client(base_url=srv.url, headers=srv.headers(token), timeout=30) as c:
        return c.request(method, path, **kwargs)


def ws_base(srv) -> str:
    return srv.url.replace("http://", "ws://")


async def first_answer(ws) -> tuple[str | None, int | None]:
    """(error code, close code) the server ends the connection with."""
    code = None
    with contextlib.suppress(websockets.ConnectionClosed):
        err = await asyncio.wait_for(recv_msg(ws), WS_TIMEOUT_S)
        code = getattr(err, "code", None)
    with contextlib.suppress(websockets.ConnectionClosed, TimeoutError):
        await asyncio.wait_for(ws.recv(), WS_TIMEOUT_S)
    return code, ws.close_code


async def garbage_join(url: str) -> tuple[str | None, int | None]:
    async with websockets.connect(url, additional_headers=GARBAGE, max_size=None,
                                  open_timeout=WS_TIMEOUT_S, close_timeout=5) as ws:
        with contextlib.suppress(websockets.ConnectionClosed):
            await ws.send(b"\x00" * BIG)
        return await first_answer(ws)


@pytest.mark.parametrize("path", ["/v1/stream?room={room}", "/v1/stream?avatar=demo"])
def test_a_garbage_header_is_refused_before_any_message_is_read(srv, path):
    """Before: the header's presence lifted the parser's limit and the waiting slots, and the
    room join read a 1 MiB hello whole before checking the token ("too_large", 4413)."""
    room = rest(srv, "POST", "/v1/rooms", json={}).json()["id"]
    url = ws_base(srv) + path.format(room=room)
    code, close = asyncio.run(garbage_join(url))
    assert close in (4401, 1009), (code, close)  # refused at once, or the frame unread
    assert code in ("unauthorized", None) and code != "too_large"


def test_a_garbage_header_burst_holds_nothing_and_the_server_serves(srv):
    room = rest(srv, "POST", "/v1/rooms", json={}).json()["id"]
    url = f"{ws_base(srv)}/v1/stream?room={room}"

    async def run():
        started = time.monotonic()
        answers = await asyncio.gather(*(garbage_join(url) for _ in range(BURST)))
        burst_s = time.monotonic() - started
        # every one refused from its credentials, none of them read
        assert all(close in (4401, 1009) for _, close in answers), answers
        assert srv.ctx.admission.waiting.count() == 0
        async with stream(srv) as ws:  # a well-behaved session still streams
            frame = await recv_until(ws, is_type("frame"))
        return burst_s, frame

    burst_s, frame = asyncio.run(run())
    assert frame.width == 64
    assert burst_s < 60  # bounded: a refusal per connection, nothing read


def test_a_valid_header_still_needs_no_waiting_slot(srv):
    """Valid credentials in the handshake: no pre-auth limit, no waiting slot."""
    room = rest(srv, "POST", "/v1/rooms", json={}).json()["id"]
    url = f"{ws_base(srv)}/v1/stream?room={room}"

    async def run():
        async with websockets.connect(url, additional_headers=srv.headers(), max_size=None,
                                      open_timeout=WS_TIMEOUT_S, close_timeout=5) as ws:
            # a hello padded past the pre-auth limit: read, since the header was valid
            await ws.send(encode(Hello(client="x" * 200)))
            return await recv_until(ws, is_type("welcome"))

    assert asyncio.run(run()).room.id == room


# -- one invitation cannot take every slot ----------------------------------------------------


def test_an_invitation_has_a_cap_and_owners_keep_their_reserve(srv):
    """Before: invitation holders had no per-holder cap over the WebSocket, and 7 joins with
    one invitation left the owner and the admin with busy (1013)."""
    owner = srv.issue("olga", ("stream",))
    room = rest(srv, "POST", "/v1/rooms", owner, json={}).json()["id"]
    watch = [rest(srv, "POST", f"/v1/rooms/{room}/invitations", owner,
                  json={"scope": "watch"}).json()["token"] for _ in range(3)]
    url = f"{ws_base(srv)}/v1/stream?room={room}"

    async def join(token: str, stack) -> tuple[str | None, int | None]:
        ws = await stack.enter_async_context(websockets.connect(
            url, max_size=None, open_timeout=WS_TIMEOUT_S, close_timeout=5))
        await ws.send(encode(Hello(token=token, role="watch")))
        msg = await recv_until(ws, lambda m: m.type in ("welcome", "error"))
        if msg.type == "welcome":
            return "welcome", None
        return msg.code, (await first_answer(ws))[1]

    async def run():
        async with contextlib.AsyncExitStack() as stack:
            first = [await join(watch[0], stack) for _ in range(3)]
            over_cap = await join(watch[0], stack)  # a 4th on one invitation
            second = [await join(watch[1], stack) for _ in range(3)]  # 6 of 8: the reserve
            reserve = await join(watch[2], stack)
            owner_in = await join(owner, stack)
            admin_in = await join(srv.token, stack)
            full = await join(srv.issue("pia", ("stream",)), stack)
            return first, over_cap, second, reserve, owner_in, admin_in, full

    first, over_cap, second, reserve, owner_in, admin_in, full = asyncio.run(run())
    assert first == [("welcome", None)] * 3 and second == [("welcome", None)] * 3
    assert over_cap == ("busy", 4429)
    assert reserve == ("busy", 1013)     # the last two slots are the owners' and admins'
    assert owner_in == ("welcome", None) and admin_in == ("welcome", None)
    assert full[0] in ("busy", "forbidden")  # the server is full (or not pia's room)
    # all released once the server has seen them leave (bounded wait)
    wait_until(lambda: srv.ctx.admission.invitations.count() == 0, 10,
               what="the invitations' sessions to be released")


# -- Ray: no private cluster without token auth -------------------------------------------------


def test_a_private_ray_without_token_auth_is_refused(monkeypatch):
    from server import cluster
    from server.config import Settings

    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    settings = Settings(cluster_address="auto")
    with pytest.raises(cluster.ClusterAuthDisabled, match="cluster_allow_no_auth"):
        cluster._refuse_no_auth(settings)
    cluster._refuse_no_auth(Settings(cluster_address="auto", cluster_allow_no_auth=True))
    monkeypatch.setenv("RAY_AUTH_MODE", "token")
    cluster._refuse_no_auth(settings)  # token auth: fine
    monkeypatch.delenv("RAY_AUTH_MODE")
    cluster._refuse_no_auth(settings)  # unset: Ray's default is token auth
