"""Many sessions on one server: the session cap, teardown, the inbound rate limit, fair sharing
of the renderer, and slow clients that must not build up lag or slow anyone else."""

import asyncio
import math
import socket
import threading
import time

import msgpack
import numpy as np
import pytest
import websockets

from protocol import Drive, Limits, Ping, Request, encode
from server.stream.drive import DriveState
from server.stream.scheduler import RenderScheduler
from tests.server_fixtures import (
    count_frames,
    is_type,
    recv_msg,
    recv_until,
    run_server,
    stream,
    wait_until,
)

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
    """Send a drive every 10 ms for ``seconds``, or until ``stop`` is set when given
    (``seconds`` then bounds it); the last seq sent."""
    seq, end = 0, time.monotonic() + seconds
    while time.monotonic() < end and not (stop is not None and stop.is_set()):
        await ws.send(drive(seq))
        seq += 1
        await asyncio.sleep(0.01)
    return seq - 1


def test_fair_sharing_between_sessions(srv):
    async def run():
        async with stream(srv) as a, stream(srv) as b:
            await asyncio.gather(*(ws.send(encode(Request(max_fps=60))) for ws in (a, b)))
            sent = asyncio.gather(_drive_for(a, 1.5), _drive_for(b, 1.5))
            counts = await asyncio.gather(count_frames(a, 1.5), count_frames(b, 1.5))
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


async def _until_stalled(srv, reader, codec: str, timeout_s: float = 30.0) -> None:
    """Until the session asking ``codec`` waits on its client (bounded; ``reader`` keeps
    reading meanwhile)."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if any(s.stalled and s.request.codec == codec for s in srv.ctx.sessions.values()):
            return
        await count_frames(reader, 0.1)
    raise AssertionError(f"no {codec} session stalled within {timeout_s} s")


def test_slow_client_builds_no_lag_and_slows_nobody(srv):
    async def run():
        sock = _small_buffer_socket(srv)
        async with stream(srv, max_queue=1, sock=sock) as slow, stream(srv) as fast:
            # Big frames (lossless 256 px) so that the buffers on the way hold few of them.
            await slow.send(encode(Request(codec="png", width=256, height=256)))
            await recv_until(slow, lambda m: m.type == "frame" and m.codec == "png")
            solo_task = asyncio.create_task(_drive_for(fast, 1.0))
            solo = await count_frames(fast, 1.0)
            await solo_task
            # The slow client keeps driving but stops reading.
            # Both drive until the counting ends: on a loaded machine the stall takes longer
            # than any fixed drive time, and an undriven session renders nothing new.
            counted = asyncio.Event()
            slow_sender = asyncio.create_task(_drive_for(slow, 60.0, counted))
            fast_sender = asyncio.create_task(_drive_for(fast, 60.0, counted))
            await count_frames(fast, 1.0)  # until the slow connection's buffers are full
            await _until_stalled(srv, fast, "png")
            shared = await count_frames(fast, 1.5) / 1.5
            counted.set()
            last = await slow_sender
            await fast_sender
            assert shared > 0.6 * solo, (shared, solo)  # the stalled session takes no slot
            # Reading again: what was buffered comes out, then the newest state at once.
            seen = []
            await recv_until(slow, is_type("frame", seq=last), timeout=10, seen=seen)
            stale = [m for m in seen if m.type == "frame"]
            assert len(stale) < 15, f"{len(stale)} stale frames were buffered"
    asyncio.run(run())


# -- sessions that never stop for good (issue 13, finding 6) --------------------------------


def _raw_drive(seq: int, **families) -> bytes:
    """A drive packed without client-side validation, as a hostile client would send it."""
    return msgpack.packb({"type": "drive", "seq": seq, **families}, use_bin_type=True)


ABSURD_DRIVES = [
    {"smplx": {"betas": [1e300]}},
    {"smplx": {"leye_pose": [1e38, 0.0, 0.0]}},
    {"smplx": {"jaw_pose": [0.0, math.nan, 0.0]}},
    {"smplx": {"transl": [math.inf, 0.0, 0.0]}},
    {"flame": {"eyes_pose": [0.0, 0.0, 0.0, 1e38, 0.0, 0.0]}},
    {"smplx": {"body_pose": [1e30] * 63}},
]


def test_absurd_drives_are_refused_and_the_next_frame_renders(srv):
    async def run():
        async with stream(srv) as ws:
            lim = ws.welcome.limits  # the ranges are announced up front
            assert (lim.max_coefficient, lim.min_fps) == (Limits().max_coefficient, 1.0)
            await recv_until(ws, is_type("frame"))
            for seq, families in enumerate(ABSURD_DRIVES, start=100):
                await ws.send(_raw_drive(seq, **families))
                err = await recv_until(ws, is_type("error"))
                assert err.code == "invalid", err.message
                assert err.answers.type == "drive" and err.answers.seq == seq
                await ws.send(drive(seq))  # the session goes on: a good drive renders
                frame = await recv_until(ws, is_type("frame", seq=seq))
                assert frame.data
    asyncio.run(run())


def test_a_tiny_max_fps_is_woken_by_the_next_request(tmp_path):
    """max_fps 0.001 (allowed here) puts the loop to wait ~1000 s; max_fps 30 wakes it.
    ``frame_burst`` 1: with a burst the drive's frame would not wait at all."""
    limits = Limits(min_fps=0.001)
    with run_server(tmp_path, limits=limits, default_width=64, default_height=64,
                    frame_burst=1) as server:
        async def run():
            async with stream(server) as ws:
                await recv_until(ws, is_type("frame"))
                await ws.send(msgpack.packb({"type": "request", "max_fps": 0.001}))
                await ws.send(drive(2))  # waits for the 1000 s cap
                await ws.send(encode(Request(max_fps=30)))
                await recv_until(ws, is_type("frame", seq=2), timeout=15)
        asyncio.run(run())


