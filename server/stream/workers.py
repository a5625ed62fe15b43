"""Where a scene's frames are made: one interface, two placements (``render_backend``).

``local``: this process's render threads (:class:`LocalWorkers` over the fair
:class:`~.scheduler.RenderScheduler`), where views of one state may also be batched into one
``render_views`` call. ``ray``: render-worker actors on a Ray cluster
(server/cluster_render/backend.py), this server the gateway that keeps every scene's state and
relays the frames. Sessions see only :class:`FrameWorkers`: a scene is opened, its frames run
and are paced by the same time-based fair share, and it is closed, whichever placement it has.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
from collections.abc import Hashable
from typing import TYPE_CHECKING, Any, Protocol

from .batching import batch_views
from .scene import FrameJob, Scene, SceneFrames, SeatPoser
from .scheduler import RenderScheduler

if TYPE_CHECKING:
    from ..context import ServerContext


class FrameWorkers(Protocol):
    """What a session and its scene need of the place where frames are made."""

    name: str

    async def start(self) -> None: ...
    async def stop(self) -> None: ...

    async def open_scene(self, ctx: ServerContext, room: Any, kind: str) -> Scene:
        """The scene of ``room`` (its seats' avatars loaded where frames are made)."""

    def run(self, scene: Scene, job: FrameJob) -> concurrent.futures.Future:
        """The frame of ``job``, on the scene's account."""

    def pace_s(self, share_key: Hashable) -> float:
        """Seconds the account should wait before its next frame (its fair share)."""

    def stalled(self, share_key: Hashable) -> None:
        """The account waits on its client, not on the renderer: its share goes to others."""

    def forget(self, share_key: Hashable) -> None:
        """The account is gone."""

    def release(self, scene: Scene, participant: Hashable) -> None:
        """What the participant's frames kept in the scene (stateful encoders) goes."""

    def close(self, scene: Scene) -> None:
        """The scene is gone."""

    def placement(self, ctx: ServerContext) -> dict[str, Any]: ...
    def observe(self, metrics: Any) -> None: ...


class LocalWorkers:
    """The render threads of this process: frames of every scene on one fair scheduler."""

    name = "local"

    def __init__(self, scheduler: RenderScheduler, backend: str,
                 batch_views_setting: int | None = None) -> None:
        self.scheduler = scheduler
        self.backend = backend
        self.views_per_batch = batch_views(batch_views_setting, backend)

    async def start(self) -> None:
        """Nothing to start: the render threads start at the first frame."""

    async def stop(self) -> None:
        """Nothing to stop: the app shuts the render scheduler down."""

    async def open_scene(self, ctx: ServerContext, room: Any, kind: str) -> Scene:
        posers = []
        for spec in room.seats:
            animator, manos = await asyncio.to_thread(ctx.session_models, spec.avatar)
            posers.append(SeatPoser(animator, manos, spec.placement))
        frames = SceneFrames(posers, self.backend,
                             max_tile_pairs=ctx.settings.max_tile_pairs)
        return Scene(f"{kind}:{room.id}", [p.shapes for p in posers], self, frames=frames,
                     max_frames=ctx.settings.max_participants_per_room,
                     batch_views=self.views_per_batch, kind=kind)

    def run(self, scene: Scene, job: FrameJob) -> concurrent.futures.Future:
        """On the render threads; views of one state and request that wait together share
        one render_views call when batching is on (server/stream/batching.py)."""
        if scene.batches is None:
            return self.scheduler.submit(scene.frames.make_one, job, key=scene.share_key)
        key = (job.versions, job.request.model_dump_json(), job.render_scale)
        return scene.batches.submit(self.scheduler, key, job, share_key=scene.share_key)

    def pace_s(self, share_key: Hashable) -> float:
        return self.scheduler.pace_s(share_key)

    def stalled(self, share_key: Hashable) -> None:
        self.scheduler.stalled(share_key)

    def forget(self, share_key: Hashable) -> None:
        self.scheduler.forget(share_key)

    def release(self, scene: Scene, participant: Hashable) -> None:
        scene.frames.release(participant)

    def close(self, scene: Scene) -> None:
        self.scheduler.forget(scene.share_key)
        scene.frames.close()

    def placement(self, ctx: ServerContext) -> dict[str, Any]:
        return {"backend": "local", "render_threads": self.scheduler.render_threads,
                "torch_threads": self.scheduler.threads_per_render,
                "render_queue": self.scheduler.queued}

    def observe(self, metrics: Any) -> None:
        """No render workers here."""
