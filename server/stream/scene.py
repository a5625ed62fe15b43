"""A scene's frame work: one pose per seat per drive update, one render per distinct (seat
versions, view, request), one encode per render, all seats in one ``render_views`` call.

A scene is what a room shows (a plain session is a room of one seat and one participant).
:class:`SceneFrames` makes frames, on a render thread or on a render worker: a seat's world
Gaussians (placement applied) are cached per drive version under the seat's lock.
:class:`Scene` shares them between participants, on the event loop's side: a frame's
concurrent future is kept under its key, so a second participant asking the same picture gets
the same future (or the finished frame) instead of a render of its own. While the performer
drives, participants snapshot at slightly different moments and so at different versions: one
asking while a render of its group (same view and request) is in flight joins that render
instead of starting another, and asks again once it has it (``Frame.versions`` tells it the
frame is older than its snapshot). So a group has at most one render in flight, and the
newest state is always rendered next. Whether a participant's encoded frame may be shared at
all is the encoders' to say (:meth:`FrameEncoders.output_key`). Where a frame is made is the
scene's workers' to decide (server/stream/workers.py: the local render threads, or a render
worker on Ray).

A frame's cost is bounded before it is made: every render asks for at most
``max_tile_pairs`` (Gaussian, tile) pairs (the server setting; avatar_core/render/cost.py),
past which the rasterizer drops the least important splats, so no avatar can make one frame
take seconds and gigabytes. A frame nobody waits for any more is abandoned: each participant
follows the shared render through a future of its own, and when the last of them is
cancelled (its session left) the render is cancelled too, which drops it if it is still
queued and otherwise makes it stop at its next stage boundary (before posing, before
rendering, before each encode: :func:`~.scheduler.abandoned`). The flag lives with the
shared render, not with a participant: a render another participant still waits for goes on.
Abandoning is local to this process (a render worker on Ray finishes what it started).
"""

from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
import functools
import threading
import time
from collections.abc import Hashable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from avatar_core.body.models import MANOModel
from avatar_core.gaussians.animate import AvatarAnimator
from avatar_core.gaussians.placement import place, placed_point, seat_transform, union
from avatar_core.render.camera import Camera, orbit
from avatar_core.render.camera_path import framing_target
from avatar_core.render.types import GaussianSet, RenderOutput, RenderRequest, to_uint8
from avatar_core.render.views import render_views
from protocol import Request, Timings, View

from .batching import DeviceCopies, ViewBatches, render_device
from .drive import DriveState, drive_shapes
from .encoders import FrameEncoders, frame_rgb
from .scheduler import abandoned

if TYPE_CHECKING:
    from .workers import FrameWorkers

RAW_CODEC = "raw"  # a frame's codec when the job asked for the RGB array itself
POSED_VERSIONS = 2  # per seat: the version being rendered and the one before


@dataclass(frozen=True)
class FrameJob:
    """What one participant's frame shows: every seat's drive state, from its view, as its
    request asks."""

    seats: tuple[DriveState, ...]
    view: View
    request: Request                  # effective: every field set
    jpeg_quality: int                 # already lowered when the view moves
    participant: Hashable = None      # whose frame (encoders keep per-participant state)
    previous_codec: str | None = None  # the codec of the participant's last frame
    track_ms: float = 0.0             # tracking time of the webcam image it first shows
    raw: bool = False                 # the RGB array itself, not encoded (a WebRTC track)
    preview: bool = False             # a moving view's cheaper frame (server/stream/view_motion.py)
    render_scale: float = 1.0         # rendered at this fraction of the size, upscaled back

    @property
    def versions(self) -> tuple[int, ...]:
        return tuple(d.version for d in self.seats)

    @functools.cached_property  # asked by the scene on the loop, again by the render thread
    def group(self) -> Hashable:
        """What picture this is, whatever the drive state: jobs of one group differ only in
        the state they show (one render of a group in flight; one WebRTC video stream)."""
        owner = FrameEncoders.output_key(self.participant, self.request)
        return (self.view.model_dump_json(exclude={"moving"}), self.request.model_dump_json(),
                self.jpeg_quality, owner, self.raw, self.render_scale)


@dataclass
class Frame:
    seq: int                          # the first seat's drive seq (a participant: its seat's)
    codec: str
    width: int
    height: int
    data: bytes
    depth: bytes | None
    keyframe: bool
    timings: Timings
    seat_seqs: tuple[int, ...] = ()   # each seat's newest drive seq
    captured: float | None = None     # t_capture of the drive ``seq`` names
    versions: tuple[int, ...] = ()    # each seat's drive version this frame shows
    rgb: np.ndarray | None = None     # [H, W, 3] uint8, raw frames only
    preview: bool = False             # rendered cheaper while its view moves
    # each seat's (t_capture, server arrival, capture instant on the server's clock) of the
    # drive shown: the one clock (voice sync, the WebRTC senders' timestamps)
    seat_drives: tuple[tuple[float | None, float | None, float | None], ...] = ()
    group: Hashable = None            # its job's group (FrameJob.group): the picture it is


