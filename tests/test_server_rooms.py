"""Rooms over real sockets: a performer drives, viewers watch from their own views; refusals
with their codes; seats in one rasterize call with depth order across avatars; a stalled viewer
slows nobody; posing and rendering shared between participants (issue 14)."""

import asyncio
import contextlib
import math
import socket
import time

import cv2
import httpx
import numpy as np
import pytest
import websockets

from protocol import PROTOCOL_MINOR, Drive, Hello, Image, Orbit, Ping, Request, View, encode
from server.stream import scene as room_frames
from server.stream.drive import DriveState, fit_drive
from server.stream.scene import view_camera
from tests.server_fixtures import (
    WS_TIMEOUT_S,
    count_frames,
    is_type,
    recv_until,
    run_server,
    wait_until,
    ws_connect,
)

SIZE = 96


@pytest.fixture(scope="module")
def srv(tmp_path_factory):
    with run_server(tmp_path_factory.mktemp("rooms"), max_sessions=16, default_width=SIZE,
                    default_height=SIZE, room_seat_hold_s=0.2, room_seat_ease_s=0.2,
                    default_max_fps=30) as running:
        yield running


# -- helpers ----------------------------------------------------------------------------------


def rest(srv, method: str, path: str, token: str | None = None, **kwargs) -> httpx.Response:
    with httpx.Client(base_url=srv.url, headers=srv.headers(token), timeout=30) as c:
        return c.request(method, path, **kwargs)


def create_room(srv, seats=None, token=None) -> dict:
    body = {} if seats is None else {"seats": seats}
    r = rest(srv, "POST", "/v1/rooms", token, json=body)
    assert r.status_code == 201, r.text
    assert r.headers["location"] == f"/v1/rooms/{r.json()['id']}"
    return r.json()


def invite(srv, room_id: str, scope: str, **body) -> dict:
    r = rest(srv, "POST", f"/v1/rooms/{room_id}/invitations", json={"scope": scope, **body})
    assert r.status_code == 201, r.text
    return r.json()


def room_url(srv, room_id: str) -> str:
    return srv.url.replace("http://", "ws://") + f"/v1/stream?room={room_id}"


@contextlib.asynccontextmanager
async def join(srv, room_id: str, token: str, *, welcome: bool = True, **hello):
    """A room's WebSocket after its hello (and, unless ``welcome=False``, its welcome)."""
    extra = {k: hello.pop(k) for k in ("sock", "max_queue") if k in hello}
    async with ws_connect(room_url(srv, room_id), **extra) as ws:
        await ws.send(encode(Hello(token=token, **hello)))
        if welcome:
            ws.welcome = await recv_until(ws, is_type("welcome"))
        yield ws


async def refused(srv, room_id: str, token: str, **hello) -> tuple[str, int]:
    """(error code, close code) of a join the server refuses."""
    async with join(srv, room_id, token, welcome=False, **hello) as ws:
        err = await recv_until(ws, is_type("error"))
        with pytest.raises(websockets.ConnectionClosed) as closed:
            await asyncio.wait_for(ws.recv(), WS_TIMEOUT_S)
        return err.code, closed.value.rcvd.code


def jaw(seq: int, angle: float) -> bytes:
    return encode(Drive(seq=seq, smplx={"jaw_pose": np.array([angle, 0.0, 0.0])}))


def decode_png(data: bytes, flags=cv2.IMREAD_COLOR) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(data, np.uint8), flags).astype(np.float64)


def live(srv, room_id: str):
    return srv.ctx.rooms.get(room_id).live


# -- a performer drives, a viewer watches -----------------------------------------------------


def mouth_box(srv, view: View, width: int, height: int, angle: float) -> tuple[int, ...]:
    """Pixel box (x0, y0, x1, y1) of the vertices a jaw rotation moves, projected with the
    viewer's camera."""
    animator, manos = srv.ctx.session_models("demo")
    model = animator.body_model
    states = []
    for a in (0.0, angle):
        state = DriveState()
        drive = Drive(seq=0, smplx={"jaw_pose": np.array([a, 0.0, 0.0])})
        state.apply(drive, fit_drive(drive, live_shapes(model, manos)))
        states.append(animator.pose(state.smplx_params(model, manos)).vertices.numpy().copy())
    moved = np.linalg.norm(states[1] - states[0], axis=1) > 0.003
    assert moved.sum() > 10, "the jaw moves some vertices"
    pts = np.concatenate([states[0][moved], states[1][moved]])
    cam = view_camera(view, width, height, np.zeros(3))
    uv, z = cam.project(pts)
    assert (z > 0).all()
    x0, y0 = np.floor(uv.min(0)).astype(int)
    x1, y1 = np.ceil(uv.max(0)).astype(int)
    return max(0, x0), max(0, y0), min(width, x1 + 1), min(height, y1 + 1)


