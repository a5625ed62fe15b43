"""A room's shared frame work: one pose per seat per drive update, one render per distinct
(seat versions, view, request), one encode per render, all seats in one rasterize call.

Runs on the render threads. A seat's world Gaussians (placement applied) are cached per drive
version under the seat's lock; a frame's concurrent future is kept under its key, so a second
participant asking the same picture gets the same future (or the finished frame) instead of a
render of its own. While the performer drives, participants snapshot at slightly different
moments and so at different versions: one asking while a render of its group (same view and
request) is in flight joins that render instead of starting another, and asks again once it
has it (``RoomFrame.versions`` tells it the frame is older than its snapshot). So a group has
at most one render in flight, and the newest state is always rendered next. H.264 is stateful
per client: such a frame is keyed by its participant. Renders of one state and request from
different views that wait together are batched into one rasterizer call
(:mod:`server.view_batch`, where the backend batches: gsplat).
"""

from __future__ import annotations

import collections
import concurrent.futures
import threading
import time
from collections.abc import Hashable
from dataclasses import dataclass

import numpy as np
import torch

from avatar_core.body.lbs import rodrigues
from avatar_core.body.models import MANOModel
from avatar_core.gaussians.animate import AvatarAnimator
from avatar_core.render.camera_path import framing_target
from avatar_core.render.types import GaussianSet, RenderRequest, to_uint8
from avatar_core.render.views import render_views
from avatar_core.rotations import matrix_to_quaternion, quaternion_multiply
from protocol import Timings

from ..drive import DriveState, drive_shapes
from ..encoders import frame_rgb
from ..renderer import FrameJob, H264Stream, RenderedFrame, encode_outputs, view_camera
from ..scheduler import RenderScheduler
from ..view_batch import DeviceCopies, ViewBatches, batch_views, render_device
from .registry import Placement


@dataclass(frozen=True)
class RoomFrameJob(FrameJob):
    """A participant's frame: its own view and request over every seat's drive state."""

    seats: tuple[DriveState, ...] = ()
    raw: bool = False  # the RGB array itself, not encoded (a WebRTC track encodes it)


@dataclass
class RoomFrame(RenderedFrame):
    seat_seqs: tuple[int, ...] = ()  # each seat's newest drive seq: a participant reports its
    versions: tuple[int, ...] = ()   # each seat's drive version this frame shows
    rgb: np.ndarray | None = None    # [H, W, 3] uint8, raw frames only


@dataclass
class FrameCounters:
    """What the room did, for tests and benchmarks: shared work shows as fewer of these than
    participants x frames."""

    poses: int = 0           # seat posings (one per seat per drive version)
    renders: int = 0         # rasterize calls (all seats in one)
    encodes: int = 0         # encoded images
    shared: int = 0          # frames a participant got from another's render
    batched: int = 0         # renders that shared a rasterizer call with other views


def place(gaussians: GaussianSet, rotation: torch.Tensor | None,
          translation: torch.Tensor | None) -> GaussianSet:
    """Gaussians moved rigidly: means rotated then translated, orientations composed.
    (View-dependent SH colour is not rotated: exact for the DC term.)"""
    if rotation is None and translation is None:
        return gaussians
    means, quats = gaussians.means, gaussians.quats
    if rotation is not None:
        means = means @ rotation.T
        q = matrix_to_quaternion(rotation).expand_as(quats)
        quats = quaternion_multiply(q, quats)
    if translation is not None:
        means = means + translation
    return GaussianSet(means=means, quats=quats, scales=gaussians.scales,
                       opacities=gaussians.opacities, sh=gaussians.sh)


def union(sets: list[GaussianSet]) -> GaussianSet:
    """One set of every seat's Gaussians (SH padded with zeros to the highest degree)."""
    if len(sets) == 1:
        return sets[0]
    bases = max(g.sh.shape[1] for g in sets)
    sh = [g.sh if g.sh.shape[1] == bases else
          torch.nn.functional.pad(g.sh, (0, 0, 0, bases - g.sh.shape[1])) for g in sets]
    return GaussianSet(means=torch.cat([g.means for g in sets]),
                       quats=torch.cat([g.quats for g in sets]),
                       scales=torch.cat([g.scales for g in sets]),
                       opacities=torch.cat([g.opacities for g in sets]), sh=torch.cat(sh))