@dataclass
class FrameCounters:
    """What the scene did, for tests and benchmarks: shared work shows as fewer of these than
    participants x frames."""

    poses: int = 0           # seat posings (one per seat per drive version)
    renders: int = 0         # render_views calls (all seats in one)
    encodes: int = 0         # encoded images
    shared: int = 0          # frames a participant got from another's render
    batched: int = 0         # renders that shared a render_views call with other views
    abandoned: int = 0       # frames stopped at a stage boundary: nobody waited any more
    cost_degraded: int = 0   # renders the pair bound degraded (splats dropped to fit)
    tile_pairs_max: int = 0  # most (Gaussian, tile) pairs one render composited
    pairs_allocated_max: int = 0  # most pairs one render's tile lists held (cpu backend)
    previews: int = 0        # renders of moving views (smaller, upscaled; fewer Gaussians)


class FrameAbandoned(RuntimeError):
    """Everyone waiting for the frame left: it stopped at a stage boundary."""


def view_camera(view: View, width: int, height: int, default_target: np.ndarray) -> Camera:
    """The camera of a view; an orbit without a target looks at ``default_target``."""
    if view.camera is not None:
        c = view.camera
        cam = Camera(np.asarray(c.K), np.asarray(c.R), np.asarray(c.t), c.width, c.height)
        return cam if cam.size == (width, height) else cam.resized(width, height)
    o = view.orbit
    target = default_target if o.target is None else np.asarray(o.target, dtype=np.float64)
    return orbit(target, o.yaw_deg, o.pitch_deg, o.distance, width=width, height=height,
                 fov_y_deg=o.fov_y_deg)


def scaled(size: int, scale: float) -> int:
    """A side of a preview render: ``scale`` of ``size``, at least 16 px (the smallest
    request)."""
    return size if scale >= 1.0 else max(16, round(size * scale))


def upscaled(out: RenderOutput, width: int, height: int) -> RenderOutput:
    """A smaller render brought back to ``width`` x ``height``: colour and alpha bilinear,
    depth nearest (no depth between a surface and the background)."""
    def resize(t: torch.Tensor | None, mode: str) -> torch.Tensor | None:
        if t is None:
            return None
        x = t.unsqueeze(0).unsqueeze(0) if t.ndim == 2 else t.permute(2, 0, 1).unsqueeze(0)
        kw = {"align_corners": False} if mode == "bilinear" else {}
        y = torch.nn.functional.interpolate(x, size=(height, width), mode=mode, **kw)[0]
        return y[0] if t.ndim == 2 else y.permute(1, 2, 0)

    return dataclasses.replace(out, rgb=resize(out.rgb, "bilinear"),
                               alpha=resize(out.alpha, "bilinear"),
                               depth=resize(out.depth, "nearest"))


class SeatPoser:
    """One seat's avatar: its animator (used by one thread at a time, under the lock) and
    its world Gaussians of the newest drive versions posed."""

    def __init__(self, animator: AvatarAnimator, manos: dict[str, MANOModel],
                 placement: Any) -> None:
        self.animator, self.manos = animator, manos
        model = animator.body_model
        self.shapes = drive_shapes(model, manos)
        self.rotation, self.translation = seat_transform(
            placement.rotation, placement.translation, model.dtype, model.device)
        # where an orbit without a target looks: the chest, placed (translation in float64)
        self.chest = placed_point(framing_target(model.joint_template), self.rotation,
                                  np.asarray(placement.translation, dtype=np.float64)
                                  if self.translation is not None else None)
        self._lock = threading.Lock()
        self._worlds: collections.OrderedDict[int, GaussianSet] = collections.OrderedDict()

    def world(self, drive: DriveState, counters: FrameCounters) -> GaussianSet:
        with self._lock:
            world = self._worlds.get(drive.version)
            if world is None:
                params = drive.smplx_params(self.animator.body_model, self.manos)
                posed = self.animator.pose(params)
                world = place(posed.gaussians, self.rotation, self.translation)
                self._worlds[drive.version] = world
                if len(self._worlds) > POSED_VERSIONS:
                    self._worlds.popitem(last=False)
                counters.poses += 1
            return world


