"""The WebSocket front door on a real server: nothing is decoded before authentication, waiting
connections are capped per address and in total, the hello has a deadline, sessions are capped
per user, a huge message of tiny objects is refused in a session before it is unpacked, tokens
never reach a log line, and tokens issued while the server runs work without a restart."""

from __future__ import annotations

import asyncio
import logging
import os
import subprocess
import sys
from pathlib import Path

import httpx
import msgpack
import pytest
import websockets

from client.stream import StreamClient
from protocol import Hello, Ping, encode
from server.stream.gate import (
    CLOSE_BUSY,
    CLOSE_HELLO_TIMEOUT,
    CLOSE_TOO_LARGE,
    CLOSE_TOO_MANY,
)
from tests.server_fixtures import (
    WS_TIMEOUT_S,
    is_type,
    recv_msg,
    recv_until,
    run_server,
    stream,
    wait_until,
)

REPO = Path(__file__).resolve().parent.parent
PER_ADDRESS = 2
WAITING_TOTAL = 3
HEAVY_BYTES = 7 * 2**20


@pytest.fixture(scope="module")
def srv(tmp_path_factory):
    with run_server(tmp_path_factory.mktemp("preauth"), max_unauthenticated_per_address=PER_ADDRESS,
                    max_unauthenticated=WAITING_TOTAL, hello_timeout_s=60.0,
                    max_sessions_per_user=1, tokens_reload_interval_s=0.05,
                    max_tickets_per_user=2) as running:
        yield running