class SeatPoser:
    """One seat's avatar: its animator (used by one thread at a time, under the lock) and
    its world Gaussians of the newest drive version posed."""

    def __init__(self, animator: AvatarAnimator, manos: dict[str, MANOModel],
                 placement: Placement) -> None:
        self.animator, self.manos = animator, manos
        model = animator.body_model
        self.shapes = drive_shapes(model, manos)
        dtype, device = model.dtype, model.device
        rot = np.asarray(placement.rotation, dtype=np.float64)
        trans = np.asarray(placement.translation, dtype=np.float64)
        self.rotation = (None if not rot.any() else
                         rodrigues(torch.as_tensor(rot, dtype=dtype, device=device)))
        self.translation = (None if not trans.any() else
                            torch.as_tensor(trans, dtype=dtype, device=device))
        chest = np.asarray(framing_target(model.joint_template), dtype=np.float64)
        if self.rotation is not None:
            chest = self.rotation.double().cpu().numpy() @ chest
        self.chest = chest + trans  # where an orbit without a target looks
        self._lock = threading.Lock()
        # The newest versions posed: groups rendering one drive update apart reuse them.
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


RAW_CODEC = "raw"  # a frame's codec when the job asked for the RGB array itself
POSED_VERSIONS = 2  # per seat: the version being rendered and the one before


