"""WHEP (egress) and WHIP (ingest): WebRTC peers of a room, signalled over plain HTTP.

``POST /v1/rooms/{id}/whep`` with an SDP offer (``application/sdp``) answers ``201`` with the
SDP answer (every ICE candidate in it: no trickle) and ``Location: .../whep/{resource}``;
``DELETE`` there ends the peer; ``PATCH`` (trickle ICE) is 405. ``.../whip`` is the same for a
performer publishing webcam video, tracked server-side into its seat. The bearer token is the
room owner's ``stream`` token or an invitation of the room (``watch`` or ``perform``; WHIP
needs ``perform``). Everything is checked before the peer is made, in this order: token (401),
room (404), role and seat (403 / 404), content type (415), size (413, before reading past
``webrtc_max_sdp_bytes``), the offer and the query (400), the peer limits (429 / 503).

``DELETE`` checks the credential before it says anything about the resource (no existence
oracle): the token that opened the peer ends it (even expired or revoked since); any other
missing or invalid credential is 401 whatever the resource; a valid one that may not end it
(not the room's owner or an admin) gets the same 404 as a resource that does not exist.
"""

from __future__ import annotations

import hashlib
import hmac
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, HTTPException, Query, Response, status
from fastapi import Request as HttpRequest
from pydantic import ValidationError

from protocol import ProtocolError, Request
from protocol.names import display_name

from ..auth import Principal, bearer_token
from ..context import ServerContext
from ..dependencies import Context, get_context
from ..rooms.join import choose_role
from ..rooms.registry import Invitation, Room, RoomError
from ..stream.admission import admit
from ..stream.gate import Refusal
from .avatars import ErrorOut

router = APIRouter(prefix="/v1/rooms", tags=["webrtc"])

SDP_TYPE = "application/sdp"
REFUSAL_STATUS = {4401: 401, 4403: 403, 4404: 404, 4429: 429, 1013: 503, 1011: 500}
ENCODER_ALIGN = 2  # VP8 / H.264 in 4:2:0 want even frame sizes

ERRORS: dict[int | str, dict[str, Any]] = {
    400: {"model": ErrorOut, "description": "Unusable SDP offer or query"},
    401: {"model": ErrorOut, "description": "Missing or invalid token"},
    403: {"model": ErrorOut, "description": "Wrong scope, another owner's room, seat taken"},
    404: {"model": ErrorOut, "description": "No such room or seat"},
    413: {"model": ErrorOut, "description": "SDP larger than webrtc_max_sdp_bytes"},
    415: {"model": ErrorOut, "description": "Content-Type is not application/sdp"},
    429: {"model": ErrorOut, "description": "webrtc_max_peers_per_user or "
                                            "max_sessions_per_user reached"},
    503: {"model": ErrorOut, "description": "webrtc_max_peers or max_sessions reached"},
}
OFFER_BODY = {"requestBody": {"required": True, "content": {SDP_TYPE: {
    "schema": {"type": "string"}}}}}
ANSWER = {201: {"description": "SDP answer; Location names the session resource",
                "content": {SDP_TYPE: {"schema": {"type": "string"}}}}}