def live_shapes(model, manos):
    from server.stream.drive import drive_shapes

    return drive_shapes(model, manos)


def test_a_performers_jaw_reaches_the_viewer_and_the_viewers_view_stays_its_own(srv):
    room = create_room(srv)
    watch = invite(srv, room["id"], "watch")
    perform = invite(srv, room["id"], "perform")
    assert perform["seat"] == 0 and watch["link"] == f"/?room={room['id']}#token={watch['token']}"
    head = srv.ctx.session_models("demo")[0].body_model.joint_template[15]
    face = View(orbit=Orbit(target=tuple(float(v) for v in head), distance=0.8))
    angle = 0.5

    async def run():
        async with join(srv, room["id"], perform["token"], name="cam") as performer, \
                join(srv, room["id"], watch["token"], client="viewer") as viewer:
            assert performer.welcome.room.role == "perform"
            assert performer.welcome.minor == PROTOCOL_MINOR
            assert viewer.welcome.room.role == "watch" and viewer.welcome.room.seat is None
            presence = await recv_until(viewer, is_type("presence"))
            assert presence.seats[0].performer == "cam" and presence.viewers == 1
            await viewer.send(encode(Request(codec="png")))
            await viewer.send(encode(face))
            await performer.send(encode(Request(codec="png")))
            await performer.send(jaw(1, 0.0))
            closed = await recv_until(viewer, lambda m: m.type == "frame" and m.seq == 1
                                      and m.codec == "png")
            mine = await recv_until(performer, lambda m: m.type == "frame" and m.seq == 1
                                    and m.codec == "png")
            await performer.send(jaw(2, angle))
            opened = await recv_until(viewer, is_type("frame", seq=2))
            # The viewer turns away: its frames change, the performer's do not.
            await viewer.send(encode(View(orbit=Orbit(yaw_deg=70))))
            await performer.send(jaw(3, 0.0))
            turned = await recv_until(viewer, is_type("frame", seq=3))
            mine_after = await recv_until(performer, is_type("frame", seq=3))
            return closed, opened, mine, mine_after, turned

    closed, opened, mine, mine_after, turned = asyncio.run(run())
    a, b = decode_png(closed.data), decode_png(opened.data)
    x0, y0, x1, y1 = mouth_box(srv, face, SIZE, SIZE, angle)
    diff = np.abs(a - b).sum(axis=2)
    inside = diff[y0:y1, x0:x1]
    assert inside.mean() > 5, (inside.mean(), (x0, y0, x1, y1))  # the mouth opened
    outside = diff.sum() - inside.sum()
    assert inside.sum() > 0.8 * (inside.sum() + outside)  # and little else changed
    # The performer's own frames (same pose, its own view) are unchanged by the viewer's view.
    before, after = decode_png(mine.data), decode_png(mine_after.data)
    assert np.abs(before - after).mean() < 0.5
    assert np.abs(decode_png(turned.data) - decode_png(closed.data)).mean() > 5


def test_a_late_joiner_gets_the_current_pose_and_presence_tracks_hold_and_rest(srv):
    room = create_room(srv)

    async def run():
        async with join(srv, room["id"], srv.token, client="owner") as performer:
            await performer.send(jaw(41, 0.4))
            await recv_until(performer, is_type("frame", seq=41))
            async with join(srv, room["id"], srv.token, role="watch", name="late") as late:
                first = await recv_until(late, is_type("frame"))
                assert first.seq == 41  # the current pose at once
                joined = await recv_until(performer, is_type("presence", event="join"))
                assert joined.who == "late" and joined.viewers == 1
        async with join(srv, room["id"], srv.token, role="watch", client="watcher") as viewer:
            # The performer left: the seat holds its pose, then eases to rest (0.2 s + 0.2 s).
            hello = await recv_until(viewer, is_type("presence"))
            assert hello.seats[0].performer is None
            if hello.seats[0].holding:
                rested = await recv_until(viewer, is_type("presence", event="update"))
                assert not rested.seats[0].holding
            seat = live(srv, room["id"]).seats[0]
            assert not seat.holding and not any(seat.drive.families.values())

    asyncio.run(run())


