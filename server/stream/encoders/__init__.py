"""Frame encoders, and the state of the stateful ones.

Everything outside this package treats a codec as a name: it asks :class:`FrameEncoders` to
encode a picture for a participant, and asks :meth:`FrameEncoders.output_key` whether that
participant's frame may be shared with others. Which codecs keep state between frames (H.264:
one stream per participant) is known here only: the state is kept per (participant, codec),
made at the participant's first frame of that codec, restarted with a keyframe when it comes
back from another codec, and closed when it leaves. A new codec touches this package, the
protocol's codec list and the clients.
"""

from __future__ import annotations

import collections
import threading
from collections.abc import Hashable
from dataclasses import dataclass
from typing import Any

import numpy as np

from protocol import ProtocolError, Request

from .choice import (
    H264_CPU,
    H264_GPU,
    JPEG_CPU,
    JPEG_GPU,
    EncodeError,
    EncoderChoice,
    EncoderPreference,
    active_encoders,
    choose_encoders,
    encoders_info,
    probe_nvjpeg,
    set_active,
)
from .h264 import H264Decoder, H264Encoder, H264Stream, probe_nvenc
from .images import decode_depth_png, encode_depth_png, encode_jpeg, encode_png, frame_rgb

__all__ = [
    "H264_CPU", "H264_GPU", "JPEG_CPU", "JPEG_GPU", "EncodeError", "EncoderChoice",
    "Encoded", "FrameEncoders", "H264Decoder", "H264Encoder", "active_encoders",
    "check_request", "choose_encoders", "decode_depth_png", "encode_depth_png", "encode_jpeg",
    "encode_png", "encoders_info", "frame_rgb", "probe_nvenc", "probe_nvjpeg",
    "select_encoders",
]

STATEFUL = {"h264": H264Stream}  # codec -> its per-participant stream class
EVEN_SIZES = frozenset(STATEFUL)  # 4:2:0 video wants even frame sizes
DEFAULT_STREAMS = 64  # stateful streams kept per encoder set (least recently used go first)


def select_encoders(prefer: EncoderPreference = "auto") -> EncoderChoice:
    """Probe (once per process) and make the choice the process's encoders (the server calls
    this at start-up)."""
    probed = prefer == "auto"
    choice = choose_encoders(prefer, nvjpeg=probed and probe_nvjpeg(),
                             nvenc=probed and probe_nvenc())
    set_active(choice)
    return choice


def check_request(request: Request) -> None:
    """ProtocolError ``unsupported`` when the codec cannot give what ``request`` asks."""
    codec = request.codec
    if codec in EVEN_SIZES and (request.width % 2 or request.height % 2):
        raise ProtocolError("unsupported", f"{codec} needs an even frame size, got "
                                           f"{request.width}x{request.height}",
                            {"type": "request", "seq": None})
    if codec in STATEFUL and "alpha" in request.outputs:
        raise ProtocolError("unsupported", f"{codec} frames carry no alpha; ask for png",
                            {"type": "request", "seq": None})


@dataclass(frozen=True)
class Encoded:
    codec: str
    data: bytes
    keyframe: bool
    depth: bytes | None  # 16-bit depth PNG, when asked


class FrameEncoders:
    """Encodes rendered pictures; owns the stateful codecs' streams, one per (participant,
    codec), at most ``max_streams`` (the least recently used is closed first). Thread-safe:
    render threads encode, the event loop releases."""

    def __init__(self, max_streams: int = DEFAULT_STREAMS) -> None:
        self.max_streams = max_streams
        self._lock = threading.Lock()
        self._streams: collections.OrderedDict[tuple[Hashable, str], Any] = (
            collections.OrderedDict())
        self._closed = False

    @staticmethod
    def output_key(participant: Hashable, request: Request) -> Hashable | None:
        """Whose encoded frame this is: the participant's own for a stateful codec (its frames
        are never shared), None when anyone asking the same picture may share it."""
        return participant if request.codec in STATEFUL else None

    def encode(self, participant: Hashable, previous_codec: str | None, rgb: Any,
               alpha: np.ndarray | None, depth: np.ndarray | None, request: Request,
               jpeg_quality: int) -> Encoded:
        """``rgb`` as ``request`` asks (from :func:`frame_rgb`); ``previous_codec``: the codec
        of the last frame the participant got (a stateful stream restarts after another)."""
        codec, keyframe = request.codec, True
        if "alpha" in request.outputs and codec not in STATEFUL:
            codec, data = "png", encode_png(rgb, alpha)
        elif codec == "png":
            data = encode_png(rgb)
        elif codec in STATEFUL:
            data, keyframe = self._encode_stateful(participant, previous_codec, codec, rgb,
                                                   request.max_fps)
        else:
            data = encode_jpeg(rgb, jpeg_quality)
        depth_png = encode_depth_png(depth) if "depth" in request.outputs else None
        return Encoded(codec, data, keyframe, depth_png)

    def _encode_stateful(self, participant: Hashable, previous_codec: str | None, codec: str,
                         rgb: np.ndarray, fps: float) -> tuple[bytes, bool]:
        key = (participant, codec)
        with self._lock:
            if self._closed:  # a frame still rendering when its scene closed: no state kept
                stream = STATEFUL[codec]()
                try:
                    return stream.encode(rgb, fps)
                finally:
                    stream.close()
            stream = self._streams.pop(key, None)
            if stream is None:
                stream = STATEFUL[codec]()
            elif previous_codec != codec:
                stream.restart()  # back from another codec: the client restarts here
            self._streams[key] = stream  # most recently used last
            evicted = []
            while len(self._streams) > self.max_streams:
                evicted.append(self._streams.popitem(last=False)[1])
        for old in evicted:
            _close(old)
        with stream.lock:
            return stream.encode(rgb, fps)

    def release(self, participant: Hashable) -> None:
        """The participant left: its streams are closed (after an encode under way)."""
        with self._lock:
            keys = [k for k in self._streams if k[0] == participant]
            streams = [self._streams.pop(k) for k in keys]
        for stream in streams:
            _close(stream)

    def close(self) -> None:
        with self._lock:
            self._closed = True
            streams = list(self._streams.values())
            self._streams.clear()
        for stream in streams:
            _close(stream)

    def __len__(self) -> int:
        with self._lock:
            return len(self._streams)


def _close(stream: Any) -> None:
    with stream.lock:
        stream.close()