class RoomFrames:
    def __init__(self, posers: list[SeatPoser], share_key: Hashable, backend: str,
                 max_frames: int, batch_max_views: int | None = None) -> None:
        self.posers = posers
        self.share_key = share_key  # the room's account at the fair scheduler
        self.backend = backend
        self.max_frames = max_frames  # frames kept for sharing (distinct views at once)
        self.counters = FrameCounters()
        self._lock = threading.Lock()
        self._frames: collections.OrderedDict[Hashable, concurrent.futures.Future] = (
            collections.OrderedDict())
        self._inflight: dict[Hashable, concurrent.futures.Future] = {}  # group -> render
        views = batch_views(batch_max_views, backend)
        self._batches = ViewBatches(self._render_views, views) if views > 1 else None
        self._on_device = DeviceCopies(render_device(backend))  # CUDA: one upload a state

    @property
    def chest(self) -> np.ndarray:
        return self.posers[0].chest

    def submit(self, scheduler: RenderScheduler, job: RoomFrameJob,
               h264: H264Stream | None = None, last_codec: str | None = None
               ) -> concurrent.futures.Future:
        """The frame of ``job``: shared with every participant asking the same one. The
        future returned is the caller's own (cancelling it leaves the shared render alone)."""
        versions = tuple(d.version for d in job.seats)
        owner = id(h264) if job.request.codec == "h264" else None
        group = (job.view.model_dump_json(exclude={"moving"}), job.request.model_dump_json(),
                 job.jpeg_quality, owner, job.raw)
        key = (versions, *group)
        with self._lock:
            shared = self._frames.get(key)
            if shared is None or _failed(shared):
                shared = self._inflight.get(group)  # an older state of this group, rendering
                if shared is not None and shared.done():
                    shared = None  # finished: this participant's newer state renders now
            if shared is not None and not _failed(shared):
                self.counters.shared += 1
            else:
                shared = self.dispatch(scheduler, job, h264, last_codec)
                self._frames[key] = self._inflight[group] = shared
                self._evict(versions)
        if owner is not None:
            return shared  # a participant's own H.264 frame: nobody else waits on it
        return _relay(shared)

    def dispatch(self, scheduler: RenderScheduler, job: RoomFrameJob,
                 h264: H264Stream | None, last_codec: str | None) -> concurrent.futures.Future:
        """Where the frame is made: on this server's render threads (render_backend ray makes
        it on a render worker: server/cluster_render/). Views of one state and request that
        wait together share one rasterizer call when batching is on (server/view_batch.py)."""
        if self._batches is None:
            return scheduler.submit(self._render, job, h264, last_codec, key=self.share_key)
        versions = tuple(d.version for d in job.seats)
        return self._batches.submit(scheduler, (versions, job.request.model_dump_json()),
                                    (job, h264, last_codec), share_key=self.share_key)

    def _evict(self, versions: tuple[int, ...]) -> None:
        """Finished frames of older drive states go (nobody asks for them again), and the
        oldest past ``max_frames`` (lock held)."""
        for key in [k for k, f in self._frames.items() if k[0] != versions and f.done()]:
            del self._frames[key]
        while len(self._frames) > self.max_frames:
            self._frames.popitem(last=False)
        for group in [g for g, f in self._inflight.items() if f.done()]:
            del self._inflight[group]

    def _render(self, job: RoomFrameJob, h264: H264Stream | None,
                last_codec: str | None) -> RoomFrame:
        """One view: a batch of one (``render_views`` of one camera is ``rasterize``)."""
        return self._render_views([(job, h264, last_codec)])[0]

    def _render_views(self, items: list[tuple[RoomFrameJob, H264Stream | None, str | None]]
                      ) -> list[RoomFrame]:
        """Views of one state and request (one, or a batch of :class:`ViewBatches`): one
        posing, one ``render_views`` call, an encode each (none for a raw frame)."""
        c = self.counters
        jobs = [job for job, _, _ in items]
        req = jobs[0].request
        t0 = time.perf_counter()
        with torch.no_grad():
            gaussians = self._on_device.get(job_versions(jobs[0]), union([
                poser.world(drive, c) for poser, drive in zip(self.posers, jobs[0].seats,
                                                              strict=True)]))
            t1 = time.perf_counter()
            cams = [view_camera(job.view, req.width, req.height, self.chest) for job in jobs]
            outputs = tuple(dict.fromkeys(("rgb", *req.outputs)))
            budget = None if req.quality >= 1.0 else float(req.quality)
            outs = render_views(gaussians, cams, RenderRequest(
                outputs=outputs, background=tuple(req.background),
                sh_degree=min(req.sh_degree, gaussians.sh_degree), budget=budget,
                backend=self.backend))
            c.renders += 1
            c.batched += len(jobs) if len(jobs) > 1 else 0
            alpha_asked = "alpha" in req.outputs
            images = [(frame_rgb(o.rgb, req.codec, alpha_asked),
                       None if o.alpha is None else to_uint8(o.alpha),
                       None if o.depth is None else o.depth.cpu().numpy()) for o in outs]
        t2 = time.perf_counter()
        frames = []
        for (job, h264, last_codec), cam, (rgb, alpha, depth) in zip(items, cams, images,
                                                                    strict=True):
            t3 = time.perf_counter()

            def own_h264(rgb_: np.ndarray, req_, h264=h264, last_codec=last_codec
                         ) -> tuple[bytes, bool]:
                assert h264 is not None, "an h264 frame is rendered for its own participant"
                return h264.encode(rgb_, req_, last_codec)

            if job.raw:  # a WebRTC track encodes it
                codec, data, keyframe, depth_png = RAW_CODEC, b"", True, None
            else:
                codec, data, keyframe, depth_png = encode_outputs(rgb, alpha, depth, req,
                                                                  job.jpeg_quality, own_h264)
                c.encodes += 1
            timings = Timings(track=job.track_ms, pose=(t1 - t0) * 1e3,
                              render=(t2 - t1) * 1e3,
                              encode=(time.perf_counter() - t3) * 1e3)
            frames.append(RoomFrame(
                job.drive.seq, codec, cam.width, cam.height, data, depth_png, keyframe,
                timings, seat_seqs=tuple(d.seq for d in job.seats),
                versions=tuple(d.version for d in job.seats), rgb=rgb if job.raw else None))
        return frames


def job_versions(job: RoomFrameJob) -> tuple[int, ...]:
    return tuple(d.version for d in job.seats)


def _failed(future: concurrent.futures.Future) -> bool:
    return future.done() and (future.cancelled() or future.exception() is not None)


def _relay(shared: concurrent.futures.Future) -> concurrent.futures.Future:
    """A future of one's own that follows ``shared``: a participant that leaves cancels its
    own, never the render the others wait for."""
    own: concurrent.futures.Future = concurrent.futures.Future()

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
