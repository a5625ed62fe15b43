"""One WebSocket in a room: a StreamSession whose drive state is its seat's and whose frames
come from the room's shared frame work.

A performer's ``drive`` and ``image`` go to its seat and wake every participant; a viewer's
get error ``forbidden`` and the session goes on. Everyone has its own view, request, pacing
and send path, so a viewer that stops reading slows only itself.
"""

from __future__ import annotations

import contextlib
import dataclasses
from typing import Any

from protocol import Drive, Image, ProtocolError, encode

from ..renderer import H264Stream, RenderedFrame
from ..session import StreamSession, error_message
from .frames import RoomFrame, RoomFrameJob
from .live import CLOSE_GONE, LiveRoom


class ParticipantRenderer:
    """What a StreamSession needs of its renderer here: the seat's parameter shapes and, for
    H.264, the participant's own encoder (the picture itself is the room's)."""

    def __init__(self, shapes: dict) -> None:
        self.shapes = shapes
        self.h264 = H264Stream()
        self.last_codec: str | None = None

    def close(self) -> None:
        self.h264.close()


class RoomParticipant(StreamSession):
    def __init__(self, ws: Any, live: LiveRoom, role: str, seat_index: int, name: str,
                 **session: Any) -> None:
        self.position = next(i for i, s in enumerate(live.seats) if s.index == seat_index)
        renderer = ParticipantRenderer(live.frames.posers[self.position].shapes)
        super().__init__(ws, renderer, **session)
        self.live = live
        self.role = role
        self.seat_index = seat_index  # performed (watching: whose drive seq frames report)
        self.name = name
        self.share_key = live.frames.share_key
        self.drive = live.seats[self.position].drive
        self._asked: tuple[int, ...] = ()  # seat versions of the newest snapshot submitted

    def wake(self) -> None:
        self._changed()

    def handle(self, msg: Any) -> None:
        if isinstance(msg, (Drive, Image)) and self.role != "perform":
            raise ProtocolError("forbidden", f"a viewer cannot send '{msg.type}': join with "
                                             "a perform invitation to drive a seat",
                                {"type": msg.type, "seq": msg.seq})
        super().handle(msg)

    def _drive_changed(self) -> None:
        self.live.seat_changed()  # this participant included

    def _snapshot(self) -> RoomFrameJob:
        job = super()._snapshot()
        fields = {f.name: getattr(job, f.name) for f in dataclasses.fields(job)}
        return RoomFrameJob(**fields, seats=self.live.snapshot())

    def _submit(self, job: RoomFrameJob):
        r = self.renderer
        self._asked = tuple(d.version for d in job.seats)
        return self.live.frames.submit(self.scheduler, job, r.h264, r.last_codec)

    async def _send_frame(self, f: RenderedFrame) -> None:
        if isinstance(f, RoomFrame) and f.seat_seqs:
            f = dataclasses.replace(f, seq=f.seat_seqs[self.position])
            if f.versions != self._asked:
                self._dirty.set()  # it joined an older render: its own state comes next
        self.renderer.last_codec = f.codec
        await super()._send_frame(f)

    def _release_share(self) -> None:
        """The room's render account outlives a participant (forgotten with the room)."""

    async def close_gone(self, message: str) -> None:
        with contextlib.suppress(Exception):  # the client may be gone already
            await self._send(encode(error_message("gone", message)))
            await self.ws.close(CLOSE_GONE, message[:120])
