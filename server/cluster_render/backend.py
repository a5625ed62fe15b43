"""Frames made on Ray render workers (``render_backend = "ray"``): :class:`RayWorkers`, the
:class:`~server.stream.workers.FrameWorkers` of a gateway whose scenes live on render-worker
actors (server/cluster_render/pool.py). The gateway keeps every scene's state (seats, drive
states, sharing between participants) and relays the frames; a worker poses, renders and
encodes them with the stream's own :class:`~server.stream.scene.SceneFrames`.

Fair share: a scene's render time (the worker's own timings) is accounted per scene with the
same time-based policy as the local render threads, pacing a scene that takes more than its
share of its worker. The serving order cannot apply here: an actor runs its calls first in
first out, so the scene with the least recent render time cannot be served first.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import shutil
import tempfile
from collections.abc import Hashable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..registry import AvatarRecord
from ..rooms.registry import Placement
from ..stream.scene import FrameJob, Scene

if TYPE_CHECKING:
    from ..context import ServerContext
    from .pool import RenderPool


class RayWorkers:
    """Render-worker actors (render_actors of them); this server is the gateway."""

    name = "ray"

    def __init__(self, pool: RenderPool, max_frames: int) -> None:
        self.pool = pool
        self.max_frames = max_frames

    async def start(self) -> None:
        await self.pool.start()

    async def stop(self) -> None:
        await self.pool.stop()

    async def open_scene(self, ctx: ServerContext, room: Any, kind: str) -> Scene:
        """The room's scene on a worker (a broken package fails here, at the join)."""
        seats = tuple([await self._seat(ctx, ctx.registry.get(spec.avatar), spec.placement)
                       for spec in room.seats])

        def audience() -> list:
            return [] if room.live is None else list(room.live.participants)

        scene_id = f"{kind}:{room.id}"
        remote = self.pool.scene(scene_id, seats, audience, kind=kind)
        try:
            await self.pool.open(remote)
        except BaseException:
            self.pool.close(remote)
            raise
        shapes = [await self._shapes(ctx, spec.avatar) for spec in room.seats]
        scene = Scene(scene_id, shapes, self, max_frames=self.max_frames, kind=kind)
        scene.remote = remote
        return scene

    def run(self, scene: Scene, job: FrameJob) -> concurrent.futures.Future:
        return self.pool.submit(scene.remote, job)

    def pace_s(self, share_key: Hashable) -> float:
        return self.pool.pace_s(share_key)

    def stalled(self, share_key: Hashable) -> None:
        self.pool.call_soon(self.pool.stalled, share_key)

    def forget(self, share_key: Hashable) -> None:
        self.pool.call_soon(self.pool.forget, share_key)

    def release(self, scene: Scene, participant: Hashable) -> None:
        self.pool.call_soon(self.pool.release, scene.remote, participant)

    def close(self, scene: Scene) -> None:
        """The scene is gone: freed on its worker (on the gateway's loop)."""
        self.pool.call_soon(self.pool.close, scene.remote)

    def placement(self, ctx: ServerContext) -> dict[str, Any]:
        return self.pool.placement()

    def observe(self, metrics) -> None:
        """The workers' states and losses, for /metrics."""
        for state in ("starting", "ready"):
            metrics.render_workers.labels(state).set(
                sum(w.state == state for w in self.pool.workers))
        metrics.render_workers_lost.set(self.pool.lost)

    async def _shapes(self, ctx: ServerContext, avatar_id: str) -> dict:
        """The parameter shapes drives are checked against here, before any frame is asked
        (the gateway loads the avatar once, shared; it never poses it)."""
        from ..stream.drive import drive_shapes

        animator, manos = await asyncio.to_thread(ctx.session_models, avatar_id)
        return drive_shapes(animator.body_model, manos)

    async def _seat(self, ctx: ServerContext, record: AvatarRecord, placement: Placement):
        from .worker import SeatSource

        package = await asyncio.to_thread(shared_package, ctx, record)
        return SeatSource(record.id, str(package), record.created, placement)


def shared_package(ctx: ServerContext, record: AvatarRecord) -> Path:
    """The avatar's package folder where every worker reaches it: the registry's own when
    cluster_storage is unset (one machine, or data_dir on shared storage), else a copy under
    ``cluster_storage/avatars/<id>-<created>/`` made once (atomically: copied, then renamed)."""
    source = ctx.registry.package_dir(record.id)
    storage = ctx.settings.cluster_storage
    if storage is None:
        return source
    target = Path(storage) / "avatars" / f"{record.id}-{record.created:.6f}"
    if not target.is_dir():
        target.parent.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=".incoming-", dir=target.parent))
        try:
            shutil.copytree(source, staging, dirs_exist_ok=True)
            try:
                staging.rename(target)
            except OSError:
                if not target.is_dir():  # not another gateway's copy, made meanwhile
                    raise
        finally:
            shutil.rmtree(staging, ignore_errors=True)
    return target


def make_frame_workers(settings, registry, scheduler):
    """The FrameWorkers of ``render_backend``: the local render threads, or Ray's workers."""
    if settings.render_backend == "local":
        from ..stream.workers import LocalWorkers

        return LocalWorkers(scheduler, settings.backend, settings.render_batch_views)
    from .pool import RenderPool
    from .worker import WorkerConfig

    config = WorkerConfig(
        backend=settings.backend, threads=max(1, round(settings.render_actor_num_cpus)),
        max_package_bytes=registry.max_package_bytes, npz_limits=registry.npz_limits,
        ranges=registry.ranges, max_streams_per_scene=settings.max_participants_per_room,
        max_tile_pairs=settings.max_tile_pairs)
    return RayWorkers(RenderPool(settings, config), settings.max_participants_per_room)
