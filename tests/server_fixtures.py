"""A real Telesplat server on 127.0.0.1 for tests: uvicorn in a thread, bounded waits.

    from tests.server_fixtures import run_server

    with run_server(tmp_path, max_sessions=2) as srv:
        srv.url          # "http://127.0.0.1:PORT"
        srv.token        # admin token (subject "local")
        srv.ws_url("demo", token=srv.token)

``server`` is a module-scoped pytest fixture with the defaults (synthetic demo avatar, 128 px
frames): ``from tests.server_fixtures import server_fixture  # noqa: F401`` in a test module
makes it available there as ``server``.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import uvicorn

from server.app import create_app
from server.config import Settings
from server.rooms.restart import RestartingServer
from server.stream.gate import handshake_check
from server.stream.net import listen_socket, websocket_protocol

START_TIMEOUT_S = 180.0  # the first warm-up compiles numba kernels (cached afterwards)
STOP_TIMEOUT_S = 15.0
TEST_SIZE = 128


@dataclass
class RunningServer:
    url: str
    token: str
    app: Any
    settings: Settings

    @property
    def ctx(self):
        return self.app.state.ctx

    def ws_url(self, avatar: str | None = "demo", token: str | None = None, **query: Any) -> str:
        params = {k: v for k, v in {"avatar": avatar, "token": token, **query}.items()
                  if v is not None}
        qs = "&".join(f"{k}={v}" for k, v in params.items())
        return self.url.replace("http://", "ws://") + "/v1/stream" + (f"?{qs}" if qs else "")

    def headers(self, token: str | None = None) -> dict[str, str]:
        return {"Authorization": f"Bearer {token or self.token}"}

    def issue(self, subject: str, scopes: tuple[str, ...]) -> str:
        return self.ctx.tokens.issue(subject, scopes)


def wait_until(predicate, timeout: float, interval: float = 0.01, what: str = "condition"):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(interval)
    raise TimeoutError(f"timed out after {timeout} s waiting for {what}")


@contextlib.contextmanager
def run_server(data_dir: Path, *, ws: Any = None, **overrides: Any) -> Iterator[RunningServer]:
    """A server with ``Settings(data_dir=data_dir, demo_avatar="synthetic", 128 px, ...)``
    updated by ``overrides``; stopped (with bounded waits) on exit. ``ws``: uvicorn's WebSocket
    protocol (default: the one ``telesplat serve`` uses)."""
    fields = {"data_dir": data_dir, "demo_avatar": "synthetic", "default_width": TEST_SIZE,
              "default_height": TEST_SIZE, "auth": "local", "stats_interval_s": 0.5,
              "torch_threads": 1,  # two xdist workers share the two cores
              # each freeze is a full collection of the test process's whole heap (hundreds
              # of servers start in a run); tests/test_loop_watch.py runs one with it
              "gc_freeze": False,
              **overrides}
    settings = Settings(**fields)
    app = create_app(settings)
    sock = listen_socket("127.0.0.1", 0, settings.send_buffer_bytes)
    port = sock.getsockname()[1]
    config = uvicorn.Config(app, log_level="warning", lifespan="on",
                            ws=ws or websocket_protocol(
                                settings.hello_max_bytes, handshake_check(app.state.ctx)),
                            ws_max_size=settings.limits.max_message_bytes + 1024,
                            timeout_graceful_shutdown=5)
    server = RestartingServer(config, app.state.ctx)  # as `telesplat serve` runs it
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True,
                              name="uvicorn-test")
    thread.start()
    try:
        wait_until(lambda: server.started or not thread.is_alive(), START_TIMEOUT_S,
                   what="the server to start")
        if not server.started:
            raise RuntimeError("the test server failed to start (see the log above)")
        # The warm-up renders behind the open server: a test's first frame should not wait
        # on numba compiling (minutes on a fresh clone) within its own timeouts.
        ctx = app.state.ctx
        wait_until(lambda: ctx.warmed.is_set() or not thread.is_alive(), START_TIMEOUT_S,
                   what="the warm-up frame")
        yield RunningServer(f"http://127.0.0.1:{port}", app.state.ctx.local_token, app, settings)
    finally:
        server.should_exit = True
        thread.join(STOP_TIMEOUT_S)
        sock.close()
        if thread.is_alive():
            raise RuntimeError("the test server did not stop")


@pytest.fixture(scope="module", name="server")
def server_fixture(tmp_path_factory) -> Iterator[RunningServer]:
    with run_server(tmp_path_factory.mktemp("server")) as srv:
        yield srv


# -- WebSocket helpers (async; run them with asyncio.run) ------------------------------------

WS_TIMEOUT_S = 20.0


async def recv_msg(ws, timeout: float = WS_TIMEOUT_S):
    """The next server message, decoded."""
    import asyncio

    from protocol import decode_server

    return decode_server(await asyncio.wait_for(ws.recv(), timeout))


async def recv_until(ws, predicate, timeout: float = WS_TIMEOUT_S, seen: list | None = None):
    """Messages until one satisfies ``predicate`` (returned); the others go to ``seen``."""
    import asyncio

    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while True:
        msg = await recv_msg(ws, max(0.01, deadline - loop.time()))
        if predicate(msg):
            return msg
        if seen is not None:
            seen.append(msg)


def is_type(kind: str, **fields):
    return lambda m: m.type == kind and all(getattr(m, k) == v for k, v in fields.items())


@contextlib.asynccontextmanager
async def ws_connect(url: str, open_timeout: float = WS_TIMEOUT_S, **kwargs):
    """``websockets.connect`` whose close reads, and drops, what the server still sends. A
    client that stopped reading a stream has its reading paused (``max_queue``), so the
    server's close frame waits behind unread frames and the close took ``close_timeout``
    (5 s) per socket: 15 of each of test_voice_mix's 17 s tests."""
    import websockets

    async with websockets.connect(url, max_size=None, open_timeout=open_timeout,
                                  close_timeout=5, **kwargs) as ws:
        try:
            yield ws
        finally:
            drain = asyncio.ensure_future(_discard(ws))
            try:
                await ws.close()
            finally:
                drain.cancel()
                await asyncio.gather(drain, return_exceptions=True)


async def _discard(ws) -> None:
    async for _ in ws:  # ends when the connection closes
        pass


@contextlib.asynccontextmanager
async def stream(srv: RunningServer, avatar: str | None = "demo", token: str | None = None,
                 welcome: bool = True, **kwargs):
    """An open /v1/stream WebSocket (its ``welcome`` received unless ``welcome=False``)."""
    url = srv.ws_url(avatar, token=srv.token if token is None else (token or None))
    async with ws_connect(url, **kwargs) as ws:
        if welcome:
            ws.welcome = await recv_until(ws, is_type("welcome"))
        yield ws


async def count_frames(ws, seconds: float) -> int:
    """Frames a WebSocket receives within ``seconds`` (bounded by that deadline)."""
    n, end = 0, time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            msg = await recv_msg(ws, timeout=max(0.01, end - time.monotonic()))
        except TimeoutError:
            break
        n += msg.type == "frame"
    return n
