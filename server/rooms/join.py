"""``/v1/stream?room=ID``: authenticate, pick the role and seat, admit, then run a participant.

In a room the first message is always a ``hello`` (it carries the role and seat), also when
the token came in the ``Authorization`` header or a ticket stood in for it. The token is the
room owner's (or an admin's) bearer token, which may take any role and seat, or an invitation
token (``tsr_...``) of this room, which takes its scope (a perform invitation: its seat only).
Refusals: ``unauthorized`` 4401 (bad, expired or revoked token), ``forbidden`` 4403 (wrong
scope, another room's invitation, a seat taken), ``not_found`` 4404 (no such room or seat),
``busy`` 1013 (server full) / 4429 (room or user full), ``gone`` 4410 (room deleted).
"""

from __future__ import annotations

import asyncio
import logging
import uuid
from collections.abc import Callable
from typing import Any

from fastapi import WebSocket
from starlette.websockets import WebSocketDisconnect

from protocol import (
    PROTOCOL_MINOR,
    AvatarInfo,
    Hello,
    Request,
    RoomWelcome,
    View,
    Welcome,
    encode,
)
from protocol.messages import CODECS, Orbit

from ..auth import Principal
from ..context import ServerContext
from ..encoders import encoders_info
from ..handshake import (
    CLOSE_BUSY,
    CLOSE_FORBIDDEN,
    CLOSE_INTERNAL,
    CLOSE_NOT_FOUND,
    CLOSE_TOO_MANY,
    CLOSE_UNAUTHORIZED,
    Refusal,
    default_request,
    inbound_limits,
    lift_preauth,
    read_credentials,
    refuse,
)
from ..session import SessionConfig, StreamSession
from .live import CLOSE_GONE, JoinRefused, LiveRoom
from .participant import RoomParticipant
from .registry import Invitation, Room, RoomError, is_invitation

log = logging.getLogger(__name__)

JOIN_CLOSE_CODES = {"busy": CLOSE_TOO_MANY, "forbidden": CLOSE_FORBIDDEN, "gone": CLOSE_GONE}


async def _credentials(ws: WebSocket, ctx: ServerContext
                       ) -> tuple[Hello, Principal | None, Invitation | None]:
    """The hello and who sent it: a principal (bearer token or ticket) or an invitation."""
    credentials = await read_credentials(ws, ctx, hello=True)
    principal, invitation, token = credentials.principal, None, credentials.token
    if principal is None:
        if is_invitation(token):
            invitation = ctx.rooms.resolve(token)
            if invitation is None:
                raise Refusal("unauthorized", "invalid, expired or revoked invitation",
                              CLOSE_UNAUTHORIZED)
        else:
            principal = ctx.tokens.principal(token)
            if principal is None:
                raise Refusal("unauthorized", "invalid token", CLOSE_UNAUTHORIZED)
    lift_preauth(ws)
    return credentials.hello, principal, invitation


def _room(ctx: ServerContext, room_id: str) -> Room:
    try:
        return ctx.rooms.get(room_id)
    except RoomError:
        raise Refusal("not_found", f"no room {room_id!r}", CLOSE_NOT_FOUND) from None


def choose_role(room: Room, asked_role: str | None, asked_seat: int | None,
                principal: Principal | None, invitation: Invitation | None) -> tuple[str, int]:
    """(role, seat index) a principal or an invitation may take in ``room`` when it asks for
    ``asked_role`` and ``asked_seat`` (None: the default)."""
    first = room.seats[0].index
    if invitation is not None:
        if invitation.room_id != room.id:
            raise Refusal("forbidden", "this invitation is for another room", CLOSE_FORBIDDEN)
        role = asked_role or invitation.scope
        if role == "perform" and invitation.scope != "perform":
            raise Refusal("forbidden", "a watch invitation cannot perform", CLOSE_FORBIDDEN)
        if role == "perform":
            if asked_seat is not None and asked_seat != invitation.seat:
                raise Refusal("forbidden", f"this invitation performs seat {invitation.seat}, "
                                           f"not {asked_seat}", CLOSE_FORBIDDEN)
            return role, invitation.seat
    else:
        if not principal.has("stream"):
            raise Refusal("forbidden", "this token lacks the 'stream' scope", CLOSE_FORBIDDEN)
        if not room.visible_to(principal):
            raise Refusal("forbidden", f"room {room.id!r} belongs to another owner; join it "
                                       "with an invitation", CLOSE_FORBIDDEN)
        role = asked_role or "perform"
    seat = first if asked_seat is None else asked_seat
    if seat not in {s.index for s in room.seats}:
        raise Refusal("not_found", f"room {room.id!r} has no seat {seat}", CLOSE_NOT_FOUND)
    return role, seat


