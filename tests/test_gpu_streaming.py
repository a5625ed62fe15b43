"""A streaming run on the GPU (marked ``gpu``): a server on gsplat serving 1, 8 and 32 plain
sessions, and a room of 32 viewers at distinct views (batched rendering), each getting
frames. Skipped without CUDA."""

import asyncio
import contextlib

import pytest

from protocol import Drive, Orbit, View, encode
from tests.server_fixtures import is_type, recv_until, run_server, stream
from tests.test_server_rooms import create_room, invite, join, live

pytestmark = pytest.mark.gpu
SIZE = 256
FRAMES = 5  # per session


@pytest.fixture(scope="module")
def srv(tmp_path_factory):  # pragma: no cover (needs CUDA)
    pytest.importorskip("gsplat", reason="gsplat not installed (the cuda extra)")
    with run_server(tmp_path_factory.mktemp("gpustream"), backend="gsplat", max_sessions=40,
                    max_sessions_per_invitation=32, render_threads=2, torch_threads=2,
                    default_width=SIZE, default_height=SIZE, default_max_fps=60) as running:
        yield running


def _drive(k: int) -> bytes:
    return encode(Drive(seq=k + 1, smplx={"jaw_pose": [0.05 * (k + 1), 0.0, 0.0]}))


async def _lockstep(driver, watchers: list) -> list[list]:
    """``FRAMES`` drives from ``driver``, each sent once every watcher has a frame after the
    last: a session renders only when something changed, so each drive brings each watcher
    at least one new frame (a settled view's full-quality frame may add one)."""
    got: list[list] = [[] for _ in watchers]
    for k in range(FRAMES):
        await driver.send(_drive(k))
        frames = await asyncio.gather(*(recv_until(ws, is_type("frame")) for ws in watchers))
        for mine, f in zip(got, frames, strict=True):
            mine.append(f)
    return got


def _full_size(got: list[list]) -> bool:
    return all(f.data and (f.preview or f.width == SIZE) for frames in got for f in frames)


@pytest.mark.parametrize("sessions", [1, 8, 32])
def test_sessions_stream_on_the_gpu(srv, sessions):  # pragma: no cover (needs CUDA)
    async def run():
        async with contextlib.AsyncExitStack() as stack:
            socks = [await stack.enter_async_context(stream(srv)) for _ in range(sessions)]
            for i, ws in enumerate(socks):
                await ws.send(encode(View(orbit=Orbit(yaw_deg=-60.0 + 4.0 * i))))
            await asyncio.gather(*(recv_until(ws, is_type("frame")) for ws in socks))
            per = await asyncio.gather(*(_lockstep(ws, [ws]) for ws in socks))
            return [frames for (frames,) in per]

    got = asyncio.run(run())
    assert len(got) == sessions and all(len(frames) == FRAMES for frames in got)
    assert _full_size(got)


def test_a_room_of_32_viewers_renders_in_batches(srv):  # pragma: no cover (needs CUDA)
    room = create_room(srv)
    watch = invite(srv, room["id"], "watch")

    async def run():
        async with join(srv, room["id"], srv.token) as performer, \
                contextlib.AsyncExitStack() as stack:
            viewers = [await stack.enter_async_context(join(srv, room["id"], watch["token"]))
                       for _ in range(32)]
            assert viewers[0].welcome.encoders is not None
            for i, ws in enumerate(viewers):
                await ws.send(encode(View(orbit=Orbit(yaw_deg=-80.0 + 5.0 * i))))
            await asyncio.gather(*(recv_until(ws, is_type("frame")) for ws in viewers))
            return await _lockstep(performer, viewers)

    got = asyncio.run(run())
    assert len(got) == 32 and all(len(frames) == FRAMES for frames in got)
    assert _full_size(got)
    scene = live(srv, room["id"]).scene
    assert scene.batches is not None  # auto: batching on with gsplat
    assert scene.counters.renders >= 1 and scene.counters.batched >= 1