# -- refusals -----------------------------------------------------------------------------------


def test_refusals_have_their_codes(srv):
    a, b = create_room(srv), create_room(srv)
    watch_a = invite(srv, a["id"], "watch")
    perform_a = invite(srv, a["id"], "perform")
    expiring = invite(srv, a["id"], "watch", ttl_s=0.05)
    revoked = invite(srv, a["id"], "watch")
    r = rest(srv, "DELETE", f"/v1/rooms/{a['id']}/invitations/{revoked['id']}")
    assert r.status_code == 204
    wait_until(lambda: time.time() > expiring["expires_at"], 5, what="expiry")
    stranger = srv.issue("stranger", ("stream",))

    async def run():
        assert await refused(srv, b["id"], watch_a["token"]) == ("forbidden", 4403)
        assert await refused(srv, a["id"], watch_a["token"], role="perform") == (
            "forbidden", 4403)
        assert await refused(srv, a["id"], expiring["token"]) == ("unauthorized", 4401)
        assert await refused(srv, a["id"], revoked["token"]) == ("unauthorized", 4401)
        assert await refused(srv, a["id"], "tsr_forged") == ("unauthorized", 4401)
        assert await refused(srv, "nosuchroom", srv.token) == ("not_found", 4404)
        assert await refused(srv, a["id"], stranger) == ("forbidden", 4403)
        assert await refused(srv, a["id"], perform_a["token"], seat=1) == ("forbidden", 4403)
        async with join(srv, a["id"], perform_a["token"], client="first") as performer:
            # One performer per seat: not even the owner takes it over.
            assert await refused(srv, a["id"], srv.token, role="perform", seat=0) == (
                "forbidden", 4403)
            async with join(srv, a["id"], watch_a["token"]) as viewer:
                await viewer.send(jaw(5, 0.3))  # a viewer cannot drive; the session goes on
                err = await recv_until(viewer, is_type("error"))
                assert err.code == "forbidden" and err.answers.seq == 5
                await viewer.send(encode(Image(seq=7, data=b"\xff\xd8 not tracked")))
                err = await recv_until(viewer, is_type("error"))
                assert err.code == "forbidden" and err.answers.type == "image"
                await viewer.send(encode(Ping(t=3.0)))
                await recv_until(viewer, is_type("pong", t=3.0))
                await performer.send(jaw(6, 0.3))
                await recv_until(viewer, is_type("frame", seq=6))
            # Deleting the room closes it for everyone in it.
            assert rest(srv, "DELETE", f"/v1/rooms/{a['id']}").status_code == 204
            err = await recv_until(performer, is_type("error"))
            assert err.code == "gone"
            with pytest.raises(websockets.ConnectionClosed) as closed:
                while True:  # bounded by the timeout below
                    await asyncio.wait_for(performer.recv(), WS_TIMEOUT_S)
            assert closed.value.rcvd.code == 4410

    asyncio.run(run())
    # REST: invitations are not bearer tokens, except to read their own room.
    assert rest(srv, "GET", "/v1/rooms", watch_a["token"]).status_code == 401
    assert rest(srv, "GET", f"/v1/rooms/{b['id']}", stranger).status_code == 403
    watch_b = invite(srv, b["id"], "watch")
    got = rest(srv, "GET", f"/v1/rooms/{b['id']}", watch_b["token"])
    assert got.status_code == 200 and got.json()["id"] == b["id"]
    assert rest(srv, "GET", f"/v1/rooms/{a['id']}").status_code == 404


def test_room_limits_are_settings(tmp_path):
    with run_server(tmp_path, max_rooms_per_user=1, max_seats_per_room=2,
                    max_participants_per_room=1, max_invitations_per_room=1,
                    room_idle_timeout_s=2.0, startup_room=False, default_width=32,
                    default_height=32) as server:
        user = server.issue("user", ("stream",))
        r = rest(server, "POST", "/v1/rooms", user, json={"seats": [{"avatar": "demo"}] * 3})
        assert r.status_code == 422
        room = create_room(server, token=user)
        assert rest(server, "POST", "/v1/rooms", user, json={}).status_code == 429
        invite(server, room["id"], "watch")
        r = rest(server, "POST", f"/v1/rooms/{room['id']}/invitations", json={"scope": "watch"})
        assert r.status_code == 429
        r = rest(server, "POST", f"/v1/rooms/{room['id']}/invitations",
                 json={"scope": "watch", "ttl_s": 8 * 86400})
        assert r.status_code == 422

        async def run():
            async with join(server, room["id"], user):
                assert await refused(server, room["id"], user, role="watch") == ("busy", 4429)

        asyncio.run(run())
        # Empty for room_idle_timeout_s: closed.
        wait_until(lambda: not server.ctx.rooms.list(server.ctx.tokens.principal(user)), 10,
                   what="the idle room to close")