async def open_live(ctx: ServerContext, room: Room) -> LiveRoom:
    """The room's runtime, made at its first join: each seat's avatar loaded once (here or
    on a render worker)."""
    async with room.opening:
        if room.live is None:
            frames = await ctx.render.room_frames(ctx, room)  # render_backend's
            room.live = LiveRoom(room, frames, ctx.settings)
        return room.live


async def join_room(ws: WebSocket, ctx: ServerContext, room_id: str) -> None:
    subject = None  # holds a per-user slot while set
    slot = False
    try:
        hello, principal, invitation = await _credentials(ws, ctx)
        room = _room(ctx, room_id)
        role, seat = choose_role(room, hello.role, hello.seat, principal, invitation)
        if not ctx.slots.try_acquire():
            raise Refusal("busy", f"server busy: {ctx.slots.limit} sessions are open; try "
                                  "again later", CLOSE_BUSY)
        slot = True
        if principal is not None and not principal.is_admin:
            if ctx.admission.sessions.try_acquire(principal.subject) is not None:
                raise Refusal("busy", f"{principal.subject!r} has "
                                      f"{ctx.settings.max_sessions_per_user} sessions open, the "
                                      "most one user may have; close one first", CLOSE_TOO_MANY)
            subject = principal.subject
        ctx.metrics.sessions.set(ctx.slots.count)
        ctx.metrics.sessions_total.inc()
        await _serve(ws, ctx, room, role, seat, hello.client)
    except Refusal as refusal:
        await refuse(ws, refusal, ctx)
    except WebSocketDisconnect:
        return  # left before joining
    finally:
        if slot:
            ctx.slots.release()
            ctx.metrics.sessions.set(ctx.slots.count)
        if subject is not None:
            ctx.admission.sessions.release(subject)


async def seat_participant(ctx: ServerContext, room: Room, role: str, seat: int,
                           client: str | None, ws: Any, *,
                           factory: Callable[..., RoomParticipant] = RoomParticipant,
                           request: Request | None = None,
                           ) -> tuple[RoomParticipant, Welcome]:
    """A participant made and admitted to the room (Refusal otherwise), and the welcome it
    is owed. ``ws`` is its message channel (a WebSocket, or what stands in for one);
    ``request`` updates the default request (already checked against the limits)."""
    s = ctx.settings
    spec = next(x for x in room.seats if x.index == seat)
    try:
        live = await open_live(ctx, room)
        record = ctx.registry.get(spec.avatar)
        tracker = await asyncio.to_thread(ctx.session_tracker, spec.avatar)
    except Exception as exc:  # noqa: BLE001 - a broken package must not take the server down
        log.exception("cannot open room %s", room.id)
        raise Refusal("internal", f"cannot open room {room.id!r}: {exc}",
                      CLOSE_INTERNAL) from None
    effective = default_request(ctx, record)
    if request is not None:
        effective = StreamSession.merged_request(effective, request, s.limits)
    name = client or f"{'performer' if role == 'perform' else 'viewer'}-{uuid.uuid4().hex[:4]}"
    participant = factory(
        ws, live, role, seat, name, tracker=tracker, scheduler=ctx.scheduler,
        track_scheduler=ctx.track_scheduler, metrics=ctx.metrics,
        config=SessionConfig(s.limits, s.jpeg_quality, s.jpeg_quality_moving,
                             s.stats_interval_s, inbound_limits(s)),
        request=effective, view=View(orbit=Orbit()), session_count=lambda: ctx.slots.count)
    try:
        live.join(participant)
    except JoinRefused as exc:
        participant.tracking.close()
        raise Refusal(exc.code, exc.message, JOIN_CLOSE_CODES[exc.code]) from None
    try:
        info = AvatarInfo(id=record.id, name=record.name, num_gaussians=record.num_gaussians,
                          sh_degree=record.sh_degree, owner=record.owner,
                          metadata=record.metadata)
        welcome = Welcome(session=participant.id, minor=PROTOCOL_MINOR, avatar=info,
                          limits=s.limits, codecs=list(CODECS), request=effective,
                          encoders=encoders_info(),
                          room=RoomWelcome(id=room.id, name=room.name, role=role,
                                           seat=seat if role == "perform" else None))
    except Exception:
        live.leave(participant)  # admitted, never run: out again
        participant.tracking.close()
        raise
    return participant, welcome


async def _serve(ws: WebSocket, ctx: ServerContext, room: Room, role: str, seat: int,
                 client: str | None) -> None:
    participant, welcome = await seat_participant(ctx, room, role, seat, client, ws)
    live = participant.live
    try:
        await ws.send_bytes(encode(welcome))
        live.broadcast(live.presence("join", participant))
        ctx.sessions[participant.id] = participant
        await participant.run()
    finally:
        ctx.sessions.pop(participant.id, None)
        live.leave(participant)
