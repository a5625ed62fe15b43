"""Frame encoders: JPEG (quality drops while the view moves), PNG with alpha, 16-bit depth PNG,
and H.264 through PyAV (one stateful encoder per session, re-created on a size change).

Inputs are uint8 RGB ``[H, W, 3]`` (alpha ``[H, W]`` uint8, depth ``[H, W]`` float metres).

On a GPU server two encoders move to the device (:func:`select_encoders`, once per process,
reported in ``welcome.encoders``): JPEG through nvJPEG (torchvision's ``encode_jpeg`` of a CUDA
tensor: the picture never crosses to the host, only its bytes), and H.264 through NVENC
(PyAV's ``h264_nvenc``). Each is probed by using it once; where a probe fails, or with the
setting ``encoders = "cpu"``, OpenCV's JPEG and libx264 are used.
"""

from __future__ import annotations

import functools
import threading
from dataclasses import dataclass
from fractions import Fraction
from typing import Any, Literal

import av
import cv2
import numpy as np

from protocol.messages import EncodersInfo

DEPTH_MAX_MM = 65535  # 65.535 m: deeper is clipped; 0 means no surface


class EncodeError(RuntimeError):
    pass


# -- which encoders: probed once, chosen from the probes' answers ----------------------------

EncoderPreference = Literal["auto", "cpu"]
JPEG_GPU, JPEG_CPU = "nvjpeg", "opencv"
H264_GPU, H264_CPU = "h264_nvenc", "libx264"


@dataclass(frozen=True)
class EncoderChoice:
    jpeg: str = JPEG_CPU   # "nvjpeg" | "opencv"
    h264: str = H264_CPU   # "h264_nvenc" | "libx264"

    def as_dict(self) -> dict[str, str]:
        return {"jpeg": self.jpeg, "h264": self.h264}


def choose_encoders(prefer: EncoderPreference, *, nvjpeg: bool, nvenc: bool) -> EncoderChoice:
    """The encoders to use, from the probes' answers (``nvjpeg``, ``nvenc``: it works here)."""
    if prefer not in ("auto", "cpu"):
        raise ValueError(f"encoders must be 'auto' or 'cpu', got {prefer!r}")
    gpu = prefer == "auto"
    return EncoderChoice(jpeg=JPEG_GPU if gpu and nvjpeg else JPEG_CPU,
                         h264=H264_GPU if gpu and nvenc else H264_CPU)


@functools.cache
def probe_nvjpeg() -> bool:
    """torchvision with CUDA installed and one tiny JPEG encoded on the GPU (cached)."""
    try:
        import torch
        import torchvision.io

        if not torch.cuda.is_available():
            return False
        img = torch.zeros(3, 16, 16, dtype=torch.uint8, device="cuda")
        data = torchvision.io.encode_jpeg(img, quality=80)
        return bool(data.numel() > 0)
    except Exception:  # noqa: BLE001 - not importable, no CUDA build, no nvJPEG: the CPU one
        return False


@functools.cache
def probe_nvenc() -> bool:
    """PyAV lists ``h264_nvenc`` and one tiny frame encodes with it (cached: PyAV's FFmpeg
    lists NVENC even where no NVIDIA driver is, and only opening it tells)."""
    if H264_GPU not in av.codecs_available:
        return False
    try:
        enc = H264Encoder(64, 64, codec=H264_GPU)
        try:
            enc.encode(np.zeros((64, 64, 3), np.uint8))
        finally:
            enc.close()
        return True
    except Exception:  # noqa: BLE001 - no driver, no device, a busy one: libx264
        return False


_active = EncoderChoice()
_active_lock = threading.Lock()


def select_encoders(prefer: EncoderPreference = "auto") -> EncoderChoice:
    """Probe (once per process) and make the choice the process's encoders (the server calls
    this at start-up)."""
    global _active
    probed = prefer == "auto"
    choice = choose_encoders(prefer, nvjpeg=probed and probe_nvjpeg(),
                             nvenc=probed and probe_nvenc())
    with _active_lock:
        _active = choice
    return choice


def active_encoders() -> EncoderChoice:
    """The encoders in use (OpenCV JPEG and libx264 until :func:`select_encoders`)."""
    return _active


def encoders_info() -> EncodersInfo:
    """The active choice as ``welcome.encoders``."""
    return EncodersInfo(**active_encoders().as_dict())


def frame_rgb(rgb: Any, codec: str, alpha: bool) -> Any:
    """The picture as the encoder of ``codec`` takes it, from a float tensor [H, W, 3]: a
    uint8 CUDA tensor where nvJPEG encodes it (no host copy of the image), else uint8 numpy."""
    from avatar_core.render.types import to_uint8

    if (codec == "jpeg" and not alpha and rgb.is_cuda
            and active_encoders().jpeg == JPEG_GPU):
        return (rgb.clamp(0, 1) * 255).round().byte()
    return to_uint8(rgb)


def _encode_jpeg_gpu(rgb: Any, quality: int) -> bytes:
    """uint8 CUDA tensor [H, W, 3] -> JPEG bytes, encoded by nvJPEG."""
    import torchvision.io

    data = torchvision.io.encode_jpeg(rgb.permute(2, 0, 1).contiguous(), quality=int(quality))
    return data.cpu().numpy().tobytes()


