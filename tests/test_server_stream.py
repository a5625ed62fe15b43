"""The streaming session over a real server and WebSocket: frames, views, latest-wins,
errors that leave the session going, fuzzed input, and the frame formats."""

import asyncio

import cv2
import msgpack
import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from protocol import Drive, Image, Orbit, Ping, ProtocolError, Request, View, decode_client, encode
from server.stream.encoders import H264Decoder, decode_depth_png
from tests.server_fixtures import (
    is_type,
    recv_until,
    server_fixture,  # noqa: F401 (the `server` fixture)
    stream,
)

RNG = np.random.default_rng(0)


def decode_image(frame) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(frame.data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img is not None, f"{frame.codec} frame does not decode"
    return img


def pose(seed: int, scale: float = 0.3) -> dict:
    rng = np.random.default_rng(seed)
    return {"body_pose": rng.normal(0, scale, (21, 3)), "global_orient": [0.0, 0.0, 0.0]}


async def _next_frame(ws, seq=None):
    if seq is None:
        return await recv_until(ws, is_type("frame"))
    return await recv_until(ws, is_type("frame", seq=seq))


def test_welcome_then_rest_frame_then_drive_frame(server):
    async def run():
        async with stream(server) as ws:
            w = ws.welcome
            assert w.avatar.id == "demo" and w.avatar.owner == "public"
            assert w.request.width == 128 and w.request.codec == "jpeg"
            assert set(w.codecs) == {"jpeg", "png", "h264"}
            first = await _next_frame(ws)
            assert first.seq == -1 and first.width == first.height == 128
            await ws.send(encode(Drive(seq=7, smplx=pose(1))))
            frame = await _next_frame(ws, seq=7)
            img = decode_image(frame)
            assert img.shape == (128, 128, 3)
            assert frame.timings.render > 0 and frame.timings.track == 0
            assert not np.array_equal(img, decode_image(first))
    asyncio.run(run())


def test_view_change_changes_the_image(server):
    async def run():
        async with stream(server) as ws:
            front = decode_image(await _next_frame(ws)).astype(int)
            await ws.send(encode(View(orbit=Orbit(yaw_deg=90))))
            side = decode_image(await _next_frame(ws)).astype(int)
            assert np.abs(front - side).mean() > 5
            # Back where it was: once still, the view's full-quality frame (a second change
            # this soon is a movement, whose frames are previews: tests/test_moving_views.py)
            await ws.send(encode(View(orbit=Orbit(yaw_deg=0))))
            again = await recv_until(ws, lambda m: m.type == "frame" and not m.preview)
            again = decode_image(again).astype(int)
            assert np.abs(front - again).mean() < 2
    asyncio.run(run())


def test_latest_input_wins(server):
    async def run():
        async with stream(server) as ws:
            await _next_frame(ws)
            for i in range(50):
                await ws.send(encode(Drive(seq=i, smplx=pose(i))))
            seen = []
            last = await recv_until(ws, is_type("frame", seq=49), seen=seen)
            frames = [m for m in seen if m.type == "frame"] + [last]
            assert len(frames) < 25, f"{len(frames)} frames for 50 drives: queued, not coalesced"
            seqs = [f.seq for f in frames]
            assert seqs == sorted(seqs)
            stats = await recv_until(ws, is_type("stats"))
            assert stats.coalesced >= 50 - len(frames) - 1 and stats.frames >= len(frames)
    asyncio.run(run())


def test_ping_pong_and_stats(server):
    async def run():
        async with stream(server) as ws:
            await ws.send(encode(Ping(t=12.5)))
            pong = await recv_until(ws, is_type("pong"))
            assert pong.t == 12.5
            stats = await recv_until(ws, is_type("stats"), timeout=5)
            assert stats.frames >= 1 and stats.sessions >= 1 and stats.render_ms > 0
    asyncio.run(run())


def test_corrupt_image_gets_an_error_and_the_session_goes_on(server):
    # "invalid" when the tracking models are there (the JPEG is corrupt), "unsupported" when
    # they cannot be loaded; tests/test_track_drive.py covers each case.
    async def run():
        async with stream(server) as ws:
            await ws.send(encode(Image(seq=3, data=b"\xff\xd8 not really a jpeg")))
            err = await recv_until(ws, is_type("error"))
            assert err.code in ("invalid", "unsupported") and err.answers.seq == 3
            await ws.send(encode(Drive(seq=4, smplx=pose(4))))
            await _next_frame(ws, seq=4)
    asyncio.run(run())


def test_bad_messages_get_errors_and_the_session_goes_on(server):
    bad = [
        (b"\xc1\xc1garbage", "bad_message"),
        (msgpack.packb([1, 2, 3]), "bad_message"),
        (msgpack.packb({"type": "dance"}), "bad_message"),
        (msgpack.packb({"type": "drive", "seq": 5, "smplx": {"body_pose": [1.0, 2.0]}}),
         "invalid"),
        (msgpack.packb({"type": "drive", "seq": 6, "smplx": {"tail": [1.0]}}), "invalid"),
        (msgpack.packb({"type": "request", "width": 100000}), "too_large"),
        (msgpack.packb({"type": "request", "codec": "gif"}), "invalid"),
    ]

    async def run():
        async with stream(server) as ws:
            await ws.send("a text frame")
            err = await recv_until(ws, is_type("error"))
            assert err.code == "bad_message"
            for data, code in bad:
                await ws.send(data)
                err = await recv_until(ws, is_type("error"))
                assert err.code == code, (data, err)
            await ws.send(msgpack.packb({"type": "drive", "seq": 5, "smplx": {
                "body_pose": [1.0, 2.0]}}))
            err = await recv_until(ws, is_type("error"))
            assert err.answers.type == "drive" and err.answers.seq == 5
            # Fits the protocol but not this avatar: PCA hand coefficients on a full-pose model.
            await ws.send(encode(Drive(seq=8, smplx={"left_hand_pose": np.zeros(6)})))
            err = await recv_until(ws, is_type("error"))
            assert err.code == "invalid" and err.answers.seq == 8
            await ws.send(encode(Drive(seq=9, smplx=pose(9))))
            await _next_frame(ws, seq=9)
    asyncio.run(run())


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=300))
def test_codec_refuses_random_bytes_with_protocol_errors_only(data):
    try:
        decode_client(data)
    except ProtocolError:
        pass


