"""The outgoing video: the newest rendered frame, handed to aiortc's encoder when it asks.

The render loop ``deliver``s a frame and waits until the encoder has taken it, so at most one
frame waits here and a slow encoder (or link) means fewer, fresh frames, as on a WebSocket.
``recv`` returns the newest frame; when none arrived for ``repeat_after_s`` (the picture is
still: nothing renders) it repeats the last one, so a late keyframe request or a new receiver
still gets a picture. Timestamps come from a monotonic clock (90 kHz), strictly increasing.
"""

from __future__ import annotations

import asyncio
import contextlib
import time

import av
import numpy as np
from aiortc import MediaStreamTrack
from aiortc.mediastreams import VIDEO_CLOCK_RATE, VIDEO_TIME_BASE, MediaStreamError

REPEAT_AFTER_S = 0.5


class LatestFrameTrack(MediaStreamTrack):
    kind = "video"

    def __init__(self, repeat_after_s: float = REPEAT_AFTER_S) -> None:
        super().__init__()
        self.repeat_after_s = repeat_after_s
        self._pending: tuple[np.ndarray, asyncio.Future] | None = None
        self._new = asyncio.Event()
        self._last: np.ndarray | None = None  # [H, W, 3] uint8, the newest taken
        self._start = time.monotonic()
        self._pts = -1
        self.sent = 0       # distinct frames handed to the encoder
        self.repeated = 0   # repeats of the last one

    async def deliver(self, rgb: np.ndarray) -> None:
        """Offer ``rgb`` ([H, W, 3] uint8); returns once the encoder took it, a newer frame
        replaced it, or the track ended."""
        if self.readyState != "live":
            return
        if self._pending is not None:
            _settle(self._pending[1])  # superseded (latest wins)
        taken = asyncio.get_running_loop().create_future()
        self._pending = (rgb, taken)
        self._new.set()
        await taken

    async def recv(self) -> av.VideoFrame:
        while True:
            if self.readyState != "live":
                raise MediaStreamError
            if self._pending is None:
                timeout = None if self._last is None else self.repeat_after_s
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._new.wait(), timeout)
                self._new.clear()
            if self.readyState != "live":
                raise MediaStreamError
            if self._pending is not None:
                rgb, taken = self._pending
                self._pending = None
                _settle(taken)
                self._last = np.ascontiguousarray(rgb)
                self.sent += 1
                break
            if self._last is not None:
                self.repeated += 1
                break
        # A new frame object each time: the encoder may still hold the one before.
        frame = av.VideoFrame.from_ndarray(self._last, format="rgb24")
        pts = int((time.monotonic() - self._start) * VIDEO_CLOCK_RATE)
        self._pts = max(pts, self._pts + 1)
        frame.pts, frame.time_base = self._pts, VIDEO_TIME_BASE
        return frame

    def stop(self) -> None:
        super().stop()
        if self._pending is not None:
            _settle(self._pending[1])
            self._pending = None
        self._new.set()  # a waiting recv sees the end


def _settle(future: asyncio.Future) -> None:
    if not future.done():
        future.set_result(None)
