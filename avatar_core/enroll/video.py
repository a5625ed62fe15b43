"""Enrollment videos: probe, refuse, decode (PyAV).

:func:`probe_video` looks at a file without decoding its pictures (one frame excepted): the
container, the video stream, its size, and its duration and frame count from demuxing the
packets (a browser's MediaRecorder WebM carries no duration in its header). Anything outside
:class:`VideoLimits` is refused with :class:`EnrollmentRefused` and what to do, before any
work. :func:`read_video` then decodes, keeping at most ``max_decode_fps`` frames a second,
downscaled to the enrollment size and turned upright (the display matrix of phone videos),
with the frame count and the unpacked bytes bounded while it decodes.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import av
import numpy as np

from .errors import EnrollmentRefused

__all__ = ["DecodedVideo", "VideoInfo", "VideoLimits", "decode_plan", "output_size", "probe_video",
           "read_video"]

MiB = 2**20
# A 35 mm frame's diagonal: a "35 mm equivalent" focal length is relative to it.
FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)
# Metadata keys that give the lens's 35 mm equivalent focal length (mm): Apple's QuickTime
# key, and the EXIF tag's name as some exporters copy it.
FOCAL_35MM_KEYS = ("com.apple.quicktime.camera.focal_length.35mm_equivalent",
                   "FocalLengthIn35mmFormat")
FOCAL_35MM_RANGE = (8.0, 400.0)  # mm; other values are ignored as nonsense
# Frames are kept one per 1 / max_decode_fps slot; timestamps rounded to a millisecond (WebM)
# land a little before their slot, so each counts this much of a slot early.
SLOT_SLACK = 0.05


@dataclass(frozen=True)
class VideoLimits:
    """What an enrollment video may be (server settings ``enroll_*``, docs/security.md)."""

    max_bytes: int = 256 * MiB          # the file
    min_duration_s: float = 3.0
    max_duration_s: float = 120.0
    min_side_px: int = 64               # the picture's shorter side
    max_side_px: int = 4096             # the picture's longer side (4K passes, 8K does not)
    max_packets: int = 20_000           # video packets the probe demuxes (about frames)
    max_decode_fps: float = 15.0        # frames kept a second; the rest are skipped
    max_frames: int = 1800              # frames kept in all
    max_decoded_bytes: int = 1024 * MiB  # the kept frames, unpacked RGB

    def __post_init__(self) -> None:
        if not (self.max_bytes >= 1 and 0 <= self.min_duration_s < self.max_duration_s
                and 1 <= self.min_side_px <= self.max_side_px and self.max_packets >= 1
                and self.max_decode_fps > 0 and self.max_frames >= 1
                and self.max_decoded_bytes >= 1):
            raise ValueError(f"inconsistent video limits: {self}")


@dataclass(frozen=True)
class VideoInfo:
    """What the probe found. ``width`` x ``height``: as displayed (after ``rotation``)."""

    container: str
    codec: str
    width: int
    height: int
    rotation: int          # degrees counter-clockwise that turn the stored picture upright
    duration_s: float
    starts_span_s: float   # the first to the last packet's start: what frame times span
    packets: int           # video packets (frames, for every codec a browser or phone writes)
    fps: float
    bytes: int
    focal_35mm: float | None  # the lens's 35 mm equivalent focal length, mm, from metadata

    def focal_px(self, width: int, height: int) -> float | None:
        """The focal length in pixels of a ``width`` x ``height`` picture of this video."""
        if self.focal_35mm is None:
            return None
        return self.focal_35mm / FULL_FRAME_DIAGONAL_MM * math.hypot(width, height)


@dataclass
class DecodedVideo:
    """Decoded frames: uint8 RGB ``[N, H, W, 3]``, upright, at most ``long_side`` px."""

    frames: np.ndarray
    times_s: np.ndarray    # each frame's time from the first, seconds
    fps: float             # frames kept per second of video
    focal_px: float | None  # at the frames' size; None: no focal length in the metadata
    rotation: int          # what was applied to turn the frames upright
    info: VideoInfo

    @property
    def size(self) -> tuple[int, int]:
        return int(self.frames.shape[2]), int(self.frames.shape[1])


def _refuse(reason: str, message: str, what_to_do: str) -> EnrollmentRefused:
    return EnrollmentRefused(reason, message, what_to_do)


def _corrupt(detail: str) -> EnrollmentRefused:
    return _refuse("corrupt_video", f"The file is not a readable video ({detail}).",
                   "Record it again, or export it again as MP4 or WebM.")


def _open(path: Path) -> Any:
    try:
        return av.open(str(path), mode="r")
    except (av.FFmpegError, ValueError, UnicodeDecodeError) as exc:
        raise _corrupt(type(exc).__name__) from None


def _focal_35mm(container: Any, stream: Any) -> float | None:
    for metadata in (stream.metadata, container.metadata):
        for key in FOCAL_35MM_KEYS:
            try:
                value = float(metadata.get(key, "nan"))
            except ValueError:
                continue
            if FOCAL_35MM_RANGE[0] <= value <= FOCAL_35MM_RANGE[1]:
                return value
    return None


def _check_size(width: int, height: int, limits: VideoLimits) -> None:
    if max(width, height) > limits.max_side_px:
        raise _refuse("resolution_too_large",
                      f"The video is {width} x {height} px, larger than the "
                      f"{limits.max_side_px} px allowed on its longer side.",
                      "Record at 1080p or 4K, or downscale the video before uploading it.")
    if min(width, height) < limits.min_side_px:
        raise _refuse("resolution_too_small",
                      f"The video is {width} x {height} px, smaller than the "
                      f"{limits.min_side_px} px needed on its shorter side.",
                      "Record at a higher resolution (480p or more).")


def _check_duration(seconds: float, limits: VideoLimits) -> None:
    if seconds > limits.max_duration_s:
        raise _refuse("too_long", f"The video lasts more than {limits.max_duration_s:g} s.",
                      f"Record at most {limits.max_duration_s:g} s (20 to 60 s is enough), or "
                      "trim it.")
    if seconds < limits.min_duration_s:
        raise _refuse("too_short", f"The video lasts {seconds:.1f} s, less than the "
                      f"{limits.min_duration_s:g} s needed.",
                      "Record 20 to 60 s: turn slowly left and right, smile, open your hands.")


def _demux(container: Any, stream: Any, limits: VideoLimits) -> tuple[int, float, float]:
    """Video packets, the duration they span and the span of their starts, without decoding;
    refused as soon as packets or duration pass their limit."""
    base = stream.time_base or Fraction(1, 1000)
    packets, first, last, last_start = 0, None, None, None
    try:
        for packet in container.demux(stream):
            if packet.size == 0 or packet.pts is None:
                continue  # the demuxer's flush packet; a packet without a time
            packets += 1
            if packets > limits.max_packets:
                raise _refuse("too_many_frames", f"The video has more than "
                              f"{limits.max_packets} frames.",
                              "Record a shorter video, at 30 or 60 frames a second.")
            start = float(packet.pts * base)
            end = start + float((packet.duration or 0) * base)
            first = start if first is None else min(first, start)
            last = end if last is None else max(last, end)
            last_start = start if last_start is None else max(last_start, start)
            if last - first > limits.max_duration_s:
                _check_duration(last - first, limits)
    except av.FFmpegError as exc:
        raise _corrupt(f"damaged after {packets} frames: {type(exc).__name__}") from None
    if packets == 0:
        raise _corrupt("its video stream holds no frames")
    starts = (last_start - first) if last_start is not None and first is not None else 0.0
    span = (last - first) if last is not None and first is not None else 0.0
    if span <= 0 and stream.average_rate:  # one packet, or no packet durations
        span = packets / float(stream.average_rate)
    return packets, span, starts


def probe_video(path: str | Path, limits: VideoLimits | None = None) -> VideoInfo:
    """What the video is; EnrollmentRefused (with what to do) when it is corrupt, has no video
    stream, or is outside ``limits``. Decodes one frame only."""
    limits = limits or VideoLimits()
    path = Path(path)
    size = os.path.getsize(path)
    if size > limits.max_bytes:
        raise _refuse("file_too_large", f"The file is {size / MiB:.0f} MiB, more than the "
                      f"{limits.max_bytes / MiB:.0f} MiB allowed.",
                      "Record a shorter video, or export it at a lower bit rate.")
    if size == 0:
        raise _corrupt("the file is empty")
    with _open(path) as container:
        if not container.streams.video:
            kinds = sorted({s.type for s in container.streams}) or ["nothing"]
            raise _refuse("no_video_stream", f"The file holds no video, only "
                          f"{' and '.join(kinds)}.",
                          "Upload the video itself (MP4, MOV or WebM from a camera), not a "
                          "sound recording.")
        stream = container.streams.video[0]
        codec = stream.codec_context.name
        stored_w, stored_h = stream.codec_context.width, stream.codec_context.height
        if not stored_w or not stored_h:
            raise _corrupt("its video stream has no picture size")
        _check_size(stored_w, stored_h, limits)
        focal = _focal_35mm(container, stream)
        packets, duration, starts_span = _demux(container, stream, limits)
        _check_duration(duration, limits)
        fmt = container.format.name
    first = _first_frame(path)
    rotation = int(round(first.rotation / 90.0)) * 90 % 360
    width, height = (stored_h, stored_w) if rotation in (90, 270) else (stored_w, stored_h)
    return VideoInfo(container=fmt, codec=codec, width=width, height=height, rotation=rotation,
                     duration_s=duration, starts_span_s=starts_span, packets=packets,
                     fps=packets / duration if duration > 0 else 0.0, bytes=size,
                     focal_35mm=focal)


def _first_frame(path: Path) -> Any:
    with _open(path) as container:
        try:
            for frame in container.decode(video=0):
                return frame
        except av.FFmpegError as exc:
            raise _corrupt(f"its first frame cannot be decoded: {type(exc).__name__}") from None
    raise _corrupt("no frame of it can be decoded")


def output_size(width: int, height: int, long_side: int) -> tuple[int, int]:
    """``width`` x ``height`` scaled down (never up) so the longer side is ``long_side``."""
    scale = min(1.0, long_side / max(width, height))
    return max(1, round(width * scale)), max(1, round(height * scale))


def decode_plan(info: VideoInfo, limits: VideoLimits, long_side: int) -> tuple[int, int, int]:
    """The frames :func:`read_video` keeps and their width and height; EnrollmentRefused when
    they pass ``max_frames`` or ``max_decoded_bytes``. From the probe alone (no decoding)."""
    width, height = output_size(info.width, info.height, long_side)
    # Slots are counted over the frames' starts as the demuxer read them. Not the duration
    # less a mean frame: a browser's WebM under load spaces frames unevenly, and its last
    # packet's duration says nothing of the mean (that estimate once fell a frame short).
    slots = math.floor(info.starts_span_s * limits.max_decode_fps + SLOT_SLACK) + 1
    kept = min(info.packets, slots)
    _check_frames(kept, width, height, limits)
    return kept, width, height


def read_video(path: str | Path, limits: VideoLimits | None = None, *,
               long_side: int = 512) -> DecodedVideo:
    """The video's frames, upright, downscaled to at most ``long_side`` px, at most
    ``limits.max_decode_fps`` a second. Probed first: EnrollmentRefused before any decoding
    for a video outside ``limits``, and while decoding when it holds more frames or bytes
    than it declared, or is damaged."""
    limits = limits or VideoLimits()
    if long_side < 16:
        raise ValueError(f"long_side must be >= 16 px, got {long_side}")
    info = probe_video(path, limits)
    kept, width, height = decode_plan(info, limits, long_side)
    stored_w, stored_h = (height, width) if info.rotation in (90, 270) else (width, height)
    frames = np.empty((kept, height, width, 3), np.uint8)
    times: list[float] = []
    step = 1.0 / limits.max_decode_fps
    start = last = None
    with _open(Path(path)) as container:
        try:
            for frame in container.decode(video=0):
                t = float(frame.time) if frame.time is not None else len(times) * step
                start = t if start is None else start
                slot = math.floor((t - start) / step + SLOT_SLACK)
                if last is not None and slot <= last:
                    continue  # over max_decode_fps: skipped
                if len(times) == kept:  # more pictures, or later ones, than its packets declared
                    raise _corrupt(f"it decodes to more frames than its {info.packets} "
                                   "packets declared")
                last = slot
                picture = frame.reformat(width=stored_w, height=stored_h, format="rgb24",
                                         interpolation="AREA").to_ndarray()
                frames[len(times)] = np.rot90(picture, k=info.rotation // 90)
                times.append(t - start)
        except av.FFmpegError as exc:
            raise _corrupt(f"damaged after {len(times)} frames: {type(exc).__name__}") from None
    if not times:
        raise _corrupt("no frame of it can be decoded")
    frames = frames[:len(times)]
    span = times[-1] if len(times) > 1 else 0.0
    fps = (len(times) - 1) / span if span > 0 else min(info.fps, limits.max_decode_fps)
    return DecodedVideo(frames=frames, times_s=np.asarray(times), fps=fps,
                        focal_px=info.focal_px(width, height), rotation=info.rotation,
                        info=info)


def _check_frames(count: int, width: int, height: int, limits: VideoLimits) -> None:
    if count > limits.max_frames:
        raise _refuse("too_many_frames", f"The video gives {count} frames to decode, more "
                      f"than the {limits.max_frames} allowed.", "Record a shorter video.")
    need = count * width * height * 3
    if need > limits.max_decoded_bytes:
        raise _refuse("too_many_frames", f"The video's frames unpack to {need / MiB:.0f} "
                      f"MiB, more than the {limits.max_decoded_bytes / MiB:.0f} MiB allowed.",
                      "Record a shorter video.")
