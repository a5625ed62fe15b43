"""A streaming run on the GPU (marked ``gpu``): a server on gsplat serving 1, 8 and 32 plain
sessions, and a room of 32 viewers at distinct views (batched rendering), each getting
frames. Skipped without CUDA."""

import asyncio
import contextlib

import pytest

from protocol import Orbit, View, encode
from tests.server_fixtures import is_type, recv_until, run_server, stream
from tests.test_server_rooms import create_room, invite, join, live

pytestmark = pytest.mark.gpu
SIZE = 256
FRAMES = 5  # per session


@pytest.fixture(scope="module")
def srv(tmp_path_factory):  # pragma: no cover (needs CUDA)
    pytest.importorskip("gsplat", reason="gsplat not installed (the cuda extra)")
    with run_server(tmp_path_factory.mktemp("gpustream"), backend="gsplat", max_sessions=40,
                    render_threads=2, torch_threads=2, default_width=SIZE,
                    default_height=SIZE, default_max_fps=60) as running:
        yield running


async def _frames(ws, n: int) -> list:
    return [await recv_until(ws, is_type("frame")) for _ in range(n)]


@pytest.mark.parametrize("sessions", [1, 8, 32])
def test_sessions_stream_on_the_gpu(srv, sessions):  # pragma: no cover (needs CUDA)
    async def run():
        async with contextlib.AsyncExitStack() as stack:
            socks = [await stack.enter_async_context(stream(srv)) for _ in range(sessions)]
            for i, ws in enumerate(socks):
                await ws.send(encode(View(orbit=Orbit(yaw_deg=-60.0 + 4.0 * i))))
            return await asyncio.gather(*(_frames(ws, FRAMES) for ws in socks))

    got = asyncio.run(run())
    assert len(got) == sessions
    assert all(f.width == SIZE and f.data for frames in got for f in frames)


def test_a_room_of_32_viewers_renders_in_batches(srv):  # pragma: no cover (needs CUDA)
    room = create_room(srv)
    watch = invite(srv, room["id"], "watch")

    async def run():
        async with join(srv, room["id"], srv.token), contextlib.AsyncExitStack() as stack:
            viewers = [await stack.enter_async_context(join(srv, room["id"], watch["token"]))
                       for _ in range(32)]
            assert viewers[0].welcome.encoders is not None
            for i, ws in enumerate(viewers):
                await ws.send(encode(View(orbit=Orbit(yaw_deg=-80.0 + 5.0 * i))))
            return await asyncio.gather(*(_frames(ws, FRAMES) for ws in viewers))

    got = asyncio.run(run())
    assert all(f.data for frames in got for f in frames)
    frames = live(srv, room["id"]).frames
    assert frames._batches is not None  # auto: batching on with gsplat
    assert frames.counters.renders >= 1
