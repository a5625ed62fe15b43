"""Batched views in the server: renders of one room state and request from different views
that wait together share one rasterizer call (server/view_batch.py), with the pictures that
separate renders give. Runs on CPU (render_batch_views forces batching there)."""

import asyncio
import concurrent.futures
import contextlib
import threading

import pytest
import torch

from protocol import Orbit, Request, View, encode
from server.stream.batching import DEFAULT_BATCH_VIEWS, ViewBatches, batch_views
from server.stream.drive import DriveState
from server.stream.scene import FrameJob, Scene
from server.stream.scheduler import RenderScheduler
from tests.server_fixtures import is_type, recv_until, run_server
from tests.test_server_rooms import create_room, invite, join, live

TIMEOUT_S = 60


@contextlib.contextmanager
def blocked_scheduler():
    """A one-thread scheduler whose thread is held until the block ends: what is submitted
    meanwhile waits, as it does behind a busy GPU."""
    scheduler = RenderScheduler(render_threads=1)
    gate = threading.Event()
    started = threading.Event()
    holder = scheduler.submit(lambda: (started.set(), gate.wait(TIMEOUT_S)))
    assert started.wait(TIMEOUT_S)
    try:
        yield scheduler, gate
    finally:
        gate.set()
        holder.result(TIMEOUT_S)
        scheduler.shutdown()


def test_items_of_one_key_run_as_one_batch():
    runs = []
    batches = ViewBatches(lambda items: runs.append(list(items)) or [i * 10 for i in items],
                          max_views=3)
    with blocked_scheduler() as (scheduler, gate):
        futs = [batches.submit(scheduler, "a", i) for i in range(5)]  # 3 + 2
        futs += [batches.submit(scheduler, "b", 7)]
        futs[1].cancel()  # a viewer that left: dropped from its batch, the batch goes on
        gate.set()
        results = [f.result(TIMEOUT_S) for i, f in enumerate(futs) if i != 1]
    assert results == [0, 20, 30, 40, 70]
    assert sorted(map(sorted, runs)) == [[0, 2], [3, 4], [7]]
    c = batches.counters
    assert (c.batches, c.items, c.largest) == (3, 5, 2)


def test_unloaded_renders_start_at_once_alone():
    batches = ViewBatches(lambda items: list(items), max_views=8)
    scheduler = RenderScheduler(render_threads=1)
    try:
        for i in range(3):  # each finishes before the next is submitted
            assert batches.submit(scheduler, "k", i).result(TIMEOUT_S) == i
    finally:
        scheduler.shutdown()
    assert (batches.counters.batches, batches.counters.largest) == (3, 1)


def test_a_failing_batch_fails_each_item_and_a_shut_down_one_cancels_them():
    def boom(items):
        raise RuntimeError("render failed")

    batches = ViewBatches(boom, max_views=4)
    with blocked_scheduler() as (scheduler, gate):
        futs = [batches.submit(scheduler, "k", i) for i in range(2)]
        gate.set()
        for f in futs:
            with pytest.raises(RuntimeError, match="render failed"):
                f.result(TIMEOUT_S)
    batches = ViewBatches(lambda items: list(items), max_views=4)
    scheduler = RenderScheduler(render_threads=1)
    gate, started = threading.Event(), threading.Event()
    scheduler.submit(lambda: (started.set(), gate.wait(TIMEOUT_S)))
    assert started.wait(TIMEOUT_S)
    queued = batches.submit(scheduler, "k", 1)

    def release_once_cancelled():  # shutdown joins the holder: end it after the cancel
        concurrent.futures.wait([queued], TIMEOUT_S)
        gate.set()

    threading.Thread(target=release_once_cancelled, daemon=True).start()
    scheduler.shutdown()  # cancels the batch's queued job
    with pytest.raises(concurrent.futures.CancelledError):
        queued.result(TIMEOUT_S)


def test_a_shut_down_scheduler_refuses_and_leaves_no_open_batch():
    batches = ViewBatches(lambda items: list(items), max_views=4)
    scheduler = RenderScheduler(render_threads=1)
    scheduler.shutdown()
    for _ in range(2):  # the second would join a batch that never runs, were it kept
        with pytest.raises(RuntimeError, match="shut down"):
            batches.submit(scheduler, "k", 1)
    assert batches._open == {}


def test_batch_size_setting():
    if not torch.cuda.is_available():
        assert batch_views(None, "auto") == 1  # cpu kernels: no batching
    assert batch_views(None, "cpu") == 1
    assert batch_views(None, "gsplat") == DEFAULT_BATCH_VIEWS  # posed on the CPU, rendered
    assert batch_views(4, "cpu") == 4
    with pytest.raises(ValueError, match="max_views"):
        ViewBatches(lambda items: items, max_views=0)


# -- the room's frame work ------------------------------------------------------------------

SIZE = 64


@pytest.fixture(scope="module")
def srv(tmp_path_factory):
    with run_server(tmp_path_factory.mktemp("batch"), max_sessions=16, default_width=SIZE,
                    default_height=SIZE, render_batch_views=8, backend="cpu") as running:
        yield running


