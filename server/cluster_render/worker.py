"""A render worker: one Ray actor that holds avatars and makes the frames of the scenes the
gateway placed on it (pose each seat, render, encode), one frame at a time.

A scene is a room or a plain session (a one-seat scene). The gateway sends every frame with
the scene's seats (avatar, package folder on storage this worker reaches, placement), so a
worker that never saw the scene, or a fresh one after a failover, opens it on the spot. The
drive state travels with each frame: nothing here outlives a frame but caches (loaded
avatars, posed seats) and the encoders' per-participant state. A scene's frames are made by the
stream's own :class:`~server.stream.scene.SceneFrames`, as on the local render threads.

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

from ..rooms.registry import Placement
from ..stream.encoders import FrameEncoders
from ..stream.scene import Frame, FrameJob, SceneFrames, SeatPoser
from ..stream.scheduler import limit_threads

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
    max_streams_per_scene: int       # stateful encoder streams kept per scene
    max_tile_pairs: int | None = None  # per render (settings.max_tile_pairs)


@dataclass
class WorkerScene:
    """A scene's frame maker on this worker, and the seats it was made for."""

    seats: tuple[SeatSource, ...]
    frames: SceneFrames


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

    def render(self, scene_id: str, seats: tuple[SeatSource, ...], job: FrameJob) -> Frame:
        started = time.perf_counter()
        try:
            return self._scene(scene_id, seats).frames.make_one(job)
        finally:
            self.frames += 1
            self.busy_s += time.perf_counter() - started

    def release(self, scene_id: str, participant: object) -> None:
        """A participant left: its encoders' state goes."""
        scene = self._scenes.get(scene_id)
        if scene is not None:
            scene.frames.release(participant)

    def close(self, scene_id: str) -> None:
        scene = self._scenes.pop(scene_id, None)
        if scene is not None:
            scene.frames.close()

    def stats(self) -> dict:
        return {"scenes": len(self._scenes), "frames": self.frames, "busy_s": self.busy_s,
                "avatars": len(self._avatars)}

    # -- scenes and avatars ----------------------------------------------------------------------

    def _scene(self, scene_id: str, seats: tuple[SeatSource, ...]) -> WorkerScene:
        scene = self._scenes.get(scene_id)
        if scene is None or scene.seats != seats:
            if scene is not None:
                scene.frames.close()
            posers = [SeatPoser(*self._animator(seat), seat.placement) for seat in seats]
            encoders = FrameEncoders(max_streams=self.config.max_streams_per_scene)
            frames = SceneFrames(posers, self.config.backend, encoders,
                                 max_tile_pairs=self.config.max_tile_pairs)
            scene = self._scenes[scene_id] = WorkerScene(seats, frames)
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
