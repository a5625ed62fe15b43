"""The outgoing video: the newest rendered frame, handed to aiortc's encoder when it asks.

The render loop ``deliver``s a frame and waits until the encoder has taken it, so at most one
frame waits here and a slow encoder (or link) means fewer, fresh frames, as on a WebSocket.
``recv`` returns the newest frame; when none arrived for ``repeat_after_s`` (the picture is
still: nothing renders) it repeats the last one, so a late keyframe request or a new receiver
still gets a picture. Timestamps (90 kHz) are strictly increasing: with a
:class:`~.sender_clock.CaptureEpoch` each frame's is the capture instant of the drive it shows
(a repeat, or a frame of no new drive, the moment of sending less the last picture lag), at
most ``max_lag_s`` before the moment of sending (``webrtc_max_sync_lag_s``: a browser delays
the voice by the picture's lag to lip-sync, and a lag of seconds would silence it), else
the moment the encoder took it (aiortc's clock: ``webrtc_sender_clock = send``).
"""

from __future__ import annotations

import asyncio
import contextlib
import time

import av
import numpy as np
from aiortc import MediaStreamTrack
from aiortc.mediastreams import VIDEO_CLOCK_RATE, VIDEO_TIME_BASE, MediaStreamError

from .sender_clock import CaptureEpoch, CaptureStamps

REPEAT_AFTER_S = 0.5
MAX_LAG_S = 1.0  # the default of webrtc_max_sync_lag_s


class CaptureClocked:
    """A video track whose timestamps a :class:`FrameTimestamps` (``clock``) gives: what the
    capture-clock sender reports read (server/webrtc/sender_clock.py)."""

    clock: FrameTimestamps

    @property
    def stamps(self) -> CaptureStamps | None:
        return self.clock.stamps

    @property
    def lag_clamped(self) -> int:
        return self.clock.lag_clamped


class LatestFrameTrack(CaptureClocked, MediaStreamTrack):
    kind = "video"

    def __init__(self, repeat_after_s: float = REPEAT_AFTER_S,
                 epoch: CaptureEpoch | None = None, max_lag_s: float = MAX_LAG_S) -> None:
        super().__init__()
        self.repeat_after_s = repeat_after_s
        self.clock = FrameTimestamps(epoch, max_lag_s)
        self._pending: tuple[np.ndarray, asyncio.Future, float | None] | None = None
        self._new = asyncio.Event()
        self._last: np.ndarray | None = None  # [H, W, 3] uint8, the newest taken
        self.sent = 0       # distinct frames handed to the encoder
        self.repeated = 0   # repeats of the last one

    async def deliver(self, rgb: np.ndarray, captured_at: float | None = None) -> None:
        """Offer ``rgb`` ([H, W, 3] uint8) showing the drive captured at ``captured_at``
        (monotonic; None: unknown); returns once the encoder took it, a newer frame replaced
        it, or the track ended."""
        if self.readyState != "live":
            return
        if self._pending is not None:
            _settle(self._pending[1])  # superseded (latest wins)
        taken = asyncio.get_running_loop().create_future()
        self._pending = (rgb, taken, captured_at)
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
            captured_at = None
            if self._pending is not None:
                rgb, taken, captured_at = self._pending
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
        frame.pts, frame.time_base = self.clock.next(captured_at), VIDEO_TIME_BASE
        return frame

    def stop(self) -> None:
        super().stop()
        if self._pending is not None:
            _settle(self._pending[1])
            self._pending = None
        self._new.set()  # a waiting recv sees the end


class FrameTimestamps:
    """A video track's 90 kHz timestamps, strictly increasing: on a capture epoch each frame's
    is the capture instant of the drive it shows (None: no new drive in it, the moment of
    sending less the last picture lag), at most ``max_lag_s`` before the moment of sending;
    without an epoch, the moment of sending."""

    def __init__(self, epoch: CaptureEpoch | None, max_lag_s: float = MAX_LAG_S) -> None:
        self.epoch = epoch
        self.max_lag_s = max_lag_s
        self.stamps = None if epoch is None else CaptureStamps()
        self.lag_clamped = 0  # frames stamped at max_lag_s because their picture lagged more
        self._start = time.monotonic()
        self._pts = -1
        self._captured_at: float | None = None  # the last new capture instant taken
        self._lag = 0.0  # from that capture to its sending

    def next(self, captured_at: float | None) -> int:
        now = time.monotonic()
        if self.epoch is None:
            self._pts = max(int((now - self._start) * VIDEO_CLOCK_RATE), self._pts + 1)
            return self._pts
        if captured_at is not None and (self._captured_at is None
                                        or captured_at > self._captured_at):
            self._captured_at, self._lag = captured_at, max(0.0, now - captured_at)
        else:  # no new drive in it: as if captured one picture lag ago
            captured_at = now - self._lag
        if now - captured_at > self.max_lag_s:  # the voice waits within bounds
            captured_at = now - self.max_lag_s
            self._lag = min(self._lag, self.max_lag_s)
            self.lag_clamped += 1
        # never back (a capture older than the last frame's: a held frame, a restarted
        # performer, or the peer's first frame showing a drive from before the epoch)
        self._pts = max(self.epoch.ticks(captured_at, VIDEO_CLOCK_RATE), self._pts + 1, 0)
        self.stamps.note(self._pts, self.epoch.monotonic + self._pts / VIDEO_CLOCK_RATE)
        return self._pts


def _settle(future: asyncio.Future) -> None:
    if not future.done():
        future.set_result(None)
