"""Small real videos for the enrollment tests, written with PyAV: a moving pattern in MP4
(H.264) or WebM (VP8), optionally rotated by a display matrix or carrying a focal length;
an audio-only file; garbage; a truncated copy."""

from __future__ import annotations

from collections.abc import Sequence
from fractions import Fraction
from pathlib import Path

import av
import numpy as np

CODECS = {".mp4": "libx264", ".webm": "libvpx", ".mkv": "libvpx"}


def pattern(index: int, width: int, height: int) -> np.ndarray:
    """A frame whose top-left quadrant is white and whose bar moves with ``index`` (so
    orientation and frame order can be read back)."""
    frame = np.full((height, width, 3), 40, np.uint8)
    frame[: height // 2, : width // 2] = 255
    x = (index * 4) % max(1, width - 8)
    frame[height - 8:, x:x + 8] = (255, 0, 0)
    return frame


def write_video(path: Path, *, seconds: float = 4.0, fps: int = 10, width: int = 160,
                height: int = 120, rotation: int = 0,
                metadata: dict[str, str] | None = None,
                times_ms: Sequence[int] | None = None) -> Path:
    """A ``seconds`` long video of :func:`pattern` frames; or, with ``times_ms``, one frame
    at each of those times while the stream still declares ``fps`` (as a browser's
    recorder does when frames come slower than the camera's rate)."""
    path = Path(path)
    options = {"movflags": "use_metadata_tags"} if metadata and path.suffix == ".mp4" else {}
    with av.open(str(path), "w", options=options) as out:
        out.metadata.update(metadata or {})
        stream = out.add_stream(CODECS[path.suffix], rate=fps)
        stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
        if rotation:
            stream.set_display_rotation(rotation)
        if times_ms is not None:
            stream.codec_context.time_base = Fraction(1, 1000)
        count = round(seconds * fps) if times_ms is None else len(times_ms)
        for i in range(count):
            frame = av.VideoFrame.from_ndarray(pattern(i, width, height), format="rgb24")
            if times_ms is not None:
                frame.pts, frame.time_base = int(times_ms[i]), Fraction(1, 1000)
            for packet in stream.encode(frame):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    return path


def write_audio_only(path: Path, seconds: float = 4.0) -> Path:
    """An Ogg/Opus (or any audio container by suffix) file with a tone and no video."""
    rate = 48000
    with av.open(str(path), "w") as out:
        stream = out.add_stream("libopus", rate=rate)
        t = np.arange(int(seconds * rate)) / rate
        samples = (0.2 * np.sin(2 * np.pi * 440 * t) * 32767).astype(np.int16)
        for start in range(0, len(samples), 960):
            chunk = samples[start:start + 960][None, :]
            frame = av.AudioFrame.from_ndarray(chunk, format="s16", layout="mono")
            frame.sample_rate = rate
            for packet in stream.encode(frame):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    return path


def write_garbage(path: Path, size: int = 50_000, seed: int = 0) -> Path:
    path.write_bytes(np.random.default_rng(seed).integers(0, 256, size, np.uint8).tobytes())
    return path


def truncate(src: Path, dst: Path, fraction: float = 0.5) -> Path:
    data = src.read_bytes()
    dst.write_bytes(data[: int(len(data) * fraction)])
    return dst
