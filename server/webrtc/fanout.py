"""One video encode per picture for every WebRTC viewer who sees it.

aiortc encodes for each sender, so N viewers of one picture cost N encodes (VP8 on the 2-core
machine: 0.8 ms a frame at 128 px, 4.2 ms at 512 px; docs/benchmarks.md). A room's
:class:`VideoFanout` keeps one :class:`SharedVideo` stream per picture its WebRTC viewers see
(the scene's render group, ``Frame.group``, and the codec): it encodes each frame once, in a
thread, and every viewer's :class:`FanoutTrack` hands the same bitstream to its sender, which
only packs it (aiortc's path for pre-encoded media) under its own picture ids and RTP
timestamps (its peer's capture clock, :class:`~.track.FrameTimestamps`).

A delta frame decodes only after the frames before it, so a viewer takes every frame of its
stream from a keyframe on. A viewer joining a stream, one falling ``QUEUE_FRAMES`` frames
behind, and a receiver's picture-loss request get a keyframe for the whole stream, at most one
per ``webrtc_keyframe_min_interval_s`` (a hostile viewer cannot make every frame a keyframe).
The bit rate is the lowest its viewers' receivers estimate (REMB, within
``webrtc_min/max_bitrate``). A viewer alone in its stream takes it along when its view moves
(no keyframe); viewers whose pictures part get streams of their own. A still picture is
repeated every ``repeat_after_s``, as :class:`~.track.LatestFrameTrack` repeats it.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import time
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from typing import Any

import av
from aiortc import MediaStreamTrack
from aiortc.mediastreams import VIDEO_TIME_BASE, MediaStreamError

from ..stream.scene import Frame
from .encoders import RAW_ENCODERS
from .sender_clock import CaptureEpoch
from .track import MAX_LAG_S, REPEAT_AFTER_S, CaptureClocked, FrameTimestamps

log = logging.getLogger(__name__)

QUEUE_FRAMES = 8  # encoded frames one viewer's sender may have waiting; past it, a keyframe
SENDER_KEYFRAME = "_send_keyframe"  # RTCRtpSender's handler of a picture-loss request


@dataclass(frozen=True, eq=False)
class Picture:
    """One encoded frame of a stream, as every viewer of it sends it."""

    data: bytes           # the codec's whole bitstream of the frame
    keyframe: bool
    frame: Frame | None   # the scene's frame it shows; None: a repeat (no new drive)


def supersedes(new: Frame, old: Frame) -> bool:
    """Whether a stream should show ``new`` after ``old``: another picture (a view that moved),
    or a later drive state of the same one (each seat's version at least as high)."""
    if new.group != old.group or len(new.versions) != len(old.versions):
        return True
    return new.versions != old.versions and all(
        n >= o for n, o in zip(new.versions, old.versions, strict=True))


class SharedVideo:
    """One picture's encoder and the viewers it sends to, in the order they joined."""

    def __init__(self, group: Hashable, mime: str, settings: Any,
                 repeat_after_s: float = REPEAT_AFTER_S) -> None:
        self.group, self.mime = group, mime
        self.encoder = RAW_ENCODERS[mime](settings.webrtc_min_bitrate,
                                          settings.webrtc_max_bitrate)
        self.key_interval_s = settings.webrtc_keyframe_min_interval_s
        self.repeat_after_s = repeat_after_s
        self.viewers: dict[FanoutTrack, None] = {}
        self.encodes = 0     # frames encoded (repeats and keyframes of a still picture too)
        self.keyframes = 0
        self._pending: tuple[Frame, asyncio.Future] | None = None
        self._last: Frame | None = None  # the newest frame taken
        self._new = asyncio.Event()
        self._key_wanted = False
        self._last_key_at = -float("inf")
        self._task = asyncio.get_running_loop().create_task(self._run(), name=f"video {mime}")

    def join(self, track: FanoutTrack) -> None:
        self.viewers[track] = None
        track.stream, track.awaiting_key = self, True
        self.want_key()

    def leave(self, track: FanoutTrack) -> None:
        self.viewers.pop(track, None)
        track.stream = None
        if not self.viewers:
            self.stop()

    def want_key(self) -> None:
        """A viewer cannot decode on without one: the next frame encoded is a keyframe, or,
        the picture still, its last frame again as one (within the keyframe interval)."""
        self._key_wanted = True
        self._new.set()

    async def offer(self, frame: Frame) -> None:
        """Returns once the stream took ``frame`` to encode, a newer one replaced it, or it
        came after a newer one (nothing to do)."""
        if self._last is not None and not supersedes(frame, self._last):
            return
        if self._pending is not None:
            waiting, taken = self._pending
            if not supersedes(frame, waiting):
                if waiting is frame or waiting.versions == frame.versions:
                    await asyncio.shield(taken)  # another viewer's offer of the same picture
                return
            _settle(taken)
        taken = asyncio.get_running_loop().create_future()
        self._pending = (frame, taken)
        self._new.set()
        await asyncio.shield(taken)

    def stop(self) -> None:
        self._task.cancel()
        if self._pending is not None:
            _settle(self._pending[1])
            self._pending = None

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        try:
            while self.viewers:
                frame, new = await self._next()
                key = self._key_wanted and self._key_allowed()
                rates = [r for v in self.viewers if (r := v.target_bitrate()) is not None]
                if rates:
                    self.encoder.target_bitrate = min(rates)
                image = av.VideoFrame.from_ndarray(frame.rgb, format="rgb24")
                image.pts, image.time_base = 0, VIDEO_TIME_BASE  # the encoder's clock is its own
                payloads, _ = await loop.run_in_executor(None, self.encoder.encode, image, key)
                self.encodes += 1
                if not payloads:
                    continue  # the rate control dropped it
                keyframe = self.encoder.is_keyframe(payloads[0])
                if keyframe:
                    self.keyframes += 1
                    self._key_wanted, self._last_key_at = False, time.monotonic()
                picture = Picture(payloads[0], keyframe, frame if new else None)
                for viewer in list(self.viewers):
                    viewer.push(picture)
        except Exception:  # a codec error: the viewers end (their peers close), the server goes on
            log.exception("a shared WebRTC video stream failed; its %d viewers end",
                          len(self.viewers))
            for viewer in list(self.viewers):
                viewer.stop()

    def _key_allowed(self) -> bool:
        return time.monotonic() - self._last_key_at >= self.key_interval_s

    async def _next(self) -> tuple[Frame, bool]:
        """The next frame to encode and whether it is new (else a repeat of the last)."""
        while True:
            if self._pending is not None:
                frame, taken = self._pending
                self._pending = None
                _settle(taken)
                self._last = frame
                return frame, True
            if self._last is not None and self._key_wanted and self._key_allowed():
                return self._last, False
            timeout = None
            if self._last is not None:
                timeout = self.repeat_after_s
                if self._key_wanted:
                    timeout = min(timeout, self._last_key_at + self.key_interval_s
                                  - time.monotonic())
            self._new.clear()
            try:
                await asyncio.wait_for(self._new.wait(), max(timeout, 0.0)
                                       if timeout is not None else None)
            except TimeoutError:
                if self._pending is None and not self._key_wanted:
                    return self._last, False  # still: repeated


class VideoFanout:
    """A room's shared video streams, by (picture, codec)."""

    def __init__(self, settings: Any) -> None:
        self.settings = settings
        self.streams: dict[tuple[Hashable, str], SharedVideo] = {}

    def stream_for(self, track: FanoutTrack, group: Hashable, mime: str) -> SharedVideo:
        """The stream ``track`` sends for a frame of ``group``: its own, another stream of
        that picture (joined), its own re-keyed (alone, its view moved), or a new one."""
        current = track.stream
        key = (group, mime)
        if current is not None and (current.group, current.mime) == key:
            return current
        other = self.streams.get(key)
        if other is not None:
            self.leave(track)
            other.join(track)
            return other
        if current is not None and len(current.viewers) == 1:
            del self.streams[(current.group, current.mime)]
            current.group = group
            self.streams[key] = current
            return current
        self.leave(track)
        stream = self.streams[key] = SharedVideo(group, mime, self.settings)
        stream.join(track)
        return stream

    def leave(self, track: FanoutTrack) -> None:
        stream = track.stream
        if stream is None:
            return
        stream.leave(track)
        if not stream.viewers:
            self.streams.pop((stream.group, stream.mime), None)

    @property
    def encodes(self) -> int:
        return sum(s.encodes for s in self.streams.values())


def room_fanout(live: Any, settings: Any) -> VideoFanout:
    """The room's video fan-out, made on first use."""
    if getattr(live, "video_fanout", None) is None:
        live.video_fanout = VideoFanout(settings)
    return live.video_fanout


class FanoutTrack(CaptureClocked, MediaStreamTrack):
    """A WebRTC viewer's video: the encoded frames of its picture's shared stream, as
    ``av.Packet``s its sender packs. ``deliver`` offers the scene's frames it is handed;
    nothing is offered before the sender asks for its first frame (its transport is up)."""

    kind = "video"

    def __init__(self, epoch: CaptureEpoch | None = None, max_lag_s: float = MAX_LAG_S,
                 queue_frames: int = QUEUE_FRAMES) -> None:
        super().__init__()
        self.fanout: VideoFanout | None = None  # the room's, once attached
        self.clock = FrameTimestamps(epoch, max_lag_s)
        self.queue_frames = queue_frames
        self.mime: str | None = None
        self.captured_at_of: Callable[[Frame], float | None] = lambda frame: None
        self.stream: SharedVideo | None = None
        self.awaiting_key = True
        self._sender_encoder: Any = None
        self._queue: collections.deque[Picture] = collections.deque()
        self._ready = asyncio.Event()
        self._receiving = asyncio.Event()
        self.sent = 0       # frames of new drives handed to the sender
        self.repeated = 0   # repeats (and keyframes) of the picture it had
        self.skipped = 0    # frames not sent: waiting for a keyframe, or fallen behind
        self.overflows = 0  # times it fell QUEUE_FRAMES behind

    def attach(self, fanout: VideoFanout, sender: Any, mime: str, sender_encoder: Any) -> None:
        """Streams of ``fanout`` (the room's), sent by ``sender`` as ``mime``;
        ``sender_encoder`` (its packer) carries the receiver's bit-rate estimate (None:
        the stream's encoder keeps its own); picture-loss requests come here."""
        self.fanout, self.mime, self._sender_encoder = fanout, mime.lower(), sender_encoder
        setattr(sender, SENDER_KEYFRAME, self.want_key)

    def want_key(self) -> None:
        if self.stream is not None:
            self.stream.want_key()

    def target_bitrate(self) -> int | None:
        return getattr(self._sender_encoder, "target_bitrate", None)

    async def deliver(self, frame: Frame) -> None:
        """Offer ``frame`` (raw, ``frame.rgb``) to this viewer's stream; returns once the
        stream took it, a newer one replaced it, or the track ended."""
        if self.readyState != "live":
            return
        await self._receiving.wait()
        if self.readyState != "live" or self.fanout is None or self.mime not in RAW_ENCODERS:
            return
        await self.fanout.stream_for(self, frame.group, self.mime).offer(frame)

    def push(self, picture: Picture) -> None:
        if len(self._queue) >= self.queue_frames:  # fallen behind: on from a keyframe
            self.skipped += len(self._queue)
            self.overflows += 1
            self._queue.clear()
            self.awaiting_key = True
            self.want_key()
        self._queue.append(picture)
        self._ready.set()

    async def recv(self) -> av.Packet:
        self._receiving.set()
        while True:
            if self.readyState != "live":
                raise MediaStreamError
            if not self._queue:
                self._ready.clear()
                await self._ready.wait()
                continue
            picture = self._queue.popleft()
            if self.awaiting_key and not picture.keyframe:
                self.skipped += 1
                continue
            self.awaiting_key = False
            break
        if picture.frame is None:
            self.repeated += 1
            captured_at = None
        else:
            self.sent += 1
            captured_at = self.captured_at_of(picture.frame)
        packet = av.Packet(picture.data)
        packet.pts, packet.time_base = self.clock.next(captured_at), VIDEO_TIME_BASE
        return packet

    def stop(self) -> None:
        super().stop()
        if self.fanout is not None:
            self.fanout.leave(self)
        self._queue.clear()
        self._ready.set()
        self._receiving.set()


def _settle(future: asyncio.Future) -> None:
    if not future.done():
        future.set_result(None)

