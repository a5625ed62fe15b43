"""Where sessions and rooms render (``render_backend``): the seam the stream and room code
goes through.

``local``: this process's render threads (server/scheduler.py), exactly the code path of a
server without a cluster. ``ray``: render-worker actors on a Ray cluster; this server is the
gateway that keeps every session's and room's state and relays the frames
(server/cluster_render/pool.py). A backend gives a plain session its renderer and a room its
frame work; both hand frames to the sessions as concurrent futures.
"""

from __future__ import annotations

import asyncio
import shutil
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..registry import AvatarRecord
from ..renderer import SessionRenderer
from ..rooms.frames import RoomFrames, SeatPoser
from ..rooms.registry import Placement, Room

if TYPE_CHECKING:
    from ..context import ServerContext
    from .pool import RenderPool


class LocalRenderBackend:
    """Today's path: a session renders on the render threads, a room's posers live here."""

    name = "local"

    async def start(self) -> None:
        """Nothing to start: the render threads start at the first frame."""

    async def stop(self) -> None:
        """Nothing to stop: the app shuts the render scheduler down."""

    async def session_renderer(self, ctx: ServerContext, record: AvatarRecord
                               ) -> SessionRenderer:
        animator, manos = await asyncio.to_thread(ctx.session_models, record.id)
        return SessionRenderer(animator, manos, backend=ctx.settings.backend)

    async def room_frames(self, ctx: ServerContext, room: Room) -> RoomFrames:
        posers = []
        for spec in room.seats:
            animator, manos = await asyncio.to_thread(ctx.session_models, spec.avatar)
            posers.append(SeatPoser(animator, manos, spec.placement))
        s = ctx.settings
        return RoomFrames(posers, f"room:{room.id}", s.backend,
                          max_frames=s.max_participants_per_room,
                          batch_max_views=s.render_batch_views)

    def observe(self, metrics) -> None:
        """No render workers here."""

    def placement(self, ctx: ServerContext) -> dict[str, Any]:
        s = ctx.settings
        return {"backend": "local", "render_threads": s.render_threads,
                "torch_threads": s.torch_threads, "render_queue": ctx.scheduler.queued}


class RayRenderBackend:
    """Render-worker actors (render_actors of them); this server is the gateway."""

    name = "ray"

    def __init__(self, pool: RenderPool) -> None:
        self.pool = pool

    async def start(self) -> None:
        await self.pool.start()

    async def stop(self) -> None:
        await self.pool.stop()

    async def session_renderer(self, ctx: ServerContext, record: AvatarRecord):
        from .gateway import RaySessionRenderer, new_session_scene_id

        seat = await self._seat(ctx, record, Placement())
        scene = self.pool.scene(new_session_scene_id(), (seat,), audience=tuple,
                                kind="session")
        try:
            await self.pool.open(scene)
        except BaseException:
            self.pool.close(scene)
            raise
        return RaySessionRenderer(self.pool, scene, await self._shapes(ctx, record.id))

    async def room_frames(self, ctx: ServerContext, room: Room) -> RoomFrames:
        from .gateway import RayRoomFrames

        seats = tuple([await self._seat(ctx, ctx.registry.get(spec.avatar), spec.placement)
                       for spec in room.seats])

        def audience() -> list:
            return [] if room.live is None else list(room.live.participants)

        scene = self.pool.scene(f"room:{room.id}", seats, audience, kind="room")
        await self.pool.open(scene)
        shapes = [await self._shapes(ctx, spec.avatar) for spec in room.seats]
        return RayRoomFrames(self.pool, scene, shapes, f"room:{room.id}",
                             ctx.settings.backend, ctx.settings.max_participants_per_room)

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
        from ..drive import drive_shapes

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


def make_render_backend(settings, registry) -> LocalRenderBackend | RayRenderBackend:
    if settings.render_backend == "local":
        return LocalRenderBackend()
    from .pool import RenderPool
    from .worker import WorkerConfig

    config = WorkerConfig(
        backend=settings.backend, threads=max(1, round(settings.render_actor_num_cpus)),
        max_package_bytes=registry.max_package_bytes, npz_limits=registry.npz_limits,
        ranges=registry.ranges, max_h264_per_scene=settings.max_participants_per_room)
    return RayRenderBackend(RenderPool(settings, config))
