"""Webcam driving: ``image`` messages tracked on the server into frames, and the errors that
leave the session going; the ``telesplat track`` parameter files."""

from __future__ import annotations

import asyncio
import json

import cv2
import numpy as np

from protocol import DEFAULT_LIMITS, Drive, Image, encode
from tests.server_fixtures import (
    is_type,
    recv_until,
    server_fixture,  # noqa: F401 (the `server` fixture)
    stream,
)
from tests.track_models import needs_models


def astronaut_jpeg(scale: float = 1.0) -> bytes:
    from skimage import data as skimage_data

    bgr = skimage_data.astronaut()[..., ::-1]
    if scale != 1.0:
        bgr = cv2.resize(bgr, None, fx=scale, fy=scale)
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 90])
    assert ok
    return buf.tobytes()


@needs_models
def test_image_message_drives_a_frame_with_tracking_time(server):
    async def run():
        async with stream(server) as ws:
            await ws.send(encode(Image(seq=7, data=astronaut_jpeg())))
            frame = await recv_until(ws, is_type("frame", seq=7), timeout=60)
            assert frame.timings.track > 0
            # The next drive's frame reports no tracking time.
            await ws.send(encode(Drive(seq=8, smplx={"jaw_pose": [0.2, 0.0, 0.0]})))
            frame = await recv_until(ws, is_type("frame", seq=8), timeout=30)
            assert frame.timings.track == 0
    asyncio.run(run())


def test_bad_images_get_errors_and_the_session_goes_on(server):
    big = np.zeros((2000, 2000, 3), np.uint8)  # 4 Mpx > max_image_pixels, a small PNG
    ok, png = cv2.imencode(".png", big)
    assert ok and len(png) < DEFAULT_LIMITS.max_image_bytes

    async def run():
        async with stream(server) as ws:
            await ws.send(encode({"type": "image", "seq": 1, "format": "jpeg", "data": b""}))
            err = await recv_until(ws, is_type("error"), timeout=30)
            assert err.code == "invalid" and "empty" in err.message
            for seq, data in ((2, b"\xff\xd8 not really a jpeg"), (3, png.tobytes())):
                await ws.send(encode(Image(seq=seq, data=data)))
                err = await recv_until(ws, is_type("error"), timeout=60)
                # Without the landmark models every image is "unsupported", with the reason.
                assert err.code in ("invalid", "unsupported"), err
                assert err.answers.seq == seq
            await ws.send(encode(Drive(seq=4, smplx={"jaw_pose": [0.1, 0.0, 0.0]})))
            await recv_until(ws, is_type("frame", seq=4), timeout=30)
    asyncio.run(run())


def _astronaut_video(path, frames: int = 3) -> None:
    from skimage import data as skimage_data

    bgr = np.ascontiguousarray(skimage_data.astronaut()[..., ::-1])
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (512, 512))
    for _ in range(frames):
        writer.write(bgr)
    writer.release()


@needs_models
def test_track_fit_cli_writes_a_motion_file(tmp_path):
    from avatar_core.cli import main
    from client.motion_file import load_motion

    video = tmp_path / "clip.avi"
    _astronaut_video(video)
    out = tmp_path / "params.json"
    assert main(["track", str(video), "--out", str(out)]) == 0  # short for `track fit`
    frames = json.loads(out.read_text())
    assert len(frames) == 3 and np.asarray(frames[0]["body_pose"]).shape == (21, 3)
    assert len(load_motion(out)) == 3
    npz = tmp_path / "params.npz"
    assert main(["track", "fit", "--image", str(tmp_path / "x.png"), "--out", str(npz)]) == 2


@needs_models
def test_client_drive_tracks_locally_and_drives(server, tmp_path):
    from client.cli import main

    video = tmp_path / "clip.avi"
    _astronaut_video(video, frames=2)
    out = tmp_path / "frames"
    assert main(["drive", "--server", server.url, "--token", server.token, "--avatar", "demo",
                 "--video", str(video), "--out", str(out), "--quiet"]) == 0
    assert len(list(out.iterdir())) == 2