def test_the_default_limits_refuse_a_sleeping_frame_rate(srv):
    async def run():
        async with stream(srv) as ws:
            await ws.send(msgpack.packb({"type": "request", "max_fps": 0.001}))
            err = await recv_until(ws, is_type("error"))
            assert err.code == "invalid" and "max_fps" in err.message
            await ws.send(drive(7))
            await recv_until(ws, is_type("frame", seq=7))
    asyncio.run(run())


def test_a_failed_render_puts_back_only_what_it_showed():
    good, state = DriveState(), DriveState()
    jaw = {"jaw_pose": np.zeros(3)}
    state.apply(Drive(seq=1, smplx=jaw), {"smplx": jaw})
    good = state.copy()
    bad = {"jaw_pose": np.full(3, 0.3), "body_pose": np.zeros((21, 3))}
    state.apply(Drive(seq=2, smplx=bad), {"smplx": bad})
    failed = state.copy()
    newer = {"body_pose": np.full((21, 3), 0.1)}
    state.apply(Drive(seq=3, smplx=newer), {"smplx": newer})  # sent after the failed frame
    version = state.version
    assert state.restore(failed, good)
    assert state.families["smplx"]["jaw_pose"] is jaw["jaw_pose"]       # put back
    assert state.families["smplx"]["body_pose"] is newer["body_pose"]   # newer: kept
    assert state.version > version and state.seq == 3
    assert not state.restore(failed, good)  # nothing left to put back


# -- fair share of render time, not of frames (issue 13, finding 7) --------------------------

BIG = 512  # the largest frame the fairness server allows: PNG + alpha + depth at BIG x BIG


@pytest.fixture(scope="module")
def fair_srv(tmp_path_factory):
    limits = Limits(max_width=BIG, max_height=BIG, max_messages_per_s=200.0)
    with run_server(tmp_path_factory.mktemp("fair"), limits=limits, default_max_fps=60,
                    fair_share="time", fair_share_window_s=1.0) as running:
        yield running


def _render_share(srv, cheap: str, big: str, seconds: float):
    """(frames of each, the expensive session's render seconds / the window) while both
    drive continuously, counted over `seconds` after a warm-up."""
    sched = srv.ctx.scheduler

    async def run():
        async with stream(srv) as a, stream(srv) as b:
            ids = {cheap: a.welcome.session, big: b.welcome.session}
            await a.send(encode(Request(max_fps=60, width=64, height=64)))
            await b.send(encode(Request(width=BIG, height=BIG, codec="png", max_fps=60,
                                        outputs=["rgb", "alpha", "depth"])))
            warm = asyncio.gather(_drive_for(a, 2.0), _drive_for(b, 2.0),
                                  count_frames(a, 2.0), count_frames(b, 2.0))
            await warm  # shares settle (window 1 s)
            before = sched.render_seconds(ids[big])
            start = time.monotonic()
            sent = asyncio.gather(_drive_for(a, seconds), _drive_for(b, seconds))
            counts = await asyncio.gather(count_frames(a, seconds), count_frames(b, seconds))
            window = time.monotonic() - start
            used = sched.render_seconds(ids[big]) - before
            await sent
            return counts, used / window
    return asyncio.run(run())


