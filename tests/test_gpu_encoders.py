"""Encoder choice: nvJPEG / NVENC where their probes succeed, else OpenCV JPEG / libx264,
reported in welcome. On this CPU machine the probes fail and the fallback is chosen; the
choice itself is tested with the probes' answers given as arguments. The GPU encoders run
only on CUDA (marked ``gpu``)."""

import asyncio

import cv2
import numpy as np
import pytest
import torch

from avatar_core.render.types import to_uint8
from server.stream import encoders as enc
from server.stream.encoders import (
    EncodeError,
    EncoderChoice,
    H264Decoder,
    H264Encoder,
    choose_encoders,
    frame_rgb,
    select_encoders,
)
from tests.server_fixtures import run_server, stream
from tests.test_server_rooms import create_room, join


@pytest.mark.parametrize(("prefer", "nvjpeg", "nvenc", "want"), [
    ("auto", True, True, ("nvjpeg", "h264_nvenc")),
    ("auto", True, False, ("nvjpeg", "libx264")),
    ("auto", False, True, ("opencv", "h264_nvenc")),
    ("auto", False, False, ("opencv", "libx264")),
    ("cpu", True, True, ("opencv", "libx264")),
])
def test_choice_from_the_probes_answers(prefer, nvjpeg, nvenc, want):
    choice = choose_encoders(prefer, nvjpeg=nvjpeg, nvenc=nvenc)
    assert (choice.jpeg, choice.h264) == want
    assert choice.as_dict() == {"jpeg": want[0], "h264": want[1]}


def test_a_bad_preference_is_refused():
    with pytest.raises(ValueError, match="'auto' or 'cpu'"):
        choose_encoders("gpu", nvjpeg=True, nvenc=True)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the CPU fallback")
def test_without_cuda_the_probes_fail_and_the_cpu_encoders_are_chosen():
    assert enc.probe_nvjpeg() is False
    assert enc.probe_nvenc() is False  # PyAV may list h264_nvenc; opening it tells
    assert enc.probe_nvenc() is False  # cached
    try:
        assert select_encoders("auto") == EncoderChoice("opencv", "libx264")
        assert enc.active_encoders() == EncoderChoice("opencv", "libx264")
        assert H264Encoder(32, 32).codec == "libx264"
    finally:
        select_encoders("cpu")


def _smooth(height: int, width: int, device: str = "cpu") -> torch.Tensor:
    """A float picture [H, W, 3] that JPEG keeps closely (random noise it does not)."""
    y, x = torch.meshgrid(torch.linspace(0, 1, height), torch.linspace(0, 1, width),
                          indexing="ij")
    return torch.stack([x, y, (x + y) / 2], -1).to(device)


def test_cpu_frames_are_numpy_and_encode_as_before():
    rgb = _smooth(24, 32)
    img = frame_rgb(rgb, "jpeg", alpha=False)
    assert isinstance(img, np.ndarray) and np.array_equal(img, to_uint8(rgb))
    data = enc.encode_jpeg(img, 90)
    back = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
    assert np.abs(back.astype(int) - img.astype(int)).mean() < 3


def test_h264_encoder_names():
    with pytest.raises(EncodeError, match="unknown H.264 encoder"):
        H264Encoder(32, 32, codec="mpeg4")
    e = H264Encoder(32, 32, codec="libx264")
    data, key = e.encode(np.full((32, 32, 3), 128, np.uint8))
    assert key and H264Decoder().decode(data)[0].shape == (32, 32, 3)
    e.close()


@pytest.fixture(scope="module")
def srv(tmp_path_factory):
    with run_server(tmp_path_factory.mktemp("enc"), default_width=32, default_height=32) as s:
        yield s


def test_welcome_reports_the_encoders(srv):
    """Sessions and room participants are told what encodes their frames (here: the CPU
    fallback, chosen automatically at start-up)."""
    want = enc.active_encoders().as_dict()
    assert want == ({"jpeg": "opencv", "h264": "libx264"} if not torch.cuda.is_available()
                    else want)
    room = create_room(srv)

    async def run():
        async with stream(srv) as ws:
            plain = ws.welcome
        async with join(srv, room["id"], srv.token) as ws:
            return plain, ws.welcome

    plain, in_room = asyncio.run(run())
    assert plain.encoders.model_dump() == want
    assert in_room.encoders.model_dump() == want


# ---- CUDA only -------------------------------------------------------------------------------

@pytest.mark.gpu
def test_nvjpeg_encodes_a_cuda_frame():  # pragma: no cover (needs CUDA)
    pytest.importorskip("torchvision", reason="torchvision not installed (the cuda extra)")
    assert enc.probe_nvjpeg()
    rgb = _smooth(48, 64, "cuda")
    img = enc.images._encode_jpeg_gpu((rgb * 255).round().byte(), 90)
    back = cv2.imdecode(np.frombuffer(img, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
    assert back.shape == (48, 64, 3)
    assert np.abs(back.astype(int) - to_uint8(rgb).astype(int)).mean() < 3


@pytest.mark.gpu
def test_nvenc_round_trip_when_present():  # pragma: no cover (needs CUDA)
    if not enc.probe_nvenc():
        pytest.skip("PyAV's FFmpeg has no working h264_nvenc here")
    e = H264Encoder(64, 64, codec="h264_nvenc")
    dec = H264Decoder()
    frames = [np.full((64, 64, 3), v, np.uint8) for v in (40, 120, 200)]
    out = [dec.decode(e.encode(f)[0]) for f in frames]
    e.close()
    assert all(len(o) == 1 for o in out)  # one packet per frame, no delay
    assert abs(int(out[-1][0].mean()) - 200) < 10