# -- seats ----------------------------------------------------------------------------------------


def test_seats_render_in_one_call_and_the_front_avatar_occludes(srv, monkeypatch):
    calls = []
    real = room_frames.render_views

    def counting(gaussians, *args, **kwargs):
        calls.append(gaussians.num)
        return real(gaussians, *args, **kwargs)

    monkeypatch.setattr(room_frames, "render_views", counting)
    front = {"avatar": "demo", "placement": {"translation": [0.0, 0.0, 0.6]}}
    both = create_room(srv, seats=[{"avatar": "demo"}, front])
    back_only = create_room(srv)
    front_only = create_room(srv, seats=[front])
    count = srv.ctx.registry.get("demo").num_gaussians

    async def depth_of(room: dict) -> np.ndarray:
        async with join(srv, room["id"], srv.token, role="watch") as ws:
            # One fixed camera for all three (an orbit target, not a seat's chest).
            await ws.send(encode(View(orbit=Orbit(target=(0.0, 0.3, 0.0), distance=3.0))))
            await ws.send(encode(Request(codec="png", outputs=["rgb", "depth"])))
            frame = await recv_until(ws, lambda m: m.type == "frame" and m.depth is not None)
            return decode_png(frame.depth, cv2.IMREAD_UNCHANGED)

    async def run():
        return [await depth_of(r) for r in (both, back_only, front_only)]

    calls.clear()
    d_both, d_back, d_front = asyncio.run(run())
    assert 2 * count in calls  # both seats in one rasterize call
    assert all(n in (count, 2 * count) for n in calls)
    overlap = (d_back > 0) & (d_front > 0)
    assert overlap.sum() > 50
    # Where they overlap the front avatar wins: its depth, ~0.6 m nearer than the back one.
    assert np.median(np.abs(d_both[overlap] - d_front[overlap])) < 20  # mm
    assert np.median(d_back[overlap] - d_both[overlap]) > 400
    seats = live(srv, both["id"]).scene.counters
    assert seats.renders >= 1 and seats.poses >= 2


# -- shared work, never repeated -----------------------------------------------------------------


async def _drive_for(ws, seconds: float, hz: float = 20.0, start: int = 100) -> int:
    seq, end = start, time.monotonic() + seconds
    while time.monotonic() < end:
        await ws.send(jaw(seq, 0.3 * math.sin(seq / 3)))
        seq += 1
        await asyncio.sleep(1 / hz)
    return seq - 1


def test_viewers_at_one_view_share_posing_rendering_and_encoding(srv):
    room = create_room(srv)
    watch = invite(srv, room["id"], "watch")
    viewers_n = 4

    async def run():
        async with join(srv, room["id"], srv.token) as performer, \
                contextlib.AsyncExitStack() as stack:
            viewers = [await stack.enter_async_context(join(srv, room["id"], watch["token"]))
                       for _ in range(viewers_n)]
            for ws in (performer, *viewers):
                await recv_until(ws, is_type("frame"))
            counters = live(srv, room["id"]).scene.counters
            before = (counters.poses, counters.renders, counters.encodes)
            sender = asyncio.create_task(_drive_for(performer, 1.5, hz=10))
            counts = await asyncio.gather(*(count_frames(ws, 2.0) for ws in
                                            (performer, *viewers)))
            last = await sender
            poses, renders, encodes = (counters.poses - before[0],
                                       counters.renders - before[1],
                                       counters.encodes - before[2])
            return counts, poses, renders, encodes, last - 100 + 1

    counts, poses, renders, encodes, drives = asyncio.run(run())
    assert 1 <= poses <= drives  # once per drive update, not per participant
    assert renders == poses and encodes == renders  # one view: one render per pose
    assert sum(counts) >= 3 * renders, (counts, renders)  # each frame went to many
    assert min(counts) >= 0.5 * max(counts), counts