def encode_jpeg(rgb: Any, quality: int) -> bytes:
    """uint8 RGB [H, W, 3]: numpy (OpenCV) or a CUDA tensor from :func:`frame_rgb` (nvJPEG)."""
    if not isinstance(rgb, np.ndarray):
        return _encode_jpeg_gpu(rgb, quality)
    ok, buf = cv2.imencode(".jpg", rgb[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise EncodeError("JPEG encoding failed")
    return buf.tobytes()


def encode_png(rgb: np.ndarray, alpha: np.ndarray | None = None) -> bytes:
    """RGB, or RGBA when ``alpha`` is given. Compression 1: fast, still lossless."""
    bgr = rgb[..., ::-1]
    img = bgr if alpha is None else np.dstack([bgr, alpha])  # [H, W, 3|4]
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise EncodeError("PNG encoding failed")
    return buf.tobytes()


def encode_depth_png(depth_m: np.ndarray) -> bytes:
    """Depth in metres [H, W] -> 16-bit grey PNG in millimetres (0: no surface)."""
    mm = np.clip(np.nan_to_num(depth_m, nan=0.0) * 1000.0, 0, DEPTH_MAX_MM)
    ok, buf = cv2.imencode(".png", np.round(mm).astype(np.uint16),
                           [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise EncodeError("depth PNG encoding failed")
    return buf.tobytes()


def decode_depth_png(data: bytes) -> np.ndarray:
    """The inverse of :func:`encode_depth_png`: metres [H, W] float32."""
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    return img.astype(np.float32) / 1000.0


class H264Encoder:
    """One H.264 stream (Annex B, baseline-like: no B-frames, zero latency).

    Each ``encode`` call returns the packet bytes of exactly that frame (the encoder is set to
    emit one packet per frame with no reordering delay) and whether it is a keyframe. A
    keyframe is forced on the first frame, every ``gop`` frames, and on ``force_keyframe()``.
    """

    def __init__(self, width: int, height: int, *, fps: float = 30.0, gop: int = 60,
                 crf: int = 28, codec: str | None = None) -> None:
        if width % 2 or height % 2:
            raise EncodeError(f"H.264 needs even frame sizes, got {width}x{height}")
        self.width, self.height, self.gop = width, height, gop
        self.codec = active_encoders().h264 if codec is None else codec
        if self.codec not in (H264_CPU, H264_GPU):
            raise EncodeError(f"unknown H.264 encoder {self.codec!r}")
        self._ctx = av.CodecContext.create(self.codec, "w")
        self._ctx.width, self._ctx.height = width, height
        self._ctx.pix_fmt = "yuv420p"
        self._ctx.time_base = Fraction(1, 1000)
        self._ctx.framerate = Fraction(round(fps * 1000), 1000)
        self._ctx.gop_size = gop
        self._ctx.max_b_frames = 0
        if self.codec == H264_CPU:
            self._ctx.options = {"preset": "ultrafast", "tune": "zerolatency", "crf": str(crf),
                                 "repeat-headers": "1"}  # SPS/PPS on every keyframe
        else:  # NVENC: lowest latency, no lookahead; forced keyframes are IDR (with SPS/PPS)
            self._ctx.options = {"preset": "p1", "tune": "ull", "zerolatency": "1",
                                 "delay": "0", "forced-idr": "1", "rc": "constqp",
                                 "qp": str(crf)}
        self._ctx.open()
        self._count = 0
        self._force = True

    def force_keyframe(self) -> None:
        self._force = True

    def encode(self, rgb: np.ndarray) -> tuple[bytes, bool]:
        """uint8 RGB [H, W, 3] -> (Annex B bytes of this frame, keyframe)."""
        if rgb.shape[:2] != (self.height, self.width):
            raise EncodeError(f"frame {rgb.shape[1]}x{rgb.shape[0]} does not match the "
                              f"encoder's {self.width}x{self.height}")
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
        frame.pts = self._count
        key = self._force or self._count % self.gop == 0
        frame.pict_type = av.video.frame.PictureType.I if key else \
            av.video.frame.PictureType.NONE
        self._force = False
        self._count += 1
        packets = self._ctx.encode(frame)
        data = b"".join(bytes(p) for p in packets)
        return data, key or any(p.is_keyframe for p in packets)

    def close(self) -> None:
        try:
            self._ctx.close()
        except Exception:  # noqa: BLE001 - closing a codec must never break a teardown
            pass


class H264Decoder:
    """Decodes the stream of :class:`H264Encoder` (tests and Python clients)."""

    def __init__(self) -> None:
        self._ctx = av.CodecContext.create("h264", "r")

    def decode(self, data: bytes) -> list[np.ndarray]:
        """uint8 RGB frames [H, W, 3] decoded from one frame's bytes."""
        # One packet per frame (see H264Encoder): no parser, which would hold the last one back.
        return [f.to_ndarray(format="rgb24") for f in self._ctx.decode(av.Packet(data))]
