"""/v1/motions: the motion library as per-frame drives for a given avatar."""

import asyncio

import httpx
import numpy as np

from protocol import Drive, encode
from tests.server_fixtures import is_type, recv_until, server_fixture  # noqa: F401


def test_list_and_sample_a_clip(server):
    h = server.headers()
    listed = httpx.get(f"{server.url}/v1/motions", headers=h, timeout=30).json()["motions"]
    names = {m["name"]: m for m in listed}
    assert {"smile", "thumbs_up", "talk_calm"} <= set(names)
    assert {m["category"] for m in listed} == {"expressions", "gestures", "conversation"}

    r = httpx.get(f"{server.url}/v1/motions/talk", params={"avatar": "demo", "fps": 10},
                  headers=h, timeout=60)
    assert r.status_code == 200
    clip = r.json()
    assert clip["name"] == "talk_calm" and clip["fps"] == 10
    assert len(clip["frames"]) == round(clip["duration"] * 10) + 1
    frame = clip["frames"][len(clip["frames"]) // 2]["smplx"]
    assert "betas" not in frame  # a clip never replaces the avatar's identity
    assert np.asarray(frame["body_pose"]).shape == (21, 3)
    jaw = np.array([f["smplx"]["jaw_pose"] for f in clip["frames"]])
    assert np.ptp(jaw) > 0  # the mouth moves while talking

    # Each frame is a valid drive body, and it drives the avatar.
    async def drive():
        from websockets.asyncio.client import connect

        async with connect(server.ws_url("demo", token=server.token)) as ws:
            await recv_until(ws, is_type("welcome"))
            await ws.send(encode(Drive(seq=7, **clip["frames"][3])))
            msg = await recv_until(ws, lambda m: m.type == "frame" and m.seq == 7)
            assert msg.data

    asyncio.run(drive())


def test_unknown_motion_avatar_fps_and_auth(server):
    h = server.headers()
    assert httpx.get(f"{server.url}/v1/motions/nope", params={"avatar": "demo"},
                     headers=h, timeout=30).status_code == 404
    assert httpx.get(f"{server.url}/v1/motions/smile", params={"avatar": "nope"},
                     headers=h, timeout=30).status_code == 404
    assert httpx.get(f"{server.url}/v1/motions/smile", params={"avatar": "demo", "fps": 0},
                     headers=h, timeout=30).status_code == 422
    assert httpx.get(f"{server.url}/v1/motions", timeout=30).status_code == 401
