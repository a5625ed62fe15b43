"""Which encoders this process uses, probed once at start-up.

On a GPU server two encoders move to the device (:func:`select_encoders`, once per process,
reported in ``welcome.encoders``): JPEG through nvJPEG (torchvision's ``encode_jpeg`` of a CUDA
tensor: the picture never crosses to the host, only its bytes), and H.264 through NVENC
(PyAV's ``h264_nvenc``, probed in h264.py). Each is probed by using it once; where a probe
fails, or with the setting ``encoders = "cpu"``, OpenCV's JPEG and libx264 are used.
"""

from __future__ import annotations

import functools
import threading
from dataclasses import dataclass
from typing import Literal

from protocol.messages import EncodersInfo


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


_active = EncoderChoice()
_active_lock = threading.Lock()


def set_active(choice: EncoderChoice) -> None:
    """Make ``choice`` the process's encoders."""
    global _active
    with _active_lock:
        _active = choice


def active_encoders() -> EncoderChoice:
    """The encoders in use (OpenCV JPEG and libx264 until :func:`select_encoders`)."""
    return _active


def encoders_info() -> EncodersInfo:
    """The active choice as ``welcome.encoders``."""
    return EncodersInfo(**active_encoders().as_dict())
