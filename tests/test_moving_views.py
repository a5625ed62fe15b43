"""Moving views render previews: a real server and WebSocket. While a participant's view moves
(view.moving, or its camera changed twice within the settle time) its frames are marked
``preview`` and rendered at moving_view_scale of the size, upscaled back; once the view is
still, one full-quality frame follows with no further input, and it equals the normal render."""

import asyncio
import math

import cv2
import numpy as np
import pytest
import torch

from protocol import Orbit, Request, View, encode
from server.stream.view_motion import MovingViewCost, ViewMotion
from tests.server_fixtures import is_type, recv_until, run_server, stream

SETTLE_MS = 300.0  # generous: a loaded machine delays the test's own messages
SIZE = 128


def image(frame) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(frame.data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img is not None
    return img


def orbit(yaw: float, moving: bool = False) -> bytes:
    return encode(View(orbit=Orbit(yaw_deg=yaw), moving=moving))


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    with run_server(tmp_path_factory.mktemp("moving"), moving_view_settle_ms=SETTLE_MS,
                    moving_view_scale=0.5) as srv:
        yield srv


def frame_where(predicate):
    return lambda m: m.type == "frame" and m.codec == "png" and predicate(m)


async def normal_render(server, yaw: float, size: int = SIZE) -> np.ndarray:
    """What a fresh session sees at ``yaw`` (one view change: never a preview)."""
    async with stream(server) as ws:
        await ws.send(encode(Request(codec="png", width=size, height=size)))
        await ws.send(orbit(yaw))
        await recv_until(ws, frame_where(lambda m: m.width == size))
        await ws.send(orbit(yaw))  # the same camera again: a frame of this state, not a move
        frame = await recv_until(ws, frame_where(lambda m: m.width == size))
        assert not frame.preview
        return image(frame)


def test_a_dragged_view_previews_at_half_size_then_ends_with_the_normal_render(server):
    async def run():
        async with stream(server) as ws:
            await ws.send(encode(Request(codec="png")))
            await recv_until(ws, frame_where(lambda m: not m.preview))
            await ws.send(orbit(40.0, moving=True))
            preview = await recv_until(ws, frame_where(lambda m: m.preview))
            assert (preview.width, preview.height) == (SIZE, SIZE)
            await ws.send(orbit(40.0, moving=False))  # the drag ends where it was
            full = await recv_until(ws, frame_where(lambda m: not m.preview))
        assert np.array_equal(image(full), await normal_render(server, 40.0))
        # the preview is the half-size render, upscaled (bilinear; rounding apart)
        half = torch.from_numpy(await normal_render(server, 40.0, SIZE // 2)).float()
        up = torch.nn.functional.interpolate(half.permute(2, 0, 1)[None], size=(SIZE, SIZE),
                                             mode="bilinear", align_corners=False)[0]
        expected = up.permute(1, 2, 0).round().numpy()
        assert np.abs(image(preview).astype(float) - expected).max() <= 2
        assert not np.array_equal(image(preview), image(full))
    asyncio.run(run())


def test_views_changing_fast_preview_and_a_still_view_gets_its_full_frame_unasked(server):
    async def run():
        async with stream(server) as ws:
            await ws.send(encode(Request(codec="png")))
            await recv_until(ws, frame_where(lambda m: True))
            for i in range(1, 8):  # an orbit without view.moving, 25 ms a step
                await ws.send(orbit(5.0 * i))
                await asyncio.sleep(0.025)
            last_yaw = 35.0
            await recv_until(ws, frame_where(lambda m: m.preview))
            # then, with nothing sent since the last view, its full frame
            full = await recv_until(ws, frame_where(lambda m: not m.preview))
        assert np.array_equal(image(full), await normal_render(server, last_yaw))
    asyncio.run(run())


def test_view_motion_rules():
    motion = ViewMotion(settle_s=0.1)
    motion.update(View(orbit=Orbit()), 0.0)          # the session's first view
    assert not motion.moving(0.0)
    motion.update(View(orbit=Orbit(yaw_deg=10)), 1.0)  # one change: a jump, not a drag
    assert not motion.moving(1.0)
    motion.update(View(orbit=Orbit(yaw_deg=10)), 1.05)  # the same camera: no change
    assert not motion.moving(1.05)
    motion.update(View(orbit=Orbit(yaw_deg=20)), 1.06)  # a second change within 0.1 s
    assert motion.moving(1.1) and not motion.moving(1.17)
    assert math.isclose(motion.still_at(), 1.16)
    motion.update(View(orbit=Orbit(yaw_deg=20), moving=True), 5.0)  # the client drags
    assert motion.moving(9.0) and motion.still_at() == math.inf
    motion.update(View(orbit=Orbit(yaw_deg=20)), 9.0)   # it let go where it was
    assert not motion.moving(9.0)


def test_moving_view_cost_refuses_bad_values():
    for bad in ({"render_scale": 0.0}, {"render_scale": 1.5}, {"quality": 0.0},
                {"settle_s": -1.0}, {"settle_s": math.inf}):
        with pytest.raises(ValueError):
            MovingViewCost(**bad)
    assert not MovingViewCost(render_scale=1.0, quality=1.0).cheaper
    assert MovingViewCost(render_scale=1.0, quality=0.5).cheaper


def test_frame_message_marks_previews():
    from protocol import decode_server
    from protocol.messages import Frame

    msg = decode_server(encode(Frame(seq=1, frame=2, codec="jpeg", width=16, height=16, data=b"x",
                              preview=True)))
    assert msg.preview is True
    assert is_type("frame", preview=True)(msg)
