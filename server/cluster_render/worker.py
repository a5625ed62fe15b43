"""A render worker: one Ray actor that holds avatars and makes the frames of the scenes the
gateway placed on it (pose each seat, render, encode), one frame at a time.

A scene is a room or a plain session (a one-seat scene). The gateway sends every frame with
the scene's seats (avatar, package folder on storage this worker reaches, placement), so a
worker that never saw the scene, or a fresh one after a failover, opens it on the spot. The
drive state travels with each frame: nothing here outlives a frame but caches (loaded
avatars, posed seats) and the H.264 encoders, which are stateful per client.

Nothing here imports ray: the pool wraps the class with ``ray.remote`` (server/cluster_render/
pool.py), so the class is also usable, and testable, in-process.
"""

from __future__ import annotations

import collections
import os
import time
from dataclasses import dataclass

from avatar_core.body.cache import StageCache
from avatar_core.bounded_npz import NpzLimits
from avatar_core.gaussians.animate import AvatarAnimator
from avatar_core.gaussians.loading import LoadedAvatar, load_avatar, mano_models
from avatar_core.gaussians.validate import GaussianRanges

from ..renderer import H264Stream
from ..rooms.frames import RoomFrame, RoomFrameJob, RoomFrames, SeatPoser
from ..rooms.registry import Placement
from ..scheduler import limit_threads

LOADED_AVATARS = 8  # avatars kept loaded per worker (least recently used goes first)


@dataclass(frozen=True)
class SeatSource:
    """One seat as a worker needs it: which avatar, where its package is, where it stands."""

    avatar: str
    package: str      # the package folder (shared storage on a cluster)
    revision: float   # the record's creation time: a replaced avatar is loaded again
    placement: Placement = Placement()


@dataclass(frozen=True)
class WorkerConfig:
    backend: str                     # rasterizer backend (settings.backend)
    threads: int                     # torch / numba threads of this worker
    max_package_bytes: int
    npz_limits: NpzLimits | None
    ranges: GaussianRanges | None
    max_h264_per_scene: int          # H.264 streams kept per scene (max_participants_per_room)


class WorkerScene(RoomFrames):
    """A scene's frame work on a worker: the room's own code (one rasterize for all seats),
    called directly: the gateway already shares frames between participants."""

    def __init__(self, posers: list[SeatPoser], seats: tuple[SeatSource, ...],
                 config: WorkerConfig) -> None:
        super().__init__(posers, share_key=None, backend=config.backend,
                         max_frames=config.max_h264_per_scene)
        self.seats = seats
        self.max_streams = config.max_h264_per_scene
        self.h264: collections.OrderedDict[int, H264Stream] = collections.OrderedDict()

    def make(self, job: RoomFrameJob, owner: int | None, last_codec: str | None) -> RoomFrame:
        return self._render(job, None if owner is None else self._stream(owner), last_codec)

    def _stream(self, owner: int) -> H264Stream:
        stream = self.h264.pop(owner, None) or H264Stream()
        self.h264[owner] = stream  # most recently used last
        while len(self.h264) > self.max_streams:
            self.h264.popitem(last=False)[1].close()
        return stream

    def close(self) -> None:
        for stream in self.h264.values():
            stream.close()
        self.h264.clear()


class RenderWorker:
    """The actor. Ray runs its calls one at a time (max_concurrency 1): each session has at
    most one frame in flight, so the sessions on a worker take turns frame by frame."""

    def __init__(self, config: WorkerConfig) -> None:
        self.config = config
        limit_threads(config.threads)
        self._avatars: collections.OrderedDict[tuple[str, float], tuple[LoadedAvatar, dict]] = (
            collections.OrderedDict())
        self._scenes: dict[str, WorkerScene] = {}
        self.frames = 0
        self.busy_s = 0.0

    def ping(self) -> dict:
        """Who this worker is (the gateway's placement table shows it)."""
        import socket

        return {"pid": os.getpid(), "host": socket.gethostname()}

    def open(self, scene_id: str, seats: tuple[SeatSource, ...]) -> None:
        """Load the scene's avatars now (a broken package fails the join, not a frame)."""
        self._scene(scene_id, seats)

    def render(self, scene_id: str, seats: tuple[SeatSource, ...], job: RoomFrameJob,
               owner: int | None, last_codec: str | None) -> RoomFrame:
        started = time.perf_counter()
        try:
            return self._scene(scene_id, seats).make(job, owner, last_codec)
        finally:
            self.frames += 1
            self.busy_s += time.perf_counter() - started

    def close(self, scene_id: str) -> None:
        scene = self._scenes.pop(scene_id, None)
        if scene is not None:
            scene.close()

    def stats(self) -> dict:
        return {"scenes": len(self._scenes), "frames": self.frames, "busy_s": self.busy_s,
                "avatars": len(self._avatars)}

    # -- scenes and avatars ----------------------------------------------------------------------

    def _scene(self, scene_id: str, seats: tuple[SeatSource, ...]) -> WorkerScene:
        scene = self._scenes.get(scene_id)
        if scene is None or scene.seats != seats:
            if scene is not None:
                scene.close()
            posers = [SeatPoser(*self._animator(seat), seat.placement) for seat in seats]
            scene = self._scenes[scene_id] = WorkerScene(posers, seats, self.config)
        return scene

    def _animator(self, seat: SeatSource) -> tuple[AvatarAnimator, dict]:
        """A seat's own animator over the avatar's shared, read-only model (as the gateway's
        registry gives a session), and the avatar's MANO models."""
        key = (seat.avatar, seat.revision)
        entry = self._avatars.pop(key, None)
        if entry is None:
            c = self.config
            loaded = load_avatar(seat.package, max_bytes=c.max_package_bytes,
                                 npz_limits=c.npz_limits, ranges=c.ranges)
            entry = (loaded, mano_models(loaded))
        self._avatars[key] = entry
        while len(self._avatars) > LOADED_AVATARS:
            self._avatars.popitem(last=False)
        loaded, manos = entry
        base = loaded.animator
        animator = AvatarAnimator(base.body_model, base.avatar, betas=base.betas,
                                  cache=StageCache(enabled=base.body_model.cache.enabled))
        return animator, manos
