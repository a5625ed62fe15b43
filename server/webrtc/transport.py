"""A session's WebRTC transport: messages on the ``telesplat`` data channel, frames on the
video track: the scene's frames to the room's shared stream of the picture (server/webrtc/
fanout.py: one encode for every viewer of it), or, stamped or with ``webrtc_shared_encode``
off, raw RGB arrays that aiortc encodes for this peer alone."""

from __future__ import annotations

import time

from protocol.stamp import stamp as stamp_frame

from ..rooms.voice import Listener
from ..stream.scene import Frame
from .channel import DataChannel
from .fanout import FanoutTrack
from .track import LatestFrameTrack


class WebRTCTransport:
    raw_frames = True

    def __init__(self, channel: DataChannel, track: LatestFrameTrack | FanoutTrack | None,
                 stamp: bool) -> None:
        self.channel = channel
        self.track = track  # None: a WHIP peer that only publishes, and so renders nothing
        self.stamp = stamp  # each frame's drive seq in its top-left corner (latency tests)
        self.voices: list[tuple[int, Listener]] = []  # (seat position, its listener) heard
        self.clock_position = 0  # the seat whose drives' capture instants stamp the video

    @property
    def renders(self) -> bool:
        return self.track is not None

    async def receive(self) -> bytes | str | None:
        return await self.channel.receive()

    async def send(self, data: bytes) -> None:
        await self.channel.send(data)

    def captured_at(self, frame: Frame) -> float | None:
        """The capture instant (server clock) of the drive of its clock's seat ``frame``
        shows: its video's timestamp on the capture clock."""
        drives = frame.seat_drives
        return drives[self.clock_position][2] if self.clock_position < len(drives) else None

    async def deliver(self, frame: Frame, number: int) -> int:
        if isinstance(self.track, FanoutTrack):  # one encode for the picture's viewers
            await self.track.deliver(frame)
        else:
            rgb = frame.rgb  # shared with the room's other raw participants: stamp a copy
            if self.stamp:
                rgb = stamp_frame(rgb.copy(), frame.seq)
            await self.track.deliver(rgb, self.captured_at(frame))
        now = time.monotonic()  # the encoder took it: the voice waits as long as it did
        for position, listener in self.voices:
            if position < len(frame.seat_drives):
                listener.follow_picture(frame.seat_drives[position][1], now)
        return 0  # the encoded size is aiortc's to know (the client's getStats has it)

    async def close(self, code: int, reason: str) -> None:
        """The session ends the peer (its room closed)."""
        self.channel.close(reason or f"closed ({code})")