def heavy_message() -> bytes:
    """~7 MiB of tiny nested arrays, each within the unpacker's own per-array limit (4096):
    msgpack needs over a second to unpack it."""
    block = [[1, 2, 3, 4]] * 1024  # 5 bytes an entry
    data = msgpack.packb({"type": "hello", "client": "x",
                          "x": [block] * (HEAVY_BYTES // (5 * 1024 + 3) - 1)})
    assert HEAVY_BYTES * 0.9 < len(data) <= HEAVY_BYTES
    return data


def _waiting(srv, address: str | None = None) -> int:
    return srv.ctx.admission.waiting.count(address)


async def _connect(srv, source: str = "127.0.0.1", token: str | None = None, **kwargs):
    """A /v1/stream connection from ``source`` (any 127/8 address reaches the server)."""
    url = srv.ws_url("demo", token=token)
    return await websockets.connect(url, max_size=None, open_timeout=WS_TIMEOUT_S,
                                    close_timeout=5, local_addr=(source, 0), **kwargs)


async def _refusal(ws) -> tuple[str, str, int]:
    """The error's code and message, and the close code that follows it."""
    err = await recv_msg(ws)
    assert err.type == "error"
    with pytest.raises(websockets.ConnectionClosed) as closed:
        await asyncio.wait_for(ws.recv(), WS_TIMEOUT_S)
    return err.code, err.message, closed.value.rcvd.code


async def _health(srv) -> dict:
    async with httpx.AsyncClient(base_url=srv.url, timeout=WS_TIMEOUT_S) as c:
        r = await c.get("/v1/health")
        assert r.status_code == 200
        return r.json()


async def _wait(predicate, what: str) -> None:
    await asyncio.to_thread(wait_until, predicate, 20, what=what)


async def _closed_unread(ws) -> tuple[int, str]:
    """The close that the frame parser sent on an oversize frame (no error message first)."""
    with pytest.raises(websockets.ConnectionClosed) as closed:
        await asyncio.wait_for(ws.recv(), WS_TIMEOUT_S)
    return closed.value.rcvd.code, closed.value.rcvd.reason


async def _flood_and_check_health(srv, refused) -> list:
    """Every waiting slot taken by a peer that then sends the heavy message; /v1/health
    answers throughout; the refusals, as ``refused(ws)`` reads them."""
    heavy = heavy_message()
    peers = [await _connect(srv, f"127.0.0.{i + 2}") for i in range(WAITING_TOTAL)]
    await _wait(lambda: _waiting(srv) == WAITING_TOTAL, "the peers to wait")
    assert (await _health(srv))["status"] == "ok"  # while they hold every waiting slot
    sends = [asyncio.create_task(ws.send(heavy)) for ws in peers]
    health, *refusals = await asyncio.gather(_health(srv), *map(refused, peers))
    await asyncio.gather(*sends, return_exceptions=True)  # may fail: the server closed
    assert health["status"] == "ok"
    await _wait(lambda: _waiting(srv) == 0, "the waiting slots to be released")
    return refusals


def test_an_oversize_first_frame_is_refused_unread_while_health_answers(srv):
    async def run():
        for close, reason in await _flood_and_check_health(srv, _closed_unread):
            # The frame parser refused it from its header: 1009 "message too big", no
            # error message (the app never saw it).
            assert close == 1009 and "4096" in reason, (close, reason)
    asyncio.run(run())


def test_without_the_transport_bound_the_app_refuses_by_length_undecoded(tmp_path):
    with run_server(tmp_path, ws="auto", warmup=False,  # e.g. wsproto: the app's check alone
                    max_unauthenticated=WAITING_TOTAL) as plain:
        async def run():
            for code, message, close in await _flood_and_check_health(plain, _refusal):
                # The frame's length alone refused it: a decode would have said
                # bad_message, invalid or "exceeds the limit".
                assert (code, close) == ("too_large", CLOSE_TOO_LARGE)
                assert "before authentication" in message
        asyncio.run(run())


def test_after_the_hello_messages_may_be_large_again(srv):
    async def run():
        async with stream(srv, token="", welcome=False) as ws:  # no credentials in the URL
            await ws.send(encode(Hello(token=srv.token, client="test")))
            await recv_until(ws, is_type("welcome"))
            big = msgpack.packb({"type": "ping", "t": 3.0, "pad": b"x" * 100_000})
            await ws.send(big)  # over the hello's size: read and decoded (then refused)
            err = await recv_until(ws, is_type("error"))
            assert err.code == "invalid" and "pad" in err.message
            await ws.send(encode(Ping(t=5.0)))
            assert (await recv_until(ws, is_type("pong"))).t == 5.0
    asyncio.run(run())


def test_waiting_connections_are_capped_per_address_and_in_total(srv):
    async def run():
        first = [await _connect(srv) for _ in range(PER_ADDRESS)]
        await _wait(lambda: _waiting(srv, "127.0.0.1") == PER_ADDRESS, "two waiting")
        over_address = await _connect(srv)
        code, message, close = await _refusal(over_address)
        assert (code, close) == ("busy", CLOSE_TOO_MANY) and "this address" in message
        other = await _connect(srv, "127.0.0.2")  # another address still gets in ...
        await _wait(lambda: _waiting(srv) == WAITING_TOTAL, "all slots taken")
        over_total = await _connect(srv, "127.0.0.3")  # ... until the total is reached
        code, message, close = await _refusal(over_total)
        assert (code, close) == ("busy", CLOSE_BUSY) and "waiting to authenticate" in message
        # The Python client's token comes in the header: it needs no waiting slot.
        async with await StreamClient.connect(srv.url, "demo", srv.token,
                                              timeout=WS_TIMEOUT_S) as client:
            assert client.welcome.session
        # Authenticating frees the slot: the address may wait again.
        await first[0].send(encode(Hello(token=srv.token, client="test")))
        await recv_until(first[0], is_type("welcome"))
        await _wait(lambda: _waiting(srv, "127.0.0.1") == PER_ADDRESS - 1, "a slot freed")
        again = await _connect(srv)
        await _wait(lambda: _waiting(srv, "127.0.0.1") == PER_ADDRESS, "the slot retaken")
        for ws in (*first, other, again):
            await ws.close()
        await _wait(lambda: _waiting(srv) == 0, "every slot released")
    asyncio.run(run())
    metrics = srv.ctx.metrics.render_text().decode()
    assert 'telesplat_sessions_refused_total{reason="busy"}' in metrics


def test_hello_deadline(tmp_path):
    with run_server(tmp_path, hello_timeout_s=0.2, warmup=False) as quick:
        async def run():
            ws = await _connect(quick)
            code, message, close = await _refusal(ws)  # sent nothing
            assert (code, close) == ("unauthorized", CLOSE_HELLO_TIMEOUT) and "0.2 s" in message
            await _wait(lambda: _waiting(quick) == 0, "the slot released")
        asyncio.run(run())


def test_sessions_per_user(srv):
    ann = srv.issue("ann", ("stream",))
    bob = srv.issue("bob", ("stream",))

    async def run():
        async with stream(srv, token=ann) as first:
            await recv_until(first, is_type("frame"))
            async with stream(srv, token=ann, welcome=False) as second:
                code, message, close = await _refusal(second)
                assert (code, close) == ("busy", CLOSE_TOO_MANY) and "'ann'" in message
            async with stream(srv, token=bob) as other, stream(srv) as admin, \
                    stream(srv) as admin2:  # another user, and admins (exempt)
                for ws in (other, admin, admin2):
                    await recv_until(ws, is_type("frame"))
        await _wait(lambda: srv.ctx.admission.sessions.count("ann") == 0, "ann's session gone")
        async with stream(srv, token=ann) as again:  # the slot came back
            await recv_until(again, is_type("frame"))
    asyncio.run(run())


def test_a_message_of_too_many_objects_is_refused_before_unpacking(srv):
    heavy = heavy_message()

    async def run():
        async with stream(srv) as ws:
            await ws.send(heavy)
            health, err = await asyncio.gather(
                _health(srv), recv_until(ws, is_type("error")))
            assert health["status"] == "ok"
            assert err.code == "too_large" and "16384 msgpack objects" in err.message
            await ws.send(encode(Ping(t=7.0)))  # the session goes on
            assert (await recv_until(ws, is_type("pong"))).t == 7.0
    asyncio.run(run())


@pytest.fixture
def server_log():
    """Every line uvicorn's access and error loggers write at INFO, formatted as uvicorn does."""
    from uvicorn.logging import AccessFormatter, DefaultFormatter

    lines: list[str] = []

    class Collect(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            lines.append(self.format(record))

    handlers = {"uvicorn.access": Collect(), "uvicorn.error": Collect()}
    handlers["uvicorn.access"].setFormatter(AccessFormatter(
        '%(client_addr)s - "%(request_line)s" %(status_code)s'))
    handlers["uvicorn.error"].setFormatter(DefaultFormatter("%(message)s"))
    levels = {}
    for name, handler in handlers.items():
        logger = logging.getLogger(name)
        levels[name] = logger.level
        logger.setLevel(logging.INFO)
        logger.addHandler(handler)
    try:
        yield lines
    finally:
        for name, handler in handlers.items():
            logging.getLogger(name).removeHandler(handler)
            logging.getLogger(name).setLevel(levels[name])


def test_tokens_never_reach_the_log(srv, server_log):
    async def run():
        async with httpx.AsyncClient(base_url=srv.url, timeout=WS_TIMEOUT_S) as c:
            await c.get(f"/v1/avatars?token={srv.token}&x=1")
            await c.get("/v1/health", params={"ticket": "tk-secret-ticket"})
        async with stream(srv) as ws:  # the legacy ?token= WebSocket URL
            await recv_until(ws, is_type("frame"))
    asyncio.run(run())
    wait_until(lambda: any("WebSocket /v1/stream" in line for line in server_log), 10,
               what="the WebSocket's log line")
    text = "\n".join(server_log)
    assert srv.token not in text and srv.token.removeprefix("tsk_") not in text
    assert "tk-secret-ticket" not in text
    # (REST reads tokens from the header only: 401)
    assert '"GET /v1/avatars?token=[redacted]&x=1 HTTP/1.1" 401' in text, text
    assert "/v1/stream?avatar=demo&token=[redacted]" in text, text


def test_tokens_issued_while_running_work_without_a_restart(srv):
    env = {k: v for k, v in os.environ.items() if not k.startswith("TELESPLAT_")}
    out = subprocess.run(
        [sys.executable, "-m", "server", "--data-dir", str(srv.settings.data_dir),
         "--issue-token", "carol:stream"],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=120, check=True)
    carol = out.stdout.strip().splitlines()[-1]
    assert carol.startswith("tsk_")

    def status(token: str) -> int:
        return httpx.get(f"{srv.url}/v1/avatars", headers=srv.headers(token), timeout=10
                         ).status_code

    wait_until(lambda: status(carol) == 200, 10, what="the new token to be accepted")
    assert status(srv.token) == 200  # the CLI's write kept the server's own token

    async def run():
        async with stream(srv, token="", welcome=False) as ws:
            await ws.send(encode(Hello(token=carol)))
            await recv_until(ws, is_type("frame"))
    asyncio.run(run())

    from server.auth import TokenStore
    assert TokenStore(srv.settings.tokens_path).revoke(carol)  # another process revokes it
    wait_until(lambda: status(carol) == 401, 10, what="the revoked token to be refused")


def test_the_byte_budget_delays_instead_of_dropping():
    from server.stream.inbound import ByteBudget

    budget = ByteBudget(rate=1.0, burst=100.0)  # 1 byte/s: refills are negligible here
    assert budget.reserve(100) == 0.0  # the burst
    assert 9.0 < budget.reserve(10) <= 10.0  # 10 bytes of debt: wait ~10 s
    assert 19.0 < budget.reserve(10) <= 20.0  # debts add up


def test_stream_tickets_are_single_use_and_capped(srv):
    tess = srv.issue("tess", ("stream",))
    with httpx.Client(base_url=srv.url, timeout=WS_TIMEOUT_S) as c:
        assert c.post("/v1/stream/tickets").status_code == 401  # the token, in the header
        tickets = [c.post("/v1/stream/tickets", headers=srv.headers(tess)) for _ in range(3)]
    assert [r.status_code for r in tickets] == [201, 201, 429]  # max_tickets_per_user=2
    ticket = tickets[0].json()["ticket"]
    assert ticket.startswith("tkt_") and tickets[0].json()["expires_in_s"] > 0

    async def run():
        url = srv.ws_url("demo", ticket=ticket)
        async with websockets.connect(url, max_size=None, open_timeout=WS_TIMEOUT_S) as ws:
            welcome = await recv_until(ws, is_type("welcome"))
            assert welcome.type == "welcome"
            await recv_until(ws, is_type("frame"))
        async with websockets.connect(url, max_size=None, open_timeout=WS_TIMEOUT_S) as ws:
            code, message, close = await _refusal(ws)  # spent
            assert (code, close) == ("unauthorized", 4401) and "ticket" in message
    asyncio.run(run())


def test_an_expired_ticket_is_refused():
    from server.auth import Principal
    from server.stream.tickets import TicketBook

    who = Principal("tess", frozenset({"stream"}))
    assert TicketBook(ttl_s=0.0, max_per_subject=4).redeem(
        TicketBook(ttl_s=0.0, max_per_subject=4).issue(who)) is None  # another book's
    book = TicketBook(ttl_s=0.0, max_per_subject=4)
    assert book.redeem(book.issue(who)) is None  # expired the moment it was made
    book = TicketBook(ttl_s=3600.0, max_per_subject=4)
    ticket = book.issue(who)
    assert book.redeem(ticket) == who and book.redeem(ticket) is None and len(book) == 0