message_maps = st.fixed_dictionaries(
    {"type": st.sampled_from(["drive", "view", "request", "ping", "hello", "image", "x"])},
    optional={"seq": st.one_of(st.integers(-5, 2**60), st.text(max_size=3)),
              "smplx": st.dictionaries(st.sampled_from(["body_pose", "betas", "jaw_pose", "q"]),
                                       st.lists(st.floats(allow_nan=True), max_size=70),
                                       max_size=2),
              "orbit": st.dictionaries(st.sampled_from(["yaw_deg", "distance"]),
                                       st.floats(-1e3, 1e3), max_size=2),
              "width": st.integers(-10, 5000), "codec": st.text(max_size=5),
              "data": st.binary(max_size=20)})


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.one_of(st.binary(max_size=200), message_maps.map(msgpack.packb)),
                min_size=1, max_size=5))
def test_fuzzed_messages_never_end_the_session(server, messages):
    async def run():
        async with stream(server) as ws:
            for data in messages:
                await ws.send(data)
            await ws.send(encode(Ping(t=1.0)))
            await recv_until(ws, is_type("pong", t=1.0))  # still answering
    asyncio.run(run())


def test_depth_and_alpha_outputs(server):
    async def run():
        async with stream(server) as ws:
            await ws.send(encode(Request(outputs=["rgb", "alpha", "depth"],
                                         background=(0.0, 0.0, 0.0))))
            frame = await recv_until(ws, lambda m: m.type == "frame" and m.codec == "png")
            rgba = decode_image(frame)
            assert rgba.shape == (128, 128, 4)
            alpha = rgba[..., 3]
            assert alpha.max() == 255 and alpha.min() == 0
            depth = decode_depth_png(frame.depth)
            assert depth.shape == (128, 128)
            body = depth[alpha > 250]
            assert 2.0 < np.median(body) < 3.4  # the orbit camera stands 2.7 m away
            assert np.all(depth[alpha == 0] == 0)
    asyncio.run(run())


def test_png_and_jpeg_quality_while_moving(server):
    async def run():
        async with stream(server) as ws:
            still = await _next_frame(ws)
            await ws.send(encode(View(orbit=Orbit(), moving=True)))
            moving = await _next_frame(ws)
            assert len(moving.data) < len(still.data)
            await ws.send(encode(Request(codec="png")))
            png = await recv_until(ws, lambda m: m.type == "frame" and m.codec == "png")
            assert decode_image(png).shape == (128, 128, 3)
    asyncio.run(run())


def test_h264_frames_decode_and_restart_on_resize(server):
    async def run():
        async with stream(server) as ws:
            await ws.send(encode(Request(codec="h264")))
            decoder = H264Decoder()
            first = await recv_until(ws, lambda m: m.type == "frame" and m.codec == "h264")
            assert first.keyframe
            images = decoder.decode(first.data)
            for i in range(3):
                await ws.send(encode(Drive(seq=i, smplx=pose(i))))
                frame = await _next_frame(ws, seq=i)
                assert frame.codec == "h264"
                images += decoder.decode(frame.data)
            assert len(images) == 4 and images[-1].shape == (128, 128, 3)
            ref = cv2.imdecode(np.frombuffer((await _jpeg_of(ws, 2)).data, np.uint8),
                               cv2.IMREAD_COLOR)[..., ::-1]
            assert np.abs(images[-1].astype(int) - ref).mean() < 6
            await ws.send(encode(Request(codec="h264", width=96, height=64)))
            resized = await recv_until(ws, lambda m: m.type == "frame" and m.width == 96)
            assert resized.keyframe and resized.height == 64
            assert H264Decoder().decode(resized.data)[0].shape == (64, 96, 3)
            await ws.send(encode(Request(width=97)))
            err = await recv_until(ws, is_type("error"))
            assert err.code == "unsupported"
    asyncio.run(run())


async def _jpeg_of(ws, seq):
    """Switch to JPEG at quality 100 and return the next frame (same state)."""
    await ws.send(encode(Request(codec="jpeg", jpeg_quality=100)))
    return await recv_until(ws, lambda m: m.type == "frame" and m.codec == "jpeg" and
                            m.seq == seq)


def test_face_and_hands_are_fused(server):
    async def run():
        async with stream(server) as ws:
            rest = decode_image(await _next_frame(ws)).astype(int)
            await ws.send(encode(Drive(seq=1, flame={"expr": np.full(50, 1.5),
                                                     "jaw_pose": [0.4, 0.0, 0.0]},
                                       mano_left={"hand_pose": RNG.normal(0, 0.5, (15, 3)),
                                                  "global_orient": [0.0, 1.0, 0.0]})))
            frame = await _next_frame(ws, seq=1)
            assert np.abs(decode_image(frame).astype(int) - rest).mean() > 0.1
            await ws.send(encode(Drive(seq=2, reset=True)))
            back = decode_image(await _next_frame(ws, seq=2)).astype(int)
            assert np.abs(back - rest).mean() < 1
    asyncio.run(run())
