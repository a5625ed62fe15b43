"""The WebRTC pieces without a network: frame stamps (also through VP8 / H.264 at 500 kbit/s),
the clamped encoders, the latest-frame track, the ICE settings."""

from __future__ import annotations

import asyncio
import fractions

import numpy as np
import pytest

from protocol.stamp import read_stamp, stamp
from server.config import Settings

pytest.importorskip("aiortc")


@pytest.mark.parametrize("width", [64, 128, 512, 1024])
def test_stamps_read_back_and_unstamped_frames_read_none(width):
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 256, (width // 2, width, 3), dtype=np.uint8)
    for seq in (0, 1, 4242, 2**24 - 1):
        assert read_stamp(stamp(frame.copy(), seq)) == seq
    assert read_stamp(stamp(frame.copy(), 2**24 + 5)) == 5  # the low 24 bits
    assert read_stamp(frame) is None
    assert read_stamp(np.zeros((width, width, 3), np.uint8)) is None  # black: no marker
    assert read_stamp(np.full((width, width, 3), 255, np.uint8)) is None


def test_stamps_refuse_what_cannot_hold_them():
    with pytest.raises(ValueError, match="at least 64 px wide"):
        stamp(np.zeros((64, 32, 3), np.uint8), 1)
    with pytest.raises(ValueError, match="uint8"):
        stamp(np.zeros((64, 64, 3), np.float32), 1)
    assert read_stamp(np.zeros((64, 32, 3), np.uint8)) is None
    assert read_stamp(np.zeros((64, 64), np.uint8)) is None


@pytest.mark.parametrize("codec", ["vp8", "h264"])
def test_stamps_survive_the_video_codecs_at_500_kbit(codec):
    """Stamped frames of a busy picture through aiortc's own encoder at 500 kbit/s, decoded
    with its decoder: every frame reads its seq back."""
    from aiortc.codecs import get_decoder, get_encoder
    from aiortc.jitterbuffer import JitterFrame
    from aiortc.rtcrtpparameters import RTCRtpCodecParameters

    from server.webrtc.encoders import ENCODERS

    mime = f"video/{codec}"
    encoder = ENCODERS[mime](100_000, 500_000, clock=FrameClock())  # sent at 30 fps
    encoder.target_bitrate = 10**9
    decoder = get_decoder(RTCRtpCodecParameters(mimeType=mime, clockRate=90000))
    assert get_encoder  # aiortc's factory exists (ours replaces its product per sender)
    depayload = {"vp8": "aiortc.codecs.vpx:vp8_depayload",
                 "h264": "aiortc.codecs.h264:h264_depayload"}[codec]
    module, name = depayload.split(":")
    depay = getattr(__import__(module, fromlist=[name]), name)
    import av

    rng = np.random.default_rng(1)
    read = []
    for seq in range(6):
        rgb = rng.integers(0, 256, (256, 256, 3), dtype=np.uint8)  # noise: the codec's worst
        frame = av.VideoFrame.from_ndarray(stamp(rgb, 1000 + seq), format="rgb24")
        frame.pts, frame.time_base = seq * 3000, fractions.Fraction(1, 90000)
        payloads, timestamp = encoder.encode(frame, force_keyframe=seq == 0)
        data = b"".join(depay(p) for p in payloads)
        for out in decoder.decode(JitterFrame(data=data, timestamp=timestamp)):
            read.append(read_stamp(out.to_ndarray(format="rgb24")))
    assert encoder.target_bitrate == 500_000  # clamped to our cap, not aiortc's
    assert read == [1000 + seq for seq in range(6)]


class FrameClock:
    """A sending clock that moves on 1/30 s each time it is read."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        self.now += 1 / 30
        return self.now


@pytest.mark.parametrize("codec", ["vp8", "h264"])
def test_the_codec_counts_sending_time_and_the_wire_keeps_the_frames_timestamps(codec):
    """Frames stamped one tick apart, or seconds apart (the capture clock when the picture's
    lag moves), encode to the same bytes as frames stamped 1/30 s apart when sent at 30 fps;
    each keeps its own timestamp for the RTP packets."""
    import av
    from aiortc.codecs.h264 import h264_depayload
    from aiortc.codecs.vpx import vp8_depayload

    from bench.encoder_clock import picture
    from server.webrtc.encoders import ENCODERS

    depay = vp8_depayload if codec == "vp8" else h264_depayload
    # a moving picture, not noise (that costs qmax either way): aiortc's VP8 encoder fed
    # one-tick timestamps spends a fraction of the bytes on it
    pictures = [picture(i, 64) for i in range(12)]
    patterns = {"even": [i * 3000 for i in range(12)],
                "one tick": [5 + i for i in range(12)],
                "jumps": [(i // 4) * 90_000 * 3 + i for i in range(12)]}
    streams = {}
    for name, stamps in patterns.items():
        encoder = ENCODERS[f"video/{codec}"](100_000, 500_000, clock=FrameClock())
        out = []
        for rgb, pts in zip(pictures, stamps, strict=True):
            frame = av.VideoFrame.from_ndarray(rgb, format="rgb24")
            frame.pts, frame.time_base = pts, fractions.Fraction(1, 90000)
            payloads, timestamp = encoder.encode(frame)
            assert timestamp == pts
            out.append(b"".join(depay(p) for p in payloads))  # the codec's own bytes
        streams[name] = out
    assert all(streams["even"]), "every frame was encoded"
    assert streams["one tick"] == streams["even"]
    assert streams["jumps"] == streams["even"]


@pytest.mark.parametrize("mime", ["video/vp8", "video/h264"])
def test_encoders_clamp_to_the_settings_not_aiortcs_bounds(mime):
    from server.webrtc.encoders import ENCODERS

    encoder = ENCODERS[mime](50_000, 8_000_000)
    encoder.target_bitrate = 10_000
    assert encoder.target_bitrate == 50_000  # below aiortc's own floor
    encoder.target_bitrate = 7_000_000
    assert encoder.target_bitrate == 7_000_000  # above aiortc's own ceiling
    encoder.target_bitrate = 10**10
    assert encoder.target_bitrate == 8_000_000


def test_the_track_hands_over_the_newest_frame_and_repeats_only_when_idle():
    from server.webrtc.track import LatestFrameTrack

    async def run():
        track = LatestFrameTrack(repeat_after_s=0.05)
        frames = [np.full((16, 16, 3), v, np.uint8) for v in (10, 20, 30)]
        first = asyncio.create_task(track.deliver(frames[0]))
        second = asyncio.create_task(track.deliver(frames[1]))  # supersedes the first
        await asyncio.sleep(0)
        await asyncio.wait_for(first, 1)  # settled: replaced, not queued
        got = await track.recv()
        await asyncio.wait_for(second, 1)  # taken
        repeat = await track.recv()  # nothing new within repeat_after_s
        third = asyncio.create_task(track.deliver(frames[2]))
        newest = await track.recv()
        await third
        track.stop()
        return got, repeat, newest, track

    got, repeat, newest, track = asyncio.run(run())
    assert got.to_ndarray(format="rgb24")[0, 0, 0] == 20
    assert repeat.to_ndarray(format="rgb24")[0, 0, 0] == 20 and repeat.pts > got.pts
    assert newest.to_ndarray(format="rgb24")[0, 0, 0] == 30 and newest.pts > repeat.pts
    assert (track.sent, track.repeated) == (2, 1)


def test_ice_servers_are_settings_and_none_by_default():
    from server.webrtc.negotiate import configuration

    assert configuration(Settings()).iceServers == []  # not aiortc's public STUN default
    s = Settings(webrtc_ice_servers="stun:stun.example.org:3478, turn:turn.example.org",
                 webrtc_turn_username="u", webrtc_turn_credential="p")
    servers = configuration(s).iceServers
    assert [x.urls for x in servers] == ["stun:stun.example.org:3478", "turn:turn.example.org"]
    assert servers[1].username == "u" and servers[0].username is None
    with pytest.raises(ValueError, match="stun:"):
        Settings(webrtc_ice_servers=["http://example.org"])
    with pytest.raises(ValueError, match="exceeds"):
        Settings(webrtc_min_bitrate=2_000_000, webrtc_max_bitrate=1_000_000)