def test_distinct_views_render_once_each_per_drive_update(srv):
    room = create_room(srv)
    watch = invite(srv, room["id"], "watch")
    side = View(orbit=Orbit(yaw_deg=45))

    async def run():
        async with join(srv, room["id"], srv.token) as performer, \
                contextlib.AsyncExitStack() as stack:
            viewers = [await stack.enter_async_context(join(srv, room["id"], watch["token"]))
                       for _ in range(4)]
            for ws in viewers[2:]:
                await ws.send(encode(side))
            for ws in (performer, *viewers):
                await recv_until(ws, is_type("frame"))
            counters = live(srv, room["id"]).scene.counters
            await asyncio.sleep(0.3)  # frames of the side view settle
            poses, renders = counters.poses, counters.renders
            sender = asyncio.create_task(_drive_for(performer, 1.5, hz=10))
            counts = await asyncio.gather(*(count_frames(ws, 2.0) for ws in viewers))
            await sender
            return counts, counters.poses - poses, counters.renders - renders

    counts, poses, renders = asyncio.run(run())
    assert poses >= 1 and min(counts) >= 1
    assert poses < renders <= 2 * poses, (poses, renders)  # two views: two renders a pose


def _small_buffer_socket(srv) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 16 * 1024)
    sock.connect(("127.0.0.1", int(srv.url.rsplit(":", 1)[1])))
    return sock


async def _until_stalled(srv, *readers, timeout_s: float = 30.0) -> None:
    """Until a png participant waits on its client (bounded; ``readers`` keep reading)."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if any(s.stalled and s.request.codec == "png" for s in srv.ctx.sessions.values()):
            return
        await asyncio.gather(*(count_frames(r, 0.1) for r in readers))
    raise AssertionError(f"no png participant stalled within {timeout_s} s")


def test_a_stalled_viewer_slows_neither_the_performer_nor_other_viewers(srv):
    room = create_room(srv)
    watch = invite(srv, room["id"], "watch")

    async def window(performer, viewer) -> tuple[int, int]:
        sender = asyncio.create_task(_drive_for(performer, 1.5, hz=30))
        counts = await asyncio.gather(count_frames(performer, 1.5),
                                      count_frames(viewer, 1.5))
        await sender
        return counts

    async def run():
        async with join(srv, room["id"], srv.token) as performer, \
                join(srv, room["id"], watch["token"]) as viewer:
            await recv_until(viewer, is_type("frame"))
            alone = await window(performer, viewer)
            sock = _small_buffer_socket(srv)
            async with join(srv, room["id"], watch["token"], sock=sock, max_queue=1) as slow:
                # Big lossless frames at a view of its own, then it stops reading.
                await slow.send(encode(Request(codec="png", width=512, height=512)))
                await slow.send(encode(View(orbit=Orbit(yaw_deg=30))))
                await window(performer, viewer)  # until its buffers are full
                await _until_stalled(srv, performer, viewer)  # longer on a loaded machine
                stalled = await window(performer, viewer)
            return alone, stalled

    alone, stalled = asyncio.run(run())
    assert stalled[0] > 0.6 * alone[0], (alone, stalled)  # the performer
    assert stalled[1] > 0.6 * alone[1], (alone, stalled)  # the other viewer


# -- the start-up room ----------------------------------------------------------------------------


def test_serve_prints_the_start_up_rooms_links_and_they_join(tmp_path, capsys, srv):
    from fastapi.testclient import TestClient

    from server.app import create_app
    from server.cli import _announce
    from server.config import Settings

    app = create_app(Settings(data_dir=tmp_path, demo_avatar="synthetic", warmup=False))
    _announce(app, "http://127.0.0.1:8000")
    with TestClient(app):
        links = app.state.ctx.startup_links
    out = capsys.readouterr().out
    assert out.count("Telesplat is serving at") == 1, out  # one banner, the admin URL's
    assert "Telesplat is serving at http://127.0.0.1:8000/#token=tsk_" in out
    assert f"  watch link: http://127.0.0.1:8000/?room={links['room']}#token=tsr_" in out
    assert f"  perform link: http://127.0.0.1:8000/?room={links['room']}#token=tsr_" in out
    # The running server's start-up room: pinned, and its links join with their scopes.
    links = srv.ctx.startup_links
    assert srv.ctx.rooms.get(links["room"]).pinned
    token = {scope: links[scope].split("#token=")[1] for scope in ("watch", "perform")}

    async def run():
        async with join(srv, links["room"], token["watch"]) as viewer:
            assert viewer.welcome.room.role == "watch"
            assert viewer.welcome.room.name == "demo"
            await recv_until(viewer, is_type("frame"))

    asyncio.run(run())
