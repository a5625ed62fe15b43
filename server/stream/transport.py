"""How a session talks to its client: a :class:`Transport`, composed into the session.

A session (server/stream/session.py) is the same whatever carries it; the transport carries
its messages both ways and its frames out. :class:`WebSocketTransport` is ``/v1/stream``: every
message and every frame a msgpack message on the socket. The WebRTC transport
(server/webrtc/transport.py) carries messages on a data channel and frames on a video track.
"""

from __future__ import annotations

import time
from typing import Any, Protocol

from fastapi import WebSocket

from protocol import Frame as FrameMessage
from protocol import encode

from .scene import Frame


class Transport(Protocol):
    raw_frames: bool  # frames as RGB arrays (a video track encodes them), not encoded
    renders: bool     # False: the client shows nothing (a WebRTC peer that only publishes)

    async def receive(self) -> bytes | str | None:
        """The client's next message; None once the client has left."""

    async def send(self, data: bytes) -> None:
        """One message to the client."""

    async def deliver(self, frame: Frame, number: int) -> int:
        """Frame number ``number`` to the client; the bytes sent (0 where not known)."""

    async def close(self, code: int, reason: str) -> None:
        """End the client's connection."""


class WebSocketTransport:
    raw_frames = False
    renders = True

    def __init__(self, ws: WebSocket) -> None:
        self.ws = ws
        # (seat position, a voice listener): each waits for the frames sent here (a viewer of
        # the room's mixed voice: server/rooms/voice_mix.py); seats' own voices do not
        self.voices: list[tuple[int, Any]] = []

    async def receive(self) -> bytes | str | None:
        message = await self.ws.receive()
        if message["type"] == "websocket.disconnect":
            return None
        data = message.get("bytes")
        return data if data is not None else message.get("text", "")

    async def send(self, data: bytes) -> None:
        await self.ws.send_bytes(data)

    async def deliver(self, frame: Frame, number: int) -> int:
        data = encode(FrameMessage(seq=frame.seq, frame=number, codec=frame.codec,
                                   width=frame.width, height=frame.height, data=frame.data,
                                   depth=frame.depth, keyframe=frame.keyframe,
                                   timings=frame.timings, preview=frame.preview,
                                   t_capture=frame.captured))
        await self.ws.send_bytes(data)
        now = time.monotonic()
        for position, listener in self.voices:
            if position < len(frame.seat_drives):
                listener.follow_picture(frame.seat_drives[position][1], now)
        return len(data)

    async def close(self, code: int, reason: str) -> None:
        await self.ws.close(code, reason[:120])
