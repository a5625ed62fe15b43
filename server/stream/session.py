"""One participant's session: a receiver, a render loop and a control sender, over a Transport.

A session is the same whatever carries it (a WebSocket, or WebRTC's data channel and video
track: server/stream/transport.py) and wherever it is (a plain ``/v1/stream?avatar=`` session
is a private room of one seat; server/rooms/). It performs a seat (its ``drive`` and ``image``
go to the seat and wake every participant) or watches (those get error ``forbidden``); it has
its own view, request, pacing and send path, so a participant that stops reading slows only
itself.

Latest input wins. The receiver applies every message to the session state at once (a drive
merges into the seat's parameters, a view replaces the camera, a request updates the render
settings) and raises a flag; the render loop takes a snapshot of the newest state only, so
inputs that arrive while a frame is being made are coalesced into the next one, never queued.
While the loop waits for its frame-rate cap or its fair share of render time, every state
change wakes it to re-check (a new max_fps applies at once). A frame that fails to render
puts back the last state that rendered, so one bad input never stops the session.
The render loop sends each frame before it renders the next: with at most one frame in the
send path, a slow client gets fewer, fresh frames instead of a growing backlog. Control
messages (errors, pongs, stats, presence) go through a small bounded queue of their own, so
the receiver never waits on the transport.
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import contextlib
import dataclasses
import logging
import statistics
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from pydantic import ValidationError
from starlette.websockets import WebSocketDisconnect

from protocol import (
    PROTOCOL_VERSION,
    Drive,
    Error,
    Hello,
    Image,
    Limits,
    Ping,
    Pong,
    ProtocolError,
    Request,
    Stats,
    Tracked,
    View,
    Voice,
    encode,
)
from protocol.messages import Answers

from ..metrics import ServerMetrics
from .capture_clock import ArrivalClock
from .drive import DriveState, fit_drive
from .encoders import check_request
from .frame_cap import FrameRateCap
from .inbound import InboundDecoder, InboundLimits
from .scene import Frame, FrameJob, Scene
from .scheduler import RenderScheduler
from .tracking import (
    DecodedImage,
    SessionTracker,
    TrackingInputInvalid,
    TrackingUnavailable,
)
from .transport import Transport
from .view_motion import MovingViewCost, ViewMotion

if TYPE_CHECKING:
    from ..rooms.live import LiveRoom

log = logging.getLogger(__name__)

CONTROL_QUEUE = 64        # pending control messages; past it new ones are dropped
RENDER_MS_WINDOW = 50     # frames in the stats median
RATE_NOTICE_S = 1.0       # at most one rate_limited error per this many seconds
SEND_STALL_S = 0.1        # a frame not sent by then: the client stalls, wants no render time


class TokenBucket:
    """``rate`` tokens per second, at most ``burst`` saved up."""

    def __init__(self, rate: float, burst: float | None = None) -> None:
        self.rate = rate
        self.capacity = burst if burst is not None else max(1.0, rate)
        self.tokens = self.capacity
        self.stamp = time.monotonic()

    def take(self) -> bool:
        now = time.monotonic()
        self.tokens = min(self.capacity, self.tokens + (now - self.stamp) * self.rate)
        self.stamp = now
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False


@dataclass
class SessionConfig:
    limits: Limits
    jpeg_quality: int
    jpeg_quality_moving: int
    stats_interval_s: float
    inbound: InboundLimits = InboundLimits()
    moving: MovingViewCost = MovingViewCost()
    frame_burst: int = 1  # frames that may start back to back under max_fps (frame_cap.py)


def error_message(code: str, message: str, answers: dict | None = None) -> Error:
    return Error(code=code, message=message,
                 answers=Answers(**answers) if answers else None)


class Session:
    """One participant of ``live`` (its room's runtime), talking over ``transport``."""

    def __init__(self, transport: Transport, live: LiveRoom, *, role: str, seat_index: int,
                 name: str, tracker: SessionTracker, track_scheduler: RenderScheduler,
                 metrics: ServerMetrics, config: SessionConfig, request: Request, view: View,
                 session_count: Callable[[], int]) -> None:
        self.id = uuid.uuid4().hex[:12]
        self.transport = transport
        self.live = live
        self.scene = live.scene
        self.role = role
        self.seat_index = seat_index  # performed (watching: whose drive seq frames report)
        self.name = name
        self.position = next(i for i, s in enumerate(live.seats) if s.index == seat_index)
        self.shapes = self.scene.shapes[self.position]
        self.drive: DriveState = live.seats[self.position].drive  # the seat's, shared
        self.capture_clock = ArrivalClock()  # this performer's t_capture on the server's clock
        self.share_key = self.scene.share_key  # whose render time this is: the scene's
        self.track_scheduler = track_scheduler
        self.metrics = metrics
        self.config = config
        self.limits = config.limits
        self.request = request
        self.view = view
        self.motion = ViewMotion(config.moving.settle_s)  # moving views render previews
        self.motion.update(view, time.monotonic())
        self._preview_shown = False  # the last frame sent was a preview: a full one follows
        self.session_count = session_count  # () -> int, for stats
        self.bucket = TokenBucket(self.limits.max_messages_per_s)
        self.frame_cap = FrameRateCap(config.frame_burst)  # max_fps as a rate
        self._rate_noticed = -RATE_NOTICE_S  # when the client was last told it is too fast
        self._rate_dropped = 0
        self.inbound = InboundDecoder(self.limits, config.inbound)
        self._dirty = asyncio.Event()
        self._dirty.set()  # the first frame shows the seats as they are
        self._wake = asyncio.Event()  # any state change: the pacing wait re-checks
        self._good: FrameJob | None = None  # the newest state that rendered
        self._asked: tuple[int, ...] = ()  # seat versions of the newest snapshot submitted
        self._last_codec: str | None = None  # of the last frame sent
        self._control: asyncio.Queue = asyncio.Queue(CONTROL_QUEUE)
        self._send_lock = asyncio.Lock()
        self._inflight = None  # concurrent future of the render running now
        self.stalled = False  # its client is not taking the frame being sent
        # counters
        self.frames = 0
        self.dropped = 0
        self.coalesced = 0
        self.bytes_sent = 0
        self._pending_inputs = 1  # inputs waiting for a frame (the initial one)
        self._pending_drives = 0
        self._render_ms: collections.deque[float] = collections.deque(maxlen=RENDER_MS_WINDOW)
        # webcam tracking: the newest image waiting (latest wins) and the tracking time of the
        # newest tracked one, reported with the next frame
        self.tracking = tracker
        self._image: tuple[Image | DecodedImage, float] | None = None
        self._image_ready = asyncio.Event()
        self._track_inflight = None
        self._tracking_at: float | None = None  # arrival of the image being tracked
        self._track_ms = 0.0
        self.closed = asyncio.Event()

    # -- sending -----------------------------------------------------------------------------

    async def send(self, data: bytes) -> None:
        async with self._send_lock:
            await self.transport.send(data)

    def send_control(self, message: Any) -> None:
        """Queue a control message; dropped (and counted) if the client is that far behind."""
        if isinstance(message, Error):
            self.metrics.errors.labels(message.code).inc()
        with contextlib.suppress(asyncio.QueueFull):
            self._control.put_nowait(encode(message))

    def send_error(self, code: str, message: str, answers: dict | None = None) -> None:
        self.send_control(error_message(code, message, answers))

    async def _control_sender(self) -> None:
        while True:
            data = await self._control.get()
            await self.send(data)

    async def close_with(self, code: str, message: str, close_code: int) -> None:
        """Tell the client why (an ``error``), then close its connection."""
        with contextlib.suppress(Exception):  # the client may be gone already
            await self.send(encode(error_message(code, message)))
            await self.transport.close(close_code, message)

    # -- receiving ---------------------------------------------------------------------------

    async def _receiver(self) -> None:
        while True:
            data = await self.transport.receive()
            if data is None:
                return
            if not isinstance(data, bytes):
                self.send_error("bad_message", "messages are binary msgpack frames, not text")
                continue
            if not self.bucket.take():
                self._rate_limited(time.monotonic())
                continue
            try:
                msg = await self.inbound.decode(data)  # bounded; large ones off the loop
                self.metrics.messages.labels(msg.type).inc()
                self.handle(msg)
            except ProtocolError as exc:
                self.metrics.messages.labels("invalid").inc()
                self.send_error(exc.code, exc.message, exc.answers)

    def _rate_limited(self, now: float) -> None:
        """Drop the message; tell the client at most once per RATE_NOTICE_S, so that a flood
        costs the server a counter, not an error message per message."""
        self.metrics.messages.labels("rate_limited").inc()
        self._rate_dropped += 1
        if now - self._rate_noticed < RATE_NOTICE_S:
            return
        self.send_error("rate_limited", f"more than {self.limits.max_messages_per_s:g} "
                                        f"messages per second: {self._rate_dropped} dropped "
                                        f"since the last notice")
        self._rate_noticed, self._rate_dropped = now, 0

    def handle(self, msg: Any) -> None:
        """Apply one decoded client message to the session state (never blocks)."""
        if isinstance(msg, (Drive, Image, Voice)) and self.role != "perform":
            raise ProtocolError("forbidden", f"a viewer cannot send '{msg.type}': join with "
                                             "a perform invitation to drive a seat",
                                {"type": msg.type, "seq": msg.seq})
        if isinstance(msg, Drive):
            fitted = fit_drive(msg, self.shapes)  # ProtocolError before anything changes
            self.drive.apply(msg, fitted, self.capture_clock)
            self._pending_drives += 1
            self._drive_changed()
        elif isinstance(msg, View):
            self.view = msg
            self.motion.update(msg, time.monotonic())
            self._changed()
        elif isinstance(msg, Request):
            self.request = self.merged_request(self.request, msg, self.limits)
            self._changed()
        elif isinstance(msg, Ping):
            self.send_control(Pong(t=msg.t))
        elif isinstance(msg, Voice):
            self.live.voice(self, msg)  # checked, counted, forwarded (server/rooms/voice.py)
        elif isinstance(msg, Image):
            if self.tracking.unavailable:
                raise ProtocolError("unsupported", self.tracking.unavailable,
                                    {"type": "image", "seq": msg.seq})
            self.offer_image(msg, time.monotonic())
        elif isinstance(msg, Hello):
            if msg.version != PROTOCOL_VERSION:
                raise ProtocolError("version", f"this server speaks protocol version "
                                               f"{PROTOCOL_VERSION}, not {msg.version}",
                                    {"type": "hello", "seq": None})

    @property
    def input_arrived(self) -> float | None:
        """When the newest input of this performer's seat arrived (monotonic): a webcam image
        waiting or being tracked counts from its arrival (the drive it becomes is that
        instant's: server/rooms/voice.py holds the voice for its frame), else the drive's."""
        times = [t for t in (self.drive.arrived, self._tracking_at,
                             self._image[1] if self._image is not None else None)
                 if t is not None]
        return max(times, default=None)

    @property
    def tracking_input(self) -> bool:
        """Is an image of this performer waiting or being tracked (its drive yet to come)?"""
        return self._tracking_at is not None or self._image is not None

    def offer_image(self, image: Image | DecodedImage, received_at: float) -> None:
        """The newest webcam image to track; it supersedes one not yet tracking."""
        self._image = (image, received_at)
        self._image_ready.set()

    @staticmethod
    def merged_request(current: Request, update: Request, limits: Limits) -> Request:
        fields = update.model_dump(exclude_none=True, exclude={"type"})
        merged = current.model_copy(update=fields)
        check_request(merged)  # what the codec can give
        if merged.max_fps > limits.max_fps:
            merged = merged.model_copy(update={"max_fps": limits.max_fps})
        return merged

    def wake(self) -> None:
        """A seat changed (this participant's or another's): render the new state."""
        self._changed()

    def _changed(self) -> None:
        self._pending_inputs += 1
        self._dirty.set()
        self._wake.set()

    def _drive_changed(self) -> None:
        """The seat's drive changed (a drive, a tracked image): everyone in the room renders."""
        self.live.seat_changed()  # this participant included

    # -- rendering ---------------------------------------------------------------------------

    def _snapshot(self) -> FrameJob:
        req = self.request
        quality = req.jpeg_quality
        cost = self.config.moving
        moving = self.motion.moving(time.monotonic())
        if moving:
            quality = min(quality, self.config.jpeg_quality_moving)
        preview = moving and cost.cheaper
        if preview and cost.quality < req.quality:
            req = req.model_copy(update={"quality": cost.quality})
        # Every input since the last frame but one lost its own frame; likewise for drives.
        self.dropped += max(0, self._pending_inputs - 1)
        self.metrics.dropped.inc(max(0, self._pending_inputs - 1))
        self.coalesced += max(0, self._pending_drives - 1)
        self.metrics.coalesced.inc(max(0, self._pending_drives - 1))
        self._pending_inputs = self._pending_drives = 0
        track_ms, self._track_ms = self._track_ms, 0.0
        return FrameJob(self.live.snapshot(), self.view, req, quality, participant=self.id,
                        previous_codec=self._last_codec, track_ms=track_ms,
                        raw=self.transport.raw_frames, preview=preview,
                        render_scale=cost.render_scale if preview else 1.0)

    def _next_frame_at(self) -> float:
        """When the next frame may start: the frame-rate cap and the fair share of render
        time, both read now (a request or another session may have changed them)."""
        now = asyncio.get_running_loop().time()  # time.monotonic, as the scheduler's
        return max(self.frame_cap.earliest(self.request.max_fps),
                   now + self.scene.workers.pace_s(self.share_key))

    async def _pace(self) -> None:
        """Wait until the next frame may start; inputs keep coalescing meanwhile."""
        loop = asyncio.get_running_loop()
        while (delay := self._next_frame_at() - loop.time()) > 0:
            self._wake.clear()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._wake.wait(), delay)

    async def _render_loop(self) -> None:
        if not self.transport.renders:
            await asyncio.get_running_loop().create_future()  # until the session ends
        while True:
            await self._until_dirty()
            await self._pace()
            self._dirty.clear()
            job = self._snapshot()
            self.frame_cap.started(asyncio.get_running_loop().time(), self.request.max_fps)
            self._asked = job.versions
            future = self.scene.submit(job)
            self._inflight = future  # kept after a cancel: teardown waits for it to finish
            try:
                frame = await asyncio.wrap_future(future)
            except ValueError as exc:  # parameters the model refused (ParameterError)
                self._restore(job, drive_only=True)
                self.send_error("invalid", f"cannot pose these parameters: {exc}; the session "
                                           "keeps its last parameters that rendered",
                                {"type": "drive", "seq": job.seats[self.position].seq})
                continue
            except Exception as exc:  # noqa: BLE001 - the session goes on
                log.exception("render failed in session %s", self.id)
                self._restore(job, drive_only=False)
                self.send_error("internal", f"rendering failed: {type(exc).__name__}; the "
                                            "session keeps its last state that rendered")
                continue
            self._good = job
            await self._send_watched(frame)

    async def _until_dirty(self) -> None:
        """Until there is something new to render; after a preview, also until the view has
        been still for the settle time (its full-quality frame, even if nothing changed)."""
        loop = asyncio.get_running_loop()
        while not self._dirty.is_set():
            if not self._preview_shown:
                await self._dirty.wait()
                return
            delay = self.motion.still_at() - loop.time()  # loop.time() is time.monotonic()
            if delay <= 0:
                self._dirty.set()
                return
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._dirty.wait(), delay)

    def _restore(self, failed: FrameJob, drive_only: bool) -> None:
        """Put back the last state that rendered wherever the failed frame's state is still
        current (newer inputs stay: they get their own try)."""
        good = self._good
        seat = self.position
        self.drive.restore(failed.seats[seat],
                           good.seats[seat] if good is not None else DriveState())
        if good is None or drive_only:
            return
        if self.view is failed.view:
            self.view = good.view
        if self.request is failed.request:
            self.request = good.request

    async def _track_loop(self) -> None:
        """Track the newest image, one at a time, off the event loop; its fit drives."""
        while True:
            await self._image_ready.wait()
            self._image_ready.clear()
            pending, self._image = self._image, None
            if pending is None:
                continue
            image, received_at = pending
            self._tracking_at = received_at
            try:
                await self._track_one(image, received_at)
            finally:
                self._tracking_at = None

    async def _track_one(self, image: Image | DecodedImage, received_at: float) -> None:
        """Track one image; its fit drives the seat (or the client hears why not)."""
        answers = {"type": "image", "seq": image.seq}
        future = self.track_scheduler.submit(self.tracking.process, image, received_at,
                                             key=self.id)
        self._track_inflight = future
        try:
            tracked = await asyncio.wrap_future(future)
            # the image's capture time: its frames carry it, its seat's voice waits for them
            drive = Drive.model_validate({"seq": tracked.seq, "smplx": tracked.params,
                                          "t_capture": tracked.t_capture},
                                         context={"limits": self.limits})
            # arrived as the image came: the picture's lag counts tracking too
            self.drive.apply(drive, fit_drive(drive, self.shapes), self.capture_clock,
                             arrived=received_at)
        except TrackingUnavailable as exc:
            self.send_error("unsupported", str(exc), answers)
            return
        except (TrackingInputInvalid, ProtocolError, ValidationError) as exc:
            self.send_error("invalid", f"cannot track this image: {exc}", answers)
            return
        except Exception as exc:  # noqa: BLE001 - the session goes on
            log.exception("tracking failed in session %s", self.id)
            self.send_error("internal", f"tracking failed: {type(exc).__name__}", answers)
            return
        self._track_ms = tracked.track_ms
        # Found or not, the client hears it: a page says "no person found" instead of
        # waiting for frames that an unchanged (held) pose never brings.
        self.send_control(Tracked(seq=tracked.seq, found=any(tracked.seen.values()),
                                  seen=tracked.seen))
        self._pending_drives += 1
        self._drive_changed()

    async def _send_watched(self, frame: Frame) -> None:
        """Send a frame; while its client does not take it, the session leaves the render
        time to the others (it is not counted among the active sessions)."""
        send = asyncio.create_task(self._send_frame(frame))
        try:
            done, _ = await asyncio.wait({send}, timeout=SEND_STALL_S)
            if not done:
                self.stalled = True
                self.scene.workers.stalled(self.share_key)
            await send
        finally:
            self.stalled = False
            send.cancel()  # the session ends: the send goes with it

    async def _send_frame(self, f: Frame) -> None:
        if f.seat_seqs:
            f = dataclasses.replace(f, seq=f.seat_seqs[self.position],
                                    captured=f.seat_drives[self.position][0]
                                    if f.seat_drives else None)
        if f.versions != self._asked:
            self._dirty.set()  # it joined an older render: its own state comes next
        self._last_codec = f.codec
        self._preview_shown = f.preview
        async with self._send_lock:  # one message at a time on the transport
            sent = await self.transport.deliver(f, self.frames)
        self.frames += 1
        self.bytes_sent += sent
        self._render_ms.append(f.timings.render)
        m = self.metrics
        m.frames.labels(f.codec).inc()
        m.bytes_sent.inc(sent)
        for stage in ("pose", "render", "encode"):
            m.stage_ms.labels(stage).observe(getattr(f.timings, stage))

    # -- the room's avatars reloaded -----------------------------------------------------------

    def render_work(self) -> concurrent.futures.Future | None:
        """The render this session's frame in flight follows, while a thread works on it."""
        work = getattr(self._inflight, "work", self._inflight)
        return work if work is not None and not work.done() else None

    def switch_scene(self, scene: Scene, tracker: SessionTracker | None,
                     sh_degree: tuple[int, int] | None = None) -> None:
        """The room's scene was reopened with a replaced avatar: frames come from ``scene``
        from the next one on (one in flight on the old scene still arrives); ``tracker``
        (None: the old one stays) fits webcam images on the new avatar; ``sh_degree`` (old,
        new): a request at the old avatar's full SH degree moves to the new one's."""
        if sh_degree is not None and self.request.sh_degree == sh_degree[0]:
            self.request = self.request.model_copy(update={"sh_degree": sh_degree[1]})
        self.scene = scene
        self.shapes = scene.shapes[self.position]
        self.share_key = scene.share_key
        self._last_codec = None  # the encoders' state stayed with the old scene
        if tracker is not None:
            old, self.tracking = self.tracking, tracker
            pending = self._track_inflight
            if pending is None or pending.done():
                old.close()
            else:  # a tracking job still uses it
                pending.add_done_callback(lambda _: old.close())
        self._changed()

    # -- stats ---------------------------------------------------------------------------------

    async def _stats_loop(self) -> None:
        interval = self.config.stats_interval_s
        frames, sent, stamp = self.frames, self.bytes_sent, time.monotonic()
        while True:
            await asyncio.sleep(interval)
            now = time.monotonic()
            dt = max(now - stamp, 1e-6)
            self.send_control(Stats(
                fps=(self.frames - frames) / dt, frames=self.frames, dropped=self.dropped,
                coalesced=self.coalesced, bytes_per_s=(self.bytes_sent - sent) / dt,
                render_ms=statistics.median(self._render_ms) if self._render_ms else 0.0,
                sessions=self.session_count()))
            frames, sent, stamp = self.frames, self.bytes_sent, now

    # -- lifetime ------------------------------------------------------------------------------

    async def run(self) -> None:
        """Until the client leaves (or the transport fails); then everything is torn down."""
        tasks = [asyncio.create_task(coro, name=f"{self.id}:{coro.__name__}") for coro in (
            self._receiver(), self._render_loop(), self._control_sender(), self._stats_loop(),
            self._track_loop())]
        try:
            done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
            for task in done:
                exc = task.exception()
                if exc is not None and not isinstance(exc, (WebSocketDisconnect, OSError,
                                                            RuntimeError)):
                    log.error("session %s: %s failed: %r", self.id, task.get_name(), exc)
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            self.track_scheduler.forget(self.id)
            self.closed.set()

    def after_work(self, fn: Callable[[], Any]) -> None:
        """``fn()`` once no thread works for this session any more (a running render or
        tracking job finishes first; a queued one was cancelled with its task)."""
        # a frame's own future is done when cancelled; the render it follows (``work``) is
        # done when no thread works on it any more
        pending = [f for f in (getattr(self._inflight, "work", self._inflight),
                               self._track_inflight) if f is not None and not f.done()]
        if not pending:
            fn()
            return
        left = [len(pending)]

        def one_done(_: Any) -> None:
            left[0] -= 1
            if not left[0]:
                fn()

        for future in pending:
            future.add_done_callback(one_done)

    def release(self) -> None:
        """Free what the session held: its tracker and its encoders' state (once no thread
        uses them)."""
        def free() -> None:
            self.tracking.close()
            self.scene.release(self.id)

        self.after_work(free)
