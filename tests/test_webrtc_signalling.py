"""WHEP / WHIP signalling over real HTTP: every refusal with its status before any peer is
made, the peer limits, and the ways a peer ends (never connected, DELETE, room deleted,
server shutdown), each freeing its slot."""

from __future__ import annotations

import asyncio
import contextlib

import httpx
import pytest

from client.webrtc import WhepError, WhepViewer
from tests.server_fixtures import run_server, wait_until
from tests.test_server_rooms import create_room, invite

pytest.importorskip("aiortc")

SIZE = 64
TIMEOUT_S = 30.0
CONNECT_TIMEOUT_S = 1.0


@pytest.fixture(scope="module")
def srv(tmp_path_factory):
    with run_server(tmp_path_factory.mktemp("whep"), default_width=SIZE, default_height=SIZE,
                    webrtc_connect_timeout_s=CONNECT_TIMEOUT_S, webrtc_max_sdp_bytes=4096,
                    max_sessions=16) as running:
        yield running


def offer_sdp(video: str | None = "recvonly", channel: bool = True) -> str:
    """A real aiortc offer (never answered: its peer will not connect)."""
    from aiortc import RTCConfiguration, RTCPeerConnection

    async def make() -> str:
        pc = RTCPeerConnection(RTCConfiguration(iceServers=[]))
        if video:
            pc.addTransceiver("video", direction=video)
        if channel:
            pc.createDataChannel("telesplat")
        await pc.setLocalDescription(await pc.createOffer())
        sdp = pc.localDescription.sdp
        await pc.close()
        return sdp

    return asyncio.run(make())


def post(srv, room_id: str, token: str | None, body: str | bytes, kind: str = "whep",
         content_type: str = "application/sdp", **query) -> httpx.Response:
    headers = {"Content-Type": content_type}
    if token:
        headers["Authorization"] = f"Bearer {token}"
    with httpx.Client(base_url=srv.url, timeout=TIMEOUT_S) as c:
        return c.post(f"/v1/rooms/{room_id}/{kind}", content=body, headers=headers,
                      params=query)


def peers(srv) -> int:
    return len(srv.ctx.webrtc_peers)


def no_peers(srv) -> None:
    wait_until(lambda: peers(srv) == 0, TIMEOUT_S, what="every WebRTC peer to be freed")


def test_refusals_have_their_statuses_and_make_no_peer(srv):
    room = create_room(srv)
    watch = invite(srv, room["id"], "watch")
    other = create_room(srv, token=srv.issue("mallory", ("stream",)))
    trainer = srv.issue("trainer", ("train",))
    good = offer_sdp()
    cases = [
        (post(srv, room["id"], None, good), 401),
        (post(srv, room["id"], "tsk_not-a-token", good), 401),
        (post(srv, room["id"], "tsr_not-an-invitation", good), 401),
        (post(srv, room["id"], trainer, good), 403),           # no stream scope
        (post(srv, other["id"], srv.issue("eve", ("stream",)), good), 403),  # not hers
        (post(srv, other["id"], watch["token"], good), 403),    # another room's invitation
        (post(srv, room["id"], watch["token"], good, kind="whip"), 403),  # watch cannot perform
        (post(srv, "nosuchroom", srv.token, good), 404),
        (post(srv, room["id"], srv.token, good, seat=7), 404),
        (post(srv, room["id"], srv.token, good, content_type="text/plain"), 415),
        (post(srv, room["id"], srv.token, good + "a=x-padding:" + "x" * 5000 + "\r\n"), 413),
        (post(srv, room["id"], srv.token, "this is not SDP"), 400),
        (post(srv, room["id"], srv.token, b"\xff\xfe\x00"), 400),
        (post(srv, room["id"], srv.token, offer_sdp(video=None)), 400),     # no video
        (post(srv, room["id"], srv.token, offer_sdp(video="sendonly")), 400),  # nothing to see
        (post(srv, room["id"], srv.token, offer_sdp(), kind="whip"), 400),  # no webcam
        (post(srv, room["id"], srv.token, good.replace("VP8", "VP9").replace(
            "H264", "H265")), 400),                             # no common codec
        (post(srv, room["id"], srv.token, good, width=33), 400),  # odd
        (post(srv, room["id"], srv.token, good, width=100000), 400),  # past limits.max_width
        (post(srv, room["id"], srv.token, good, fps=0.01), 400),  # below limits.min_fps
        (post(srv, room["id"], srv.token, good, fps="nan"), 400),
        (post(srv, room["id"], srv.token, good, height=-64), 400),
    ]
    for response, status in cases:
        assert response.status_code == status, (status, response.text)
        assert isinstance(response.json()["detail"], str)  # the server's usual error shape
    assert peers(srv) == 0 and srv.ctx.slots.count == 0
    # The server goes on serving.
    assert httpx.get(f"{srv.url}/v1/health").json()["webrtc"] is True


