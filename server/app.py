"""The FastAPI application: ``create_app(settings)``.

``app.state`` carries one thing, ``ctx`` (the ServerContext: settings, tokens, avatars,
schedulers, metrics, sessions, the job service; in local auth mode ``ctx.local_token`` is the
admin token printed at start-up, the same at every start: data_dir/local_token). Routes reach
it through server/dependencies.py. The demo avatar is registered in the lifespan's start-up; a
warm-up frame (numba compiles its kernels once) renders behind it, the server already up.
With ``cors_origins`` set, CORSMiddleware answers browsers of those origins (preflights
included).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import gc
import logging
import time
from collections.abc import AsyncIterator
from functools import partial
from importlib import import_module
from pathlib import Path

from fastapi import FastAPI
from fastapi.middleware.cors import CORSMiddleware
from fastapi.staticfiles import StaticFiles

from protocol import PROTOCOL_VERSION, View
from protocol.messages import Orbit

from .auth import LOCAL_SUBJECT, SCOPES, Principal, TokenStore, local_admin_token
from .cluster_render import routes as cluster_render
from .cluster_render.backend import make_frame_workers
from .config import Settings
from .context import ServerContext
from .jobs.demo_build import DemoBuild
from .logsafe import install_log_redaction
from .loop_watch import GcWatch, LoopWatch, freeze_survivors
from .metrics import ServerMetrics
from .private import private_dir
from .registry import DEMO_ID, AvatarRecord, AvatarRegistry
from .rooms.registry import Placement, RoomRegistry, SeatSpec
from .rooms.reload import reload_avatar
from .rooms.restart import RESTART_MESSAGE, announce_restart
from .rooms.store import RoomStore, store_path
from .routers import avatars, jobs, motions, rooms, stream, system, webrtc
from .stream.admission import SessionSlots
from .stream.drive import DriveState
from .stream.encoders import select_encoders
from .stream.gate import default_request
from .stream.scene import FrameJob, SceneFrames, SeatPoser
from .stream.scheduler import RenderScheduler

log = logging.getLogger("telesplat.server")

WEB_DIR = Path(__file__).resolve().parent.parent / "client" / "web"  # served, never imported
WARMUP_SIZE = 64
STARTUP_ROOM = "demo"  # the start-up room's name (owner 'local', pinned)


def warm_up(ctx: ServerContext) -> float | None:
    """Render one small frame of the demo avatar (compiles the numba kernels). Seconds taken."""
    try:
        record = ctx.registry.get(DEMO_ID)
    except KeyError:
        return None
    start = time.perf_counter()
    animator, manos = ctx.session_models(record.id)
    frames = SceneFrames([SeatPoser(animator, manos, Placement())], ctx.settings.backend)
    req = default_request(ctx, record).model_copy(
        update={"width": WARMUP_SIZE, "height": WARMUP_SIZE})
    job = FrameJob((DriveState(),), View(orbit=Orbit()), req, ctx.settings.jpeg_quality)
    ctx.scheduler.submit(frames.make_one, job).result()
    frames.close()
    return time.perf_counter() - start


def open_startup_room(ctx: ServerContext) -> None:
    """The demo room (owner 'local', pinned) and new watch and perform links to it, for the
    start-up banner (``ctx.startup_links``). The room is stored: a restart finds it and keeps
    its id, and the links printed before stay valid until they expire (a token is shown only
    once, so each start prints new ones). When the room's valid invitations are at
    ``max_invitations_per_room``, the ones expiring soonest are revoked to make room."""
    try:
        ctx.registry.get(DEMO_ID)
    except KeyError:
        return
    owner = Principal(LOCAL_SUBJECT, frozenset(SCOPES))
    room = next((r for r in ctx.rooms.list(owner) if r.owner == LOCAL_SUBJECT and r.pinned
                 and r.name == STARTUP_ROOM and [s.avatar for s in r.seats] == [DEMO_ID]), None)
    if room is None:
        room = ctx.rooms.create(owner, STARTUP_ROOM, [SeatSpec(0, DEMO_ID)], pinned=True)
    else:
        log.info("start-up room %s found in the store", room.id)
    now = time.time()
    valid = sorted((i for i in room.invitations.values() if i.valid(now)),
                   key=lambda i: i.expires_at)
    for old in valid[:max(0, len(valid) + 2 - ctx.settings.max_invitations_per_room)]:
        ctx.rooms.revoke(room, old.id)
    links = {"room": room.id}
    for scope in ("watch", "perform"):
        invitation, token = ctx.rooms.invite(room, scope, None, None)
        links[scope] = f"/?room={room.id}#token={token}"
    ctx.startup_links = links


def _start(ctx: ServerContext) -> None:
    s = ctx.settings
    chosen = select_encoders(s.encoders)  # probes the GPU encoders once
    log.info("encoders: JPEG %s, H.264 %s", chosen.jpeg, chosen.h264)
    rec = ctx.registry.register_demo(s.demo_avatar, cache=s.demo_cache_dir,
                                     recipe=s.demo_build_recipe)  # never trains here
    if rec is not None:
        log.info("demo avatar %r (%s, %d Gaussians)", rec.id, rec.name, rec.num_gaussians)
    ctx.metrics.avatars.set(len(ctx.registry.list()))
    if s.startup_room:
        open_startup_room(ctx)
    if s.webrtc_max_peers > 0:
        # aiortc and PyAV loaded here, not by the first WHEP/WHIP request on the event loop
        # (a 66 ms stall at the first peer, logged by loop_stall_log_ms; longer when busy)
        import_module("server.webrtc.peer")
    if s.gc_freeze:
        freeze_survivors()


def _warm_up_behind(ctx: ServerContext) -> None:
    """The warm-up frame, while the server already answers: the page shows at once, and a
    first frame asked meanwhile waits for the same kernels (compiled once, under numba's
    lock). Minutes on a fresh clone of a busy machine (docs/benchmarks.md, "First run")."""
    try:
        took = warm_up(ctx)
    except Exception:  # noqa: BLE001 - a session's first frame compiles them instead
        log.exception("the warm-up frame failed")
        return
    finally:
        ctx.warmed.set()
    if took is not None:
        log.info("warm-up frame rendered in %.1f s", took)
    if ctx.settings.gc_freeze:
        freeze_survivors()  # the kernels it compiled


def _reload_demo(ctx: ServerContext, loop: asyncio.AbstractEventLoop,
                 stand_in: AvatarRecord | None) -> None:
    """The trained demo replaced its stand-in: reload it into the live rooms and sessions
    (on the loop; called from the build's thread, which waits until the server stops)."""
    future = asyncio.run_coroutine_threadsafe(reload_avatar(ctx, DEMO_ID, stand_in), loop)
    while not ctx.demo_build.stopping:
        try:
            future.result(timeout=1.0)
            return
        except concurrent.futures.TimeoutError:
            continue
    future.cancel()


async def _sweep_rooms(ctx: ServerContext) -> None:
    """Close rooms left empty for room_idle_timeout_s (checked a few times per timeout)."""
    interval = min(5.0, ctx.settings.room_idle_timeout_s / 4)
    while True:
        await asyncio.sleep(interval)
        rooms.sweep_idle_rooms(ctx)


CORS_METHODS = ("GET", "POST", "DELETE", "PATCH")  # every method a route answers
CORS_HEADERS = ("Authorization", "Content-Type")
CORS_EXPOSED = ("Location", "Link", "ETag")  # WHEP/WHIP's resource, ICE servers, entity tag


def cors_options(settings: Settings) -> dict:
    """CORSMiddleware's arguments: the settings' origins, no credentials mode (tokens travel
    in the Authorization header, never in cookies), the methods and headers of REST and
    WHEP/WHIP, and the headers a WHEP player reads exposed."""
    return {"allow_origins": list(settings.cors_origins), "allow_methods": list(CORS_METHODS),
            "allow_headers": list(CORS_HEADERS), "expose_headers": list(CORS_EXPOSED),
            "allow_credentials": False, "max_age": settings.cors_max_age_s}


def render_scheduler(settings: Settings) -> RenderScheduler:
    """The render threads, shaped by the settings or chosen from the machine (logged)."""
    pool = settings.render_pool()
    level = logging.WARNING if "oversubscribe" in pool.why else logging.INFO
    log.log(level, "render threads: %s", pool)
    return RenderScheduler(pool.workers, pool.per_frame, settings.fair_share,
                           settings.fair_share_window_s, spread=pool.spread)


def create_app(settings: Settings) -> FastAPI:
    install_log_redaction()  # before uvicorn logs a URL with ?token= in it
    private_dir(settings.data_dir)  # 0700: tokens, uploads, avatars and logs live below
    tokens = TokenStore(settings.tokens_path, settings.tokens_reload_interval_s)
    local_token = None
    if settings.auth == "local":  # the same token at every start (data_dir/local_token)
        local_token = local_admin_token(tokens, settings.local_token_path)
    ctx = ServerContext(
        settings=settings, tokens=tokens,
        registry=AvatarRegistry.from_settings(settings),
        scheduler=render_scheduler(settings),
        track_scheduler=RenderScheduler(settings.track_threads, 1),
        metrics=ServerMetrics(), slots=SessionSlots(settings.max_sessions),
        rooms=RoomRegistry(settings, RoomStore(store_path(settings.data_dir))),
        local_token=local_token)
    ctx.render = make_frame_workers(settings, ctx.registry, ctx.scheduler)
    ctx.demo_build = DemoBuild(settings, ctx.registry)

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        await asyncio.to_thread(_start, ctx)
        warming = None
        if settings.warmup and settings.render_backend == "local":  # a worker compiles its own
            warming = asyncio.create_task(asyncio.to_thread(_warm_up_behind, ctx),
                                          name="warm-up")
        else:
            ctx.warmed.set()
        await ctx.render.start()  # render_backend ray: connects, starts the render workers
        sweeper = asyncio.create_task(_sweep_rooms(ctx), name="rooms:sweep")
        loop_watch = LoopWatch(ctx.metrics, settings.loop_lag_interval_s,
                               settings.loop_stall_log_ms)
        loop_watch.start()
        gc_watch = GcWatch.into(ctx.metrics)
        gc_watch.start()
        try:
            async with jobs.lifespan(ctx):  # the training worker
                # the trained demo, when not built yet: its job trains while we serve
                ctx.demo_build.on_replaced = partial(_reload_demo, ctx,
                                                     asyncio.get_running_loop())
                await asyncio.to_thread(ctx.demo_build.start, ctx.jobs)
                try:
                    yield
                finally:
                    await asyncio.to_thread(ctx.demo_build.stop)
        finally:
            sweeper.cancel()
            await loop_watch.stop()
            gc_watch.stop()
            # Whoever is still in (RestartingServer told the rest before uvicorn closed them)
            await announce_restart(ctx, settings.restart_notice_s)
            await ctx.webrtc_peers.close_all(RESTART_MESSAGE)
            await ctx.render.stop()
        if warming is not None:
            await warming  # its frame is on the render threads: before they shut down
        await asyncio.to_thread(ctx.scheduler.shutdown)
        await asyncio.to_thread(ctx.track_scheduler.shutdown)
        if ctx.rooms.store is not None:
            ctx.rooms.store.close()
        if settings.gc_freeze:
            gc.unfreeze()  # what it froze is collectable again in a process that goes on

    app = FastAPI(title="Telesplat", version="0.1.0", lifespan=lifespan,
                  description="Hosts 3D-Gaussian upper-body avatars and drives them live over "
                              f"a WebSocket (protocol version {PROTOCOL_VERSION}).")
    app.state.ctx = ctx
    for routes in (system, avatars, stream, rooms, webrtc, motions, jobs, cluster_render):
        app.include_router(routes.router)
    if settings.cors_origins:  # none by default: no CORS header at all
        app.add_middleware(CORSMiddleware, **cors_options(settings))
    # Last: the browser page at "/" would shadow any route added after it.
    if (WEB_DIR / "index.html").is_file():
        app.mount("/", StaticFiles(directory=WEB_DIR, html=True), name="web")
    return app