def _digest(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


UNAUTHORIZED = "missing or invalid bearer token (a stream token or a room invitation)"


def _credentials(ctx: ServerContext, request: HttpRequest
                 ) -> tuple[str, Principal | None, Invitation | None]:
    token = bearer_token(request.headers.get("authorization"))
    principal, invitation = ctx.credential(token)
    if principal is None and invitation is None:
        raise HTTPException(401, UNAUTHORIZED, headers={"WWW-Authenticate": "Bearer"})
    return token, principal, invitation


def _room(ctx: ServerContext, room_id: str) -> Room:
    try:
        return ctx.rooms.get(room_id)
    except RoomError as exc:
        raise HTTPException(exc.status, str(exc)) from None


async def _read_offer(request: HttpRequest, limit: int) -> str:
    kind = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if kind != SDP_TYPE:
        raise HTTPException(415, f"the offer's Content-Type must be {SDP_TYPE}, not "
                                 f"{kind or 'missing'!r}")
    too_large = HTTPException(413, f"the SDP offer exceeds {limit} bytes "
                                   "(webrtc_max_sdp_bytes)")
    declared = request.headers.get("content-length", "")
    if declared.isdigit() and int(declared) > limit:
        raise too_large
    body = bytearray()
    async for chunk in request.stream():
        body += chunk
        if len(body) > limit:
            raise too_large
    try:
        return body.decode("utf-8")
    except UnicodeDecodeError:
        raise HTTPException(400, "the SDP offer is not UTF-8 text") from None


def _request(ctx: ServerContext, width: int | None, height: int | None,
             fps: float | None) -> Request | None:
    """The frame size and rate asked in the query, checked against the limits (400)."""
    if width is None and height is None and fps is None:
        return None
    s = ctx.settings
    try:
        request = Request.model_validate(
            {"width": width, "height": height, "max_fps": fps}, context={"limits": s.limits})
    except ValidationError as exc:
        problems = "; ".join(e["msg"] for e in exc.errors())
        raise HTTPException(400, f"width / height / fps: {problems}") from None
    for name, value in (("width", width), ("height", height)):
        if value is not None and value % ENCODER_ALIGN:
            raise HTTPException(400, f"{name} must be even for VP8 / H.264, not {value}")
    return request


async def _open(kind: Literal["whep", "whip"], room_id: str, request: HttpRequest,
                ctx: ServerContext, role: str | None, seat: int | None, width: int | None,
                height: int | None, fps: float | None, stamp: bool,
                name: str | None, voice_mix: bool = False) -> Response:
    from ..webrtc.negotiate import OfferRefused, check_offer  # aiortc: loaded on first use
    from ..webrtc.peer import WebRTCPeer
    from ..webrtc.registry import PeerRefused

    s = ctx.settings
    token, principal, invitation = _credentials(ctx, request)
    room = _room(ctx, room_id)
    try:
        role, seat = choose_role(room, role, seat, principal, invitation)
    except Refusal as refusal:
        raise HTTPException(REFUSAL_STATUS.get(refusal.close_code, 403), refusal.message) from None
    if voice_mix and role != "watch":
        raise HTTPException(400, "voice=mix is for viewers: a performer hears the other seats "
                                 "each on its own track (the one mix would hold its own voice)")
    text = await _read_offer(request, s.webrtc_max_sdp_bytes)
    try:
        offer = check_offer(text, kind)
    except OfferRefused as exc:
        raise HTTPException(400, str(exc)) from None
    frame_request = _request(ctx, width, height, fps)
    if name is not None:
        try:
            name = display_name(name, s.limits.max_name_chars)
        except ValueError as exc:
            raise HTTPException(400, f"name: {exc}") from None
    if s.webrtc_max_peers == 0:
        raise HTTPException(503, "WebRTC is off on this server (webrtc_max_peers = 0)")
    holder = principal.subject if principal is not None else f"invitation:{invitation.id}"
    try:
        resource = ctx.webrtc_peers.reserve(holder, principal is not None and principal.is_admin)
    except PeerRefused as exc:
        raise HTTPException(exc.status, str(exc)) from None
    try:
        admitted = admit(ctx, principal, invitation)  # the one admission of every entry
    except Refusal as refusal:
        ctx.webrtc_peers.release(resource)
        raise HTTPException(REFUSAL_STATUS.get(refusal.close_code, 503),
                            f"{refusal.message} (max_sessions / max_sessions_per_user)"
                            ) from None
    try:
        peer = WebRTCPeer(ctx, kind, resource, room, _digest(token), admitted)
    except Exception:
        admitted.release()
        ctx.webrtc_peers.release(resource)
        raise
    ctx.webrtc_peers.add(peer)
    try:  # from here on a failure closes the peer, which frees its slots
        answer = await peer.start(offer, role, seat, frame_request, stamp, name, voice_mix)
    except OfferRefused as exc:
        raise HTTPException(400, str(exc)) from None
    except ProtocolError as exc:
        raise HTTPException(400, exc.message) from None
    except Refusal as refusal:
        raise HTTPException(REFUSAL_STATUS.get(refusal.close_code, 403), refusal.message) from None
    return Response(answer, status_code=201, media_type=SDP_TYPE,
                    headers={"Location": f"/v1/rooms/{room.id}/{kind}/{resource}"})


def _deletable(request: HttpRequest, room_id: str, kind: str, resource: str) -> Any:
    """The peer ``DELETE`` may end. The credential is checked before anything about the
    resource is told: 401 for a missing or invalid one whatever the resource, and the same
    404 for a peer this credential may not end as for one that does not exist."""
    ctx = get_context(request)
    token = bearer_token(request.headers.get("authorization")) or ""
    digest = _digest(token)
    peer = ctx.webrtc_peers.get(resource)
    if peer is not None and (peer.kind != kind or peer.room.id != room_id):
        peer = None
    # The token that opened it ends it, even if it expired or was revoked since.
    if token and peer is not None and hmac.compare_digest(digest, peer.token_digest):
        return peer
    _, principal, _ = _credentials(ctx, request)  # 401
    if peer is None or principal is None or not peer.room.visible_to(principal):
        raise HTTPException(404, f"no {kind.upper()} session {resource!r} in room {room_id!r} "
                                 "that this token may end")
    return peer


Role = Annotated[Literal["perform", "watch"] | None, Query(
    description="perform (drive the seat over the data channel) or watch; default: the "
                "invitation's scope, perform for the room's owner")]
Seat = Annotated[int | None, Query(description="the seat to perform; default the invitation's, "
                                               "or the first for the owner")]
Width = Annotated[int | None, Query(description="frame width (even; default default_width)")]
Height = Annotated[int | None, Query(description="frame height (even; default default_height)")]
Fps = Annotated[float | None, Query(description="frame-rate cap (default default_max_fps)")]
Stamp = Annotated[bool, Query(description="stamp each frame's drive seq into its top-left "
                                          "corner (protocol/stamp.py), for latency "
                                          "measurements")]
VoiceChoice = Annotated[Literal["seats", "mix"], Query(
    description="seats: each seat's voice on its own audio m-line (forwarded undecoded); mix: "
                "the offer's first audio m-line carries one mix of every seat (decoded, summed "
                "and encoded once per room; viewers only, at most voice_mix_max_seats)")]
Name = Annotated[str | None, Query(description="the display name others see in the room's "
                                               "presence (limits.max_name_chars; letters, "
                                               "digits, spaces, . _ ' -); default "
                                               "'performer' / 'viewer N'")]


@router.post("/{room_id}/whep", status_code=201, response_class=Response,
             summary="Watch a room over WebRTC (WHEP)", openapi_extra=OFFER_BODY,
             responses={**ANSWER, **ERRORS})
async def whep(room_id: str, request: HttpRequest, ctx: Context, role: Role = None,
               seat: Seat = None, width: Width = None, height: Height = None,
               fps: Fps = None, stamp: Stamp = False, name: Name = None,
               voice: VoiceChoice = "seats") -> Response:
    """A WebRTC viewer (or, with a perform-capable token, a performer driving its seat over
    the data channel ``telesplat``): the avatar as a VP8 or H.264 video track."""
    return await _open("whep", room_id, request, ctx, role, seat, width, height, fps, stamp,
                       name, voice == "mix")


@router.post("/{room_id}/whip", status_code=201, response_class=Response,
             summary="Perform in a room from a webcam over WebRTC (WHIP)",
             openapi_extra=OFFER_BODY, responses={**ANSWER, **ERRORS})
async def whip(room_id: str, request: HttpRequest, ctx: Context, seat: Seat = None,
               width: Width = None, height: Height = None, fps: Fps = None,
               stamp: Stamp = False, name: Name = None) -> Response:
    """The offer's sendonly video is tracked server-side and drives the performer's seat; a
    recvonly video in the same offer watches the room, a data channel carries messages."""
    return await _open("whip", room_id, request, ctx, "perform", seat, width, height, fps,
                       stamp, name)


DELETE_ERRORS: dict[int | str, dict[str, Any]] = {
    401: ERRORS[401],
    404: {"model": ErrorOut, "description": "No such session, or not one this token may end "
                                            "(the same answer)"}}


@router.delete("/{room_id}/{kind}/{resource}", status_code=204,
               summary="End a WHEP / WHIP session", responses=DELETE_ERRORS)
async def end(room_id: str, kind: Literal["whep", "whip"], resource: str,
              peer: Annotated[Any, Depends(_deletable)]) -> Response:
    """The same token as the POST (or the room owner's, or an admin's) ends the peer and frees
    its seat."""
    await peer.close("DELETE by the client")
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.patch("/{room_id}/{kind}/{resource}", status_code=405, summary="Trickle ICE (not "
              "supported)", responses={405: {"model": ErrorOut}})
async def trickle(room_id: str, kind: Literal["whep", "whip"], resource: str) -> Response:
    """Candidates travel in the offer and the answer: no trickle ICE."""
    raise HTTPException(405, "trickle ICE is not supported: put every candidate in the offer",
                        headers={"Allow": "DELETE"})