class SceneFrames:
    """Makes a scene's frames: pose (once per seat version) -> render_views -> encode. Runs
    where the scene's workers put it: a render thread here, or a render worker on Ray."""

    def __init__(self, posers: list[SeatPoser], backend: str,
                 encoders: FrameEncoders | None = None,
                 max_tile_pairs: int | None = None) -> None:
        self.posers = posers
        self.backend = backend
        self.max_tile_pairs = max_tile_pairs  # per render; None: the rasterizer contract's
        self.encoders = encoders if encoders is not None else FrameEncoders()
        self.counters = FrameCounters()
        self._on_device = DeviceCopies(render_device(backend))  # CUDA: one upload a state
        self._checked: tuple[int, ...] | None = None  # versions whose Gaussians were scanned

    @property
    def chest(self) -> np.ndarray:
        return self.posers[0].chest

    def make_one(self, job: FrameJob) -> Frame:
        """One view: a batch of one (``render_views`` of one camera is ``rasterize``)."""
        return self.make([job])[0]

    def _stage(self) -> None:
        """A stage boundary: stop here when nobody waits for the frame any more."""
        if abandoned():
            self.counters.abandoned += 1
            raise FrameAbandoned("nobody waits for this frame any more")

    def make(self, jobs: list[FrameJob]) -> list[Frame]:
        """Views of one state and request: one posing, one ``render_views`` call, an encode
        each (none for a raw frame); abandoned (:class:`FrameAbandoned`) at the first stage
        boundary after everyone waiting for it left."""
        c = self.counters
        req = jobs[0].request
        self._stage()
        t0 = time.perf_counter()
        with torch.no_grad():
            gaussians = self._on_device.get(jobs[0].versions, union([
                poser.world(drive, c) for poser, drive in zip(self.posers, jobs[0].seats,
                                                              strict=True)]))
            t1 = time.perf_counter()
            self._stage()
            scale = jobs[0].render_scale
            width, height = scaled(req.width, scale), scaled(req.height, scale)
            cams = [view_camera(job.view, width, height, self.chest) for job in jobs]
            outputs = tuple(dict.fromkeys(("rgb", *req.outputs)))
            budget = None if req.quality >= 1.0 else float(req.quality)
            versions = jobs[0].versions
            outs = render_views(gaussians, cams, RenderRequest(
                outputs=outputs, background=tuple(req.background),
                sh_degree=min(req.sh_degree, gaussians.sh_degree), budget=budget,
                backend=self.backend, max_tile_pairs=self.max_tile_pairs),
                check_finite=versions != self._checked)  # once per posed state, not per view
            self._checked = versions
            c.renders += 1
            c.previews += int(jobs[0].preview)
            if scale < 1.0:
                outs = [upscaled(o, req.width, req.height) for o in outs]
            c.batched += len(jobs) if len(jobs) > 1 else 0
            self._count_cost([o.stats for o in outs])
            alpha_asked = "alpha" in req.outputs
            images = [(frame_rgb(o.rgb, req.codec, alpha_asked),
                       None if o.alpha is None else to_uint8(o.alpha),
                       None if o.depth is None else o.depth.cpu().numpy()) for o in outs]
        t2 = time.perf_counter()
        frames = []
        for job, (rgb, alpha, depth) in zip(jobs, images, strict=True):
            self._stage()
            t3 = time.perf_counter()
            if job.raw:  # a WebRTC track encodes it
                codec, data, keyframe, depth_png = RAW_CODEC, b"", True, None
            else:
                out = self.encoders.encode(job.participant, job.previous_codec, rgb, alpha,
                                           depth, req, job.jpeg_quality)
                codec, data, keyframe, depth_png = out.codec, out.data, out.keyframe, out.depth
                c.encodes += 1
            timings = Timings(track=job.track_ms, pose=(t1 - t0) * 1e3,
                              render=(t2 - t1) * 1e3,
                              encode=(time.perf_counter() - t3) * 1e3)
            seqs = tuple(d.seq for d in job.seats)
            frames.append(Frame(seqs[0], codec, req.width, req.height, data, depth_png,
                                keyframe, timings, seat_seqs=seqs, versions=job.versions,
                                rgb=rgb if job.raw else None, preview=job.preview,
                                captured=job.seats[0].captured,
                                seat_drives=tuple((d.captured, d.arrived, d.captured_at)
                                                  for d in job.seats),
                                group=job.group if job.raw else None))
        return frames

    def _count_cost(self, stats: list[dict]) -> None:
        c = self.counters
        for st in stats:
            c.cost_degraded += int(st.get("n_cost_dropped", 0) > 0)
            c.tile_pairs_max = max(c.tile_pairs_max, int(st.get("tile_pairs", 0)))
            c.pairs_allocated_max = max(c.pairs_allocated_max,
                                        int(st.get("pairs_allocated", 0)))

    def release(self, participant: Hashable) -> None:
        self.encoders.release(participant)

    def close(self) -> None:
        self.encoders.close()