def test_patch_is_405_and_delete_needs_the_same_token(srv):
    room = create_room(srv)
    watch = invite(srv, room["id"], "watch")
    response = post(srv, room["id"], watch["token"], offer_sdp())
    assert response.status_code == 201, response.text
    assert response.headers["content-type"].startswith("application/sdp")
    answer, location = response.text, response.headers["location"]
    assert "a=candidate:" in answer and "a=end-of-candidates" in answer  # no trickle
    assert location.startswith(f"/v1/rooms/{room['id']}/whep/")
    with httpx.Client(base_url=srv.url, timeout=TIMEOUT_S) as c:
        assert c.patch(location, headers={"Authorization": f"Bearer {watch['token']}"},
                       content="a=candidate:x", ).status_code == 405
        assert c.delete(location).status_code == 401
        stranger = srv.issue("stranger", ("stream",))  # the same 404 as for no such peer
        assert c.delete(location, headers={"Authorization": f"Bearer {stranger}"}
                        ).status_code == 404
        assert c.delete(location.replace("/whep/", "/whip/"), headers={
            "Authorization": f"Bearer {watch['token']}"}).status_code == 404
        assert peers(srv) == 1
        # Revoked since: it admits nobody new, but still ends what it opened.
        assert c.delete(f"/v1/rooms/{room['id']}/invitations/{watch['id']}",
                        headers=srv.headers()).status_code == 204
        assert c.delete(location, headers={"Authorization": f"Bearer {watch['token']}"}
                        ).status_code == 204
        assert peers(srv) == 0
        # Revoked, and its peer gone: an invalid credential, 401 whatever the resource.
        assert c.delete(location, headers={"Authorization": f"Bearer {watch['token']}"}
                        ).status_code == 401
        assert c.delete(location, headers=srv.headers()).status_code == 404  # the owner's


def test_a_peer_that_never_connects_is_dropped(srv):
    room = create_room(srv)
    watch = invite(srv, room["id"], "watch")
    response = post(srv, room["id"], watch["token"], offer_sdp())
    assert response.status_code == 201
    assert peers(srv) == 1
    no_peers(srv)  # webrtc_connect_timeout_s later
    assert srv.ctx.slots.count == 0
    assert not srv.ctx.rooms.get(room["id"]).live.participants


def test_peer_limits_are_settings(tmp_path):
    with run_server(tmp_path, default_width=SIZE, default_height=SIZE, webrtc_max_peers=2,
                    webrtc_max_peers_per_user=1, webrtc_connect_timeout_s=CONNECT_TIMEOUT_S
                    ) as server:
        room = create_room(server)
        a, b, c = (invite(server, room["id"], "watch") for _ in range(3))
        sdp = offer_sdp()
        assert post(server, room["id"], a["token"], sdp).status_code == 201
        limited = post(server, room["id"], a["token"], sdp)
        assert limited.status_code == 429 and "webrtc_max_peers_per_user" in limited.text
        assert post(server, room["id"], b["token"], sdp).status_code == 201
        busy = post(server, room["id"], c["token"], sdp)
        assert busy.status_code == 503 and "webrtc_max_peers" in busy.text
        no_peers(server)  # neither connects
        assert post(server, room["id"], c["token"], sdp).status_code == 201
    with run_server(tmp_path / "off", default_width=SIZE, default_height=SIZE,
                    webrtc_max_peers=0) as server:
        room = create_room(server)
        assert post(server, room["id"], server.token, offer_sdp()).status_code == 503
        assert httpx.get(f"{server.url}/v1/health").json()["webrtc"] is False


def test_deleting_the_room_closes_its_peers_with_gone(srv):
    room = create_room(srv)
    watch = invite(srv, room["id"], "watch")

    async def run():
        async with WhepViewer(srv.url, room["id"], watch["token"], timeout_s=TIMEOUT_S) as v:
            await v.next_frame()
            await v.welcome()
            assert peers(srv) == 1
            async with httpx.AsyncClient(base_url=srv.url, timeout=TIMEOUT_S) as c:
                r = await c.delete(f"/v1/rooms/{room['id']}", headers=srv.headers())
                assert r.status_code == 204
            return await v.message(lambda m: m.type == "error")

    gone = asyncio.run(run())
    assert gone.code == "gone"
    no_peers(srv)


def test_server_shutdown_closes_connected_peers(tmp_path):
    async def run():
        with contextlib.ExitStack() as stack:
            server = stack.enter_context(run_server(tmp_path, default_width=SIZE,
                                                    default_height=SIZE))
            room = await asyncio.to_thread(create_room, server)
            v = await WhepViewer(server.url, room["id"], server.token,
                                 timeout_s=TIMEOUT_S).start()
            await v.next_frame()
            assert peers(server) == 1
            await asyncio.to_thread(stack.close)  # the lifespan ends
            left = peers(server)
            await v.pc.close()
            return left

    assert asyncio.run(run()) == 0


def test_whep_error_carries_status_and_detail(srv):
    async def run():
        with pytest.raises(WhepError) as refused:
            await WhepViewer(srv.url, "nosuchroom", srv.token, timeout_s=TIMEOUT_S).start()
        return refused.value

    error = asyncio.run(run())
    assert error.status == 404 and "nosuchroom" in error.detail


def test_a_performed_seat_refuses_a_second_performer_but_not_a_viewer(srv):
    room = create_room(srv)
    perform = invite(srv, room["id"], "perform")
    sdp = offer_sdp()
    first = post(srv, room["id"], perform["token"], sdp)
    assert first.status_code == 201
    taken = post(srv, room["id"], srv.token, sdp)  # the owner performs seat 0 by default
    assert taken.status_code == 403 and "performed" in taken.json()["detail"]
    assert post(srv, room["id"], srv.token, sdp, role="watch").status_code == 201
    assert peers(srv) == 2
    no_peers(srv)  # neither connects
    live = srv.ctx.rooms.get(room["id"]).live
    assert live.seats[0].performer is None and not live.participants
