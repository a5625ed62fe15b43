"""Authentication before existence (issue 25, finding 4): no route says whether something
exists to a caller without a valid credential. Every HTTP route with a path parameter is
probed on a real server with no token and with garbage ones, once naming things that exist
(a room, its invitation, a live WHEP peer, an avatar, a job, a motion) and once naming things
that do not: the status and the body are the same. A WHEP/WHIP resource also answers a valid
credential that may not end it exactly as it answers one that does not exist.
"""

from __future__ import annotations

import asyncio
import re

import httpx
import pytest

from avatar_core.motion.library import MOTIONS
from server.jobs.store import NewJob
from tests.server_fixtures import run_server
from tests.test_server_rooms import create_room, invite

pytest.importorskip("aiortc")

TIMEOUT_S = 30.0
GARBAGE = (None, "garbage", "tsk_" + "A" * 43, "tsr_" + "A" * 43)  # none, junk, token-like


def whep_offer() -> str:
    """A real aiortc offer (its peer never connects)."""
    from aiortc import RTCConfiguration, RTCPeerConnection

    async def make() -> str:
        pc = RTCPeerConnection(RTCConfiguration(iceServers=[]))
        pc.addTransceiver("video", direction="recvonly")
        pc.createDataChannel("telesplat")
        await pc.setLocalDescription(await pc.createOffer())
        sdp = pc.localDescription.sdp
        await pc.close()
        return sdp

    return asyncio.run(make())


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A server, and one of everything a path can name."""
    with run_server(tmp_path_factory.mktemp("auth"), default_width=64, default_height=64,
                    webrtc_connect_timeout_s=120.0) as srv:
        room = create_room(srv)
        invitation = invite(srv, room["id"], "watch")
        with httpx.Client(base_url=srv.url, timeout=TIMEOUT_S) as c:
            answer = c.post(f"/v1/rooms/{room['id']}/whep", content=whep_offer(),
                            headers={**srv.headers(invitation["token"]),
                                     "Content-Type": "application/sdp"})
        assert answer.status_code == 201, answer.text
        resource = answer.headers["location"].rsplit("/", 1)[1]
        job = srv.ctx.jobs.store.create(NewJob(owner="local", dataset="upload",
                                               dataset_path=str(srv.settings.data_dir / "none"),
                                               config={}, total=1))
        srv.ctx.jobs.store.request_cancel(job.id)  # (before the worker claims it, mostly)
        existing = {"room_id": room["id"], "invitation_id": invitation["id"], "kind": "whep",
                    "resource": resource, "avatar_id": "demo", "job_id": job.id,
                    "name": next(iter(MOTIONS))}
        missing = {**existing, "room_id": "nosuchroom01", "invitation_id": "nosuchinvite",
                   "resource": "00000000deadbeef", "avatar_id": "nosuchavatar",
                   "job_id": "00000000feedface", "name": "nosuchmotion"}
        yield srv, room, invitation, existing, missing


def routes(srv) -> list[tuple[str, str, list[str]]]:
    """(method, path template, path parameters) of every HTTP route with parameters, from
    the server's OpenAPI document (every route of every router is in it)."""
    spec = httpx.get(f"{srv.url}/openapi.json", timeout=TIMEOUT_S).json()
    return [(method.upper(), path, re.findall(r"{(\w+)}", path))
            for path, methods in spec["paths"].items() if "{" in path
            for method in methods]


def answer(response: httpx.Response, values: dict[str, str]) -> tuple[int, str]:
    """The status and the body, with the names the request gave put back as placeholders
    (an answer may repeat what was asked; it must tell nothing else)."""
    text = response.text
    for name, value in sorted(values.items(), key=lambda item: -len(item[1])):
        text = text.replace(value, "{" + name + "}")
    return response.status_code, text


def test_no_route_tells_an_unauthenticated_caller_what_exists(world):
    srv, _, _, existing, missing = world
    probed = routes(srv)
    assert len(probed) >= 20  # every router's routes are in the list
    unknown = {p for _, _, params in probed for p in params} - existing.keys()
    assert not unknown, f"routes with parameters this test does not fill: {unknown}"
    answers = {}
    with httpx.Client(base_url=srv.url, timeout=TIMEOUT_S) as c:
        for method, path, _ in probed:
            for token in GARBAGE:
                headers = {} if token is None else {"Authorization": f"Bearer {token}"}
                there, absent = (c.request(method, path.format(**values), headers=headers)
                                 for values in (existing, missing))
                where = (method, path, token)
                assert answer(there, existing) == answer(absent, missing), (
                    where, there.status_code, there.text, absent.status_code, absent.text)
                assert there.headers.get("www-authenticate") == absent.headers.get(
                    "www-authenticate"), where
                answers[where] = there.status_code
    # 401 everywhere but trickle ICE, which no one may use (405 alike).
    assert {status for (method, path, _), status in answers.items()
            if method != "PATCH"} == {401}, answers
    assert {status for (method, _, _), status in answers.items() if method == "PATCH"} == {405}
    # Nothing was ended or changed by the probes.
    assert srv.ctx.webrtc_peers.get(existing["resource"]) is not None
    assert srv.ctx.rooms.get(existing["room_id"]) is not None
    assert httpx.get(f"{srv.url}/v1/avatars/demo", headers=srv.headers(),
                     timeout=TIMEOUT_S).status_code == 200


def test_a_webrtc_resource_is_not_told_to_a_credential_that_may_not_end_it(world):
    srv, room, _, existing, missing = world
    other_room = create_room(srv)
    credentials = {
        "another user": srv.issue("stranger", ("stream",)),
        "another user, train scope only": srv.issue("trainer", ("train",)),
        "another invitation of the room": invite(srv, room["id"], "watch")["token"],
        "another room's invitation": invite(srv, other_room["id"], "perform")["token"],
    }
    with httpx.Client(base_url=srv.url, timeout=TIMEOUT_S) as c:
        for who, token in credentials.items():
            for kind in ("whep", "whip"):
                answers = []
                for values in ({**existing, "kind": kind}, {**missing, "kind": kind}):
                    path = "/v1/rooms/{room_id}/{kind}/{resource}".format(**values)
                    answers.append(answer(c.delete(path, headers=srv.headers(token)), values))
                there, absent = answers
                assert there == absent and there[0] == 404, (who, kind, there, absent)
        # still there: the owner ends it (204), then it is gone for everyone (404 / 401)
        assert srv.ctx.webrtc_peers.get(existing["resource"]) is not None
        path = "/v1/rooms/{room_id}/{kind}/{resource}".format(**existing)
        assert c.delete(path, headers=srv.headers()).status_code == 204
        assert c.delete(path, headers=srv.headers()).status_code == 404
        assert c.delete(path).status_code == 401