def test_an_expensive_session_gets_its_share_of_render_time_not_more(fair_srv):
    seconds = 4.0
    (cheap, big), big_share = _render_share(fair_srv, "cheap", "big", seconds)
    # Served frame for frame, the expensive session would take most of the time (its frames
    # cost several cheap ones) and the two would get equal frame counts.
    assert big >= 1, "the expensive session still gets frames"
    # Its share is 1/2; the credit it may save up (share x window, 1 s) can fall into the
    # count, and one frame (~0.1 s on a loaded machine) straddles each end. Measured 0.43-0.61
    # under -n 2 (the frames policy: ~0.69, which the frame ratio below tells apart).
    bound = 0.5 * (1 + 1.0 / seconds) + 2 * 0.1 / seconds
    assert big_share <= bound, (big_share, bound, cheap, big)
    assert cheap >= 1.5 * big, (cheap, big)  # frame for frame it would be 1:1 (measured 2.5-3.4x)


@pytest.mark.parametrize("policy,first", [("time", "light"), ("frames", "heavy")])
def test_the_scheduler_serves_the_least_recent_render_time_first(policy, first):
    sched = RenderScheduler(1, 1, policy, window_s=1.0)
    try:
        now = time.monotonic()
        sched.share.add("heavy", 5.0, now)
        sched.share.add("light", 0.01, now)
        gate, order = threading.Event(), []
        blocker = sched.submit(gate.wait, 10)  # holds the one thread while both queue
        jobs = [sched.submit(order.append, name, key=name) for name in ("heavy", "light")]
        gate.set()
        for job in (blocker, *jobs):
            job.result(timeout=10)
        assert order[0] == first
    finally:
        sched.shutdown()


def test_only_a_session_over_its_share_is_paced_and_only_while_others_are_active():
    sched = RenderScheduler(1, 1, "time", window_s=1.0)  # two sessions: half a second each
    try:
        now = time.monotonic()
        for key in ("heavy", "light"):
            sched.share.seen(key, now)
        sched.share.add("light", 0.01, now)
        sched.share.add("heavy", 0.3, now)   # within its saved-up credit (0.5 s): goes on
        assert sched.pace_s("heavy") == 0.0
        sched.share.add("heavy", 1.0, now)   # 0.8 s in debt, refilled at 0.5 s per second
        assert 1.5 < sched.pace_s("heavy") <= 1.6
        assert sched.pace_s("light") == 0.0
        sched.forget("light")                # alone: never held back
        assert sched.pace_s("heavy") == 0.0
        assert RenderScheduler(1, 1, "frames").pace_s("heavy") == 0.0
        with pytest.raises(ValueError):
            RenderScheduler(1, 1, "lottery")
    finally:
        sched.shutdown()


def test_the_scheduler_cancels_queued_jobs_on_shutdown():
    sched = RenderScheduler(1, 1)
    gate = threading.Event()
    running = sched.submit(gate.wait, 10, key="a")
    queued = sched.submit(time.monotonic, key="b")
    wait_until(lambda: sched.running == 1, 10, what="the first job to start")
    gate.set()
    sched.shutdown()
    assert running.result(timeout=1) is True
    assert queued.cancelled() or queued.done()
    assert sched.queued == 0 and sched.running == 0
    with pytest.raises(RuntimeError):
        sched.submit(time.monotonic)


def test_a_session_that_never_runs_closes_its_scene(tmp_path, monkeypatch):
    """The scene opened for a plain session that then fails to start (here its tracker
    cannot be made) is closed at once: with render workers it holds a scene on one of them."""
    with run_server(tmp_path, startup_room=False) as server:
        ctx = server.ctx
        made, closed = [], []
        real = ctx.render.open_scene

        async def watched(ctx_, room, kind):
            scene = await real(ctx_, room, kind)
            close = scene.close
            scene.close = lambda: (closed.append(scene), close())
            made.append(scene)
            return scene

        def no_tracker(avatar_id):
            raise RuntimeError("tracker unavailable")

        monkeypatch.setattr(ctx.render, "open_scene", watched)
        monkeypatch.setattr(ctx, "session_tracker", no_tracker)

        async def run():
            async with stream(server, welcome=False) as ws:
                with pytest.raises(websockets.ConnectionClosedError) as closed_by:
                    await recv_until(ws, is_type("welcome"))
            return closed_by.value.rcvd

        refusal = asyncio.run(run())
        assert refusal.code == 1011 and "cannot load avatar" in refusal.reason
        assert len(made) == 1 and closed == made
        monkeypatch.undo()
        assert asyncio.run(_still_serves(server))  # and the server goes on


async def _still_serves(server) -> bool:
    async with stream(server) as ws:
        return ws.welcome.type == "welcome"
