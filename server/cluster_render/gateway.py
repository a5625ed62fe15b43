"""The gateway's side of a scene on a render worker: a room's frame work (the room's own
sharing, frames made remotely) and a plain session's renderer.

Drives are checked here against the seat's parameter shapes, so a bad drive is refused before
any frame is asked; the drive state goes to the worker with each frame.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import uuid
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..renderer import FrameJob, H264Stream
from ..rooms.frames import RoomFrameJob, RoomFrames
from ..scheduler import RenderScheduler
from .pool import RenderPool, Scene

PLAIN_SESSION_H264 = 0  # a plain session's one H.264 stream on its worker


def new_session_scene_id() -> str:
    return f"session:{uuid.uuid4().hex[:12]}"


@dataclass(frozen=True)
class SeatShapes:
    """What a participant needs of its seat here: the parameter shapes (posing is remote)."""

    shapes: dict
    chest: np.ndarray | None = None


class RayRoomFrames(RoomFrames):
    """A room's frames: shared between participants here as with the local backend, each
    distinct frame made on the room's render worker."""

    def __init__(self, pool: RenderPool, scene: Scene, shapes: list[dict], share_key: str,
                 backend: str, max_frames: int) -> None:
        super().__init__([SeatShapes(s) for s in shapes], share_key, backend, max_frames)
        self.pool, self.scene = pool, scene

    def dispatch(self, scheduler: RenderScheduler, job: RoomFrameJob,
                 h264: H264Stream | None, last_codec: str | None) -> concurrent.futures.Future:
        owner = id(h264) if job.request.codec == "h264" else None  # its stream on the worker
        return self.pool.submit(self.scene, job, owner, last_codec)


class RaySessionRenderer:
    """A plain session's renderer: a one-seat scene on a render worker."""

    def __init__(self, pool: RenderPool, scene: Scene, shapes: dict) -> None:
        self.pool, self.scene = pool, scene
        self.shapes = shapes
        self.last_codec: str | None = None
        self._closed = False

    def submit(self, scheduler: RenderScheduler, job: FrameJob, session: Any
               ) -> concurrent.futures.Future:
        """The frame of ``job`` from the worker; the session gets the scene's notices."""
        self.scene.audience = lambda: (session,)
        fields = {f.name: getattr(job, f.name) for f in dataclasses.fields(job)}
        owner = PLAIN_SESSION_H264 if job.request.codec == "h264" else None
        future = self.pool.submit(self.scene, RoomFrameJob(**fields, seats=(job.drive,)),
                                  owner, self.last_codec)
        future.add_done_callback(self._sent)
        return future

    def _sent(self, future: concurrent.futures.Future) -> None:
        if not future.cancelled() and future.exception() is None:
            self.last_codec = future.result().codec  # H.264 back from another: a keyframe

    def close(self) -> None:
        """The session ended: its scene is freed on its worker (on the gateway's loop)."""
        if not self._closed:
            self._closed = True
            self.pool.call_soon(self.pool.close, self.scene)