class Scene:
    """A scene as its participants see it: frames shared between them, made by ``workers``.

    ``frames`` is the frame maker where frames are made in this process (None where the
    workers make them elsewhere); ``shapes`` each seat's parameter shapes, which drives are
    checked against before any frame is asked."""

    def __init__(self, scene_id: str, shapes: list[dict], workers: FrameWorkers, *,
                 frames: SceneFrames | None = None, max_frames: int = 64,
                 batch_views: int = 1, kind: str = "room") -> None:
        self.id = scene_id
        self.kind = kind
        self.shapes = shapes
        self.workers = workers
        self.frames = frames
        self.share_key = scene_id  # the scene's account at the fair scheduler
        self.max_frames = max_frames  # frames kept for sharing (distinct views at once)
        self.remote: Any = None  # the workers' handle of it (a render worker's scene)
        self.batches = (ViewBatches(frames.make, batch_views)
                        if frames is not None and batch_views > 1 else None)
        self.shared = 0  # frames a participant got from another's render
        self.closed = False
        self._lock = threading.Lock()
        self._frames: collections.OrderedDict[Hashable, _Render] = collections.OrderedDict()
        self._inflight: dict[Hashable, _Render] = {}  # group -> render

    @property
    def counters(self) -> FrameCounters:
        """What this process did for the scene (tests, benchmarks)."""
        counters = self.frames.counters if self.frames is not None else FrameCounters()
        counters.shared = self.shared
        return counters

    def submit(self, job: FrameJob) -> concurrent.futures.Future:
        """The frame of ``job``: shared with every participant asking the same one. The
        future returned is the caller's own: cancelling it leaves a render others still
        wait for alone, and abandons one nobody else waits for (see the module docstring).
        Its ``work`` is the render's own future (done when no thread works on it)."""
        versions, group = job.versions, job.group
        key = (versions, *group)
        with self._lock:
            render = self._frames.get(key)
            if render is None or render.failed:
                render = self._inflight.get(group)  # an older state of this group, rendering
                if render is not None and render.future.done():
                    render = None  # finished: this participant's newer state renders now
            if render is not None and not render.failed:
                self.shared += 1
            else:
                render = _Render(self.workers.run(self, job))
                self._frames[key] = self._inflight[group] = render
                self._evict(versions)
            render.waiting += 1
        return self._follow(render)

    def _follow(self, render: _Render) -> concurrent.futures.Future:
        """A waiter's own future of ``render`` (counted in ``render.waiting`` already)."""
        own = _relay(render.future)
        own.add_done_callback(lambda done: self._left(render, done))
        return own

    def _left(self, render: _Render, own: concurrent.futures.Future) -> None:
        """A waiter's future is done; if it was cancelled and was the last one waiting, the
        render is abandoned: dropped if still queued, else stopped at its next stage."""
        if not own.cancelled():
            return
        with self._lock:
            render.waiting -= 1
            if render.waiting > 0 or render.future.done():
                return
            render.abandoned = True  # nobody joins it any more
        render.future.cancel()

    def _evict(self, versions: tuple[int, ...]) -> None:
        """Finished frames of older drive states go (nobody asks for them again), and the
        oldest past ``max_frames`` (lock held)."""
        for key in [k for k, r in self._frames.items()
                    if k[0] != versions and r.future.done()]:
            del self._frames[key]
        while len(self._frames) > self.max_frames:
            self._frames.popitem(last=False)
        for group in [g for g, r in self._inflight.items() if r.future.done()]:
            del self._inflight[group]

    def release(self, participant: Hashable) -> None:
        """The participant left: what its frames kept (stateful encoders) goes."""
        self.workers.release(self, participant)

    def close(self) -> None:
        """Nobody watches any more: the scene's state goes (here, or on its render worker)."""
        if not self.closed:
            self.closed = True
            self.workers.close(self)


@dataclass(eq=False)
class _Render:
    """One render of a scene and who waits for it (counted under the scene's lock)."""

    future: concurrent.futures.Future
    waiting: int = 0          # participants whose own future follows it, not cancelled
    abandoned: bool = False   # the last of them left: it is cancelled, nobody may join

    @property
    def failed(self) -> bool:
        f = self.future
        return self.abandoned or (f.done() and (f.cancelled() or f.exception() is not None))


def _relay(shared: concurrent.futures.Future) -> concurrent.futures.Future:
    """A future of one's own that follows ``shared``: a participant that leaves cancels its
    own, never the render the others wait for. ``own.work`` is ``shared``."""
    own: concurrent.futures.Future = concurrent.futures.Future()
    own.work = shared  # type: ignore[attr-defined]

    def copy(done: concurrent.futures.Future) -> None:
        if not own.set_running_or_notify_cancel():
            return  # cancelled by its participant
        if done.cancelled():
            own.set_exception(concurrent.futures.CancelledError())
        elif done.exception() is not None:
            own.set_exception(done.exception())
        else:
            own.set_result(done.result())

    shared.add_done_callback(copy)
    return own
