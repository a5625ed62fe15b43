"""Many sessions on one server: the session cap, teardown, the inbound rate limit, fair sharing
of the renderer, and slow clients that must not build up lag or slow anyone else."""

import asyncio
import socket
import time

import numpy as np
import pytest
import websockets

from protocol import Drive, Limits, Ping, Request, encode
from tests.server_fixtures import is_type, recv_msg, recv_until, run_server, stream, wait_until

MAX_SESSIONS = 3


@pytest.fixture(scope="module")
def srv(tmp_path_factory):
    limits = Limits(max_messages_per_s=100.0)
    with run_server(tmp_path_factory.mktemp("sessions"), max_sessions=MAX_SESSIONS,
                    limits=limits, default_width=64, default_height=64,
                    default_max_fps=60, send_buffer_bytes=32 * 1024) as running:
        yield running


def _idle(srv) -> bool:
    ctx = srv.ctx
    return ctx.slots.count == 0 and not ctx.sessions and ctx.scheduler.queued == 0


def drive(seq: int) -> bytes:
    rng = np.random.default_rng(seq)
    return encode(Drive(seq=seq, smplx={"body_pose": rng.normal(0, 0.3, (21, 3))}))


def test_session_cap_and_teardown(srv):
    wait_until(lambda: _idle(srv), 10, what="no sessions")

    async def run():
        async with stream(srv) as a, stream(srv) as b, stream(srv) as c:
            for ws in (a, b, c):
                await recv_until(ws, is_type("frame"))
            assert srv.ctx.slots.count == MAX_SESSIONS
            async with stream(srv, welcome=False) as d:
                err = await recv_msg(d)
                assert err.type == "error" and err.code == "busy"
                with pytest.raises(websockets.ConnectionClosed) as closed:
                    await asyncio.wait_for(d.recv(), 10)
                assert closed.value.rcvd.code == 1013
                assert "busy" in closed.value.rcvd.reason
        # All three left: their tasks end, slots and render jobs are released.
        await asyncio.to_thread(wait_until, lambda: _idle(srv), 10, what="teardown")
        async with stream(srv) as e:  # admitted again
            await recv_until(e, is_type("frame"))
    asyncio.run(run())
    wait_until(lambda: _idle(srv), 10, what="teardown")
    metrics = srv.ctx.metrics.render_text().decode()
    assert 'telesplat_sessions_refused_total{reason="busy"} 1.0' in metrics


def test_teardown_while_rendering(srv):
    """A client that vanishes mid-stream (drives in flight) leaves nothing behind."""
    async def run():
        for _ in range(3):
            async with stream(srv) as ws:
                for i in range(20):
                    await ws.send(drive(i))
            # closed without reading the frames
    asyncio.run(run())
    wait_until(lambda: _idle(srv), 10, what="teardown")
    assert srv.ctx.scheduler.running == 0


def test_inbound_rate_limit(tmp_path):
    # The bucket counts messages as the server reads them, so a CPU-starved server reads
    # slower; 20 / s (burst 20) stays far below any rate it reads 300 queued pings at.
    limits = Limits(max_messages_per_s=20.0)
    with run_server(tmp_path, limits=limits, default_width=64, default_height=64) as server:
        _check_rate_limit(server)


def _check_rate_limit(srv):
    async def run():
        async with stream(srv) as ws:
            for i in range(300):  # far above 20 / s, burst 20
                await ws.send(encode(Ping(t=float(i))))
            await ws.send(encode(Ping(t=-2.0)))  # rate-limited too, most likely
            pongs = limited = 0
            end = time.monotonic() + 1.0  # stats keep coming: count for a fixed time
            while time.monotonic() < end:
                try:
                    msg = await recv_msg(ws, timeout=max(0.01, end - time.monotonic()))
                except TimeoutError:
                    break
                pongs += msg.type == "pong"
                limited += msg.type == "error" and msg.code == "rate_limited"
            assert limited > 0 and pongs >= 20, (pongs, limited)  # at least the burst
            assert pongs < 250
            await asyncio.sleep(0.1)  # tokens refill: the session goes on
            await ws.send(encode(Ping(t=-1.0)))
            await recv_until(ws, is_type("pong", t=-1.0))
    asyncio.run(run())


async def _drive_for(ws, seconds: float, stop: asyncio.Event | None = None) -> int:
    """Send a drive every 10 ms for ``seconds``; the last seq sent."""
    seq, end = 0, time.monotonic() + seconds
    while time.monotonic() < end:
        await ws.send(drive(seq))
        seq += 1
        await asyncio.sleep(0.01)
    return seq - 1


async def _count_frames(ws, seconds: float) -> int:
    n, end = 0, time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            msg = await recv_msg(ws, timeout=max(0.01, end - time.monotonic()))
        except TimeoutError:
            break
        n += msg.type == "frame"
    return n


def test_fair_sharing_between_sessions(srv):
    async def run():
        async with stream(srv) as a, stream(srv) as b:
            await asyncio.gather(*(ws.send(encode(Request(max_fps=60))) for ws in (a, b)))
            sent = asyncio.gather(_drive_for(a, 1.5), _drive_for(b, 1.5))
            counts = await asyncio.gather(_count_frames(a, 1.5), _count_frames(b, 1.5))
            await sent
            assert min(counts) > 5
            assert max(counts) / min(counts) < 1.6, counts
    asyncio.run(run())


def _small_buffer_socket(srv) -> socket.socket:
    """A client socket with a small receive buffer, so a client that does not read stalls
    its connection quickly (as a slow link would)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 16 * 1024)
    sock.connect(("127.0.0.1", int(srv.url.rsplit(":", 1)[1])))
    return sock


def test_slow_client_builds_no_lag_and_slows_nobody(srv):
    async def run():
        sock = _small_buffer_socket(srv)
        async with stream(srv, max_queue=1, sock=sock) as slow, stream(srv) as fast:
            # Big frames (lossless 256 px) so that the buffers on the way hold few of them.
            await slow.send(encode(Request(codec="png", width=256, height=256)))
            await recv_until(slow, lambda m: m.type == "frame" and m.codec == "png")
            solo_task = asyncio.create_task(_drive_for(fast, 1.0))
            solo = await _count_frames(fast, 1.0)
            await solo_task
            # The slow client keeps driving but stops reading.
            slow_sender = asyncio.create_task(_drive_for(slow, 2.5))
            fast_sender = asyncio.create_task(_drive_for(fast, 2.5))
            await _count_frames(fast, 1.0)  # until the slow connection's buffers are full
            shared = await _count_frames(fast, 1.5) / 1.5
            last = await slow_sender
            await fast_sender
            assert shared > 0.6 * solo, (shared, solo)  # the stalled session takes no slot
            # Reading again: what was buffered comes out, then the newest state at once.
            seen = []
            await recv_until(slow, is_type("frame", seq=last), timeout=10, seen=seen)
            stale = [m for m in seen if m.type == "frame"]
            assert len(stale) < 15, f"{len(stale)} stale frames were buffered"
    asyncio.run(run())