def _jobs(scene: Scene, yaws, codec="jpeg"):
    req = Request(outputs=["rgb", "depth"], width=SIZE, height=SIZE, background=(0.2, 0.2, 0.2),
                  sh_degree=3, quality=1.0, jpeg_quality=90, codec=codec, max_fps=30)
    seats = tuple(DriveState() for _ in scene.shapes)
    return [FrameJob(seats, View(orbit=Orbit(yaw_deg=y)), req, 90) for y in yaws]


def _on(scheduler: RenderScheduler, scene: Scene, views: int) -> Scene:
    """The server's scene (its frame maker, its setting's batches) on another scheduler."""
    from server.stream.workers import LocalWorkers

    workers = LocalWorkers(scheduler, "cpu", views)
    return Scene(f"{scene.id}:test", scene.shapes, workers, frames=scene.frames,
                 batch_views=workers.views_per_batch)


def test_room_views_are_batched_and_equal_separate_renders(srv):
    room = create_room(srv)

    async def open_room():
        async with join(srv, room["id"], srv.token):
            return live(srv, room["id"]).scene

    server_scene = asyncio.run(open_room())  # the server's own scene, setting applied
    assert server_scene.batches is not None and server_scene.batches.max_views == 8
    yaws = (-50.0, -20.0, 0.0, 15.0, 40.0)
    c = server_scene.frames.counters
    renders, batched = c.renders, c.batched
    with blocked_scheduler() as (scheduler, gate):
        scene = _on(scheduler, server_scene, 8)
        futs = [scene.submit(job) for job in _jobs(scene, yaws)]
        gate.set()
        got = [f.result(TIMEOUT_S) for f in futs]
    # one render_views call for the five views (the performer's own frame may render too)
    assert scene.batches.counters.largest == len(yaws) and c.batched - batched == len(yaws)
    assert c.renders - renders <= 2

    scheduler = RenderScheduler(render_threads=1)
    try:
        alone = _on(scheduler, server_scene, 1)
        assert alone.batches is None
        renders = c.renders
        want = [alone.submit(job).result(TIMEOUT_S) for job in _jobs(alone, yaws)]
    finally:
        scheduler.shutdown()
    assert c.renders - renders == len(yaws)
    for a, b in zip(got, want, strict=True):
        assert (a.codec, a.width, a.height) == (b.codec, b.width, b.height)
        assert a.data == b.data and a.depth == b.depth  # the same pixels, the same bytes
    assert len({f.data for f in got}) == len(yaws)  # distinct views, distinct pictures


def test_batched_raw_views_come_back_unencoded(srv):
    """A WebRTC peer asks for the RGB array (its track encodes it): in a batch too."""
    import dataclasses

    from server.stream.scene import RAW_CODEC

    room = create_room(srv)

    async def open_room():
        async with join(srv, room["id"], srv.token):
            return live(srv, room["id"]).scene

    server_scene = asyncio.run(open_room())
    jobs = [dataclasses.replace(job, raw=True)
            for job in _jobs(server_scene, (-30.0, 0.0, 30.0))]
    with blocked_scheduler() as (scheduler, gate):
        scene = _on(scheduler, server_scene, 8)
        futs = [scene.submit(job) for job in jobs]
        gate.set()
        got = [f.result(TIMEOUT_S) for f in futs]
    assert scene.batches.counters.largest == len(jobs)
    assert all(f.codec == RAW_CODEC and f.data == b"" for f in got)
    assert all(f.rgb is not None and f.rgb.shape == (SIZE, SIZE, 3) for f in got)
    assert len({f.rgb.tobytes() for f in got}) == len(jobs)  # distinct views


def test_viewers_of_distinct_views_stream_with_batching_on(srv):
    room = create_room(srv)
    watch = invite(srv, room["id"], "watch")

    async def run():
        async with join(srv, room["id"], srv.token), contextlib.AsyncExitStack() as stack:
            viewers = [await stack.enter_async_context(join(srv, room["id"], watch["token"]))
                       for _ in range(4)]
            for i, ws in enumerate(viewers):
                await ws.send(encode(View(orbit=Orbit(yaw_deg=-45.0 + 30.0 * i))))
            return [await recv_until(ws, is_type("frame")) for ws in viewers]

    got = asyncio.run(run())
    assert all(f.width == SIZE and f.data for f in got)
    c = live(srv, room["id"]).scene.counters
    # a render may still be under way when the counters are read (a newer view's), so each
    # count is only known to have started
    assert c.renders >= 1 and c.encodes >= 1


def test_render_device_and_one_upload_per_state():
    from server.stream.batching import DeviceCopies, render_device

    assert render_device("cpu") is None and render_device("torch") is None
    assert render_device("gsplat") == torch.device("cuda")
    if not torch.cuda.is_available():
        assert render_device("auto") is None  # posed and rendered on the CPU, as before
    from avatar_core.render.scenes import random_scene

    g = random_scene(5, 0)
    assert DeviceCopies(None).get(1, g) is g
    copies = DeviceCopies(torch.device("meta"), keep=2)  # a device any machine has
    a = copies.get((1,), g)
    assert a.means.device.type == "meta" and a.sh.shape == g.sh.shape
    assert copies.get((1,), g) is a  # one upload per state, shared by its views
    copies.get((2,), g)
    copies.get((3,), g)
    assert copies.get((1,), g) is not a  # the oldest went
