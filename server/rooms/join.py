"""``/v1/stream``: authenticate, pick the room, role and seat, admit, then run a session.

``?avatar=ID`` (or nothing: the demo) is a plain session: a private room of one seat, made for
it and gone when it ends, which it performs. ``?room=ID`` joins that room. In a room the first
message is always a ``hello`` (it carries the role and seat), also when the token came in the
``Authorization`` header or a ticket stood in for it. The token is the
room owner's (or an admin's) bearer token, which may take any role and seat, or an invitation
token (``tsr_...``) of this room, which takes its scope (a perform invitation: its seat only).
Refusals: ``unauthorized`` 4401 (bad, expired or revoked token), ``forbidden`` 4403 (wrong
scope, another room's invitation, a seat taken), ``not_found`` 4404 (no such room or seat),
``busy`` 1013 (server full) / 4429 (room or user full), ``gone`` 4410 (room deleted).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
import uuid
from typing import Any

from fastapi import WebSocket
from starlette.websockets import WebSocketDisconnect, WebSocketState

from protocol import (
    PROTOCOL_MINOR,
    AvatarInfo,
    Framing,
    Request,
    RoomWelcome,
    View,
    VoiceBounds,
    Welcome,
    encode,
)
from protocol.messages import CODECS, Orbit

from ..auth import Principal
from ..context import ServerContext
from ..registry import AvatarNotFound, AvatarRecord
from ..stream.admission import Admitted, admit
from ..stream.encoders import encoders_info
from ..stream.framing import room_framing
from ..stream.gate import (
    CLOSE_BAD_HELLO,
    CLOSE_FORBIDDEN,
    CLOSE_INTERNAL,
    CLOSE_NOT_FOUND,
    CLOSE_TOO_MANY,
    CLOSE_UNAUTHORIZED,
    Refusal,
    authenticate,
    default_request,
    inbound_limits,
    refuse,
)
from ..stream.session import Session, SessionConfig
from ..stream.transport import Transport, WebSocketTransport
from ..stream.view_motion import MovingViewCost
from .live import CLOSE_GONE, JoinRefused, LiveRoom
from .registry import Invitation, Room, RoomError, SeatSpec
from .voice import relay_voices
from .voice_mix import relay_mix

log = logging.getLogger(__name__)

JOIN_CLOSE_CODES = {"busy": CLOSE_TOO_MANY, "forbidden": CLOSE_FORBIDDEN, "gone": CLOSE_GONE}


def _room(ctx: ServerContext, room_id: str) -> Room:
    try:
        return ctx.rooms.get(room_id)
    except RoomError:
        raise Refusal("not_found", f"no room {room_id!r}", CLOSE_NOT_FOUND) from None


def _avatar(ctx: ServerContext, principal: Principal, avatar_id: str) -> AvatarRecord:
    if not principal.has("stream"):
        raise Refusal("forbidden", "this token lacks the 'stream' scope", CLOSE_FORBIDDEN)
    try:
        record = ctx.registry.get(avatar_id)
    except AvatarNotFound:
        raise Refusal("not_found", f"no avatar {avatar_id!r}", CLOSE_NOT_FOUND) from None
    if not principal.can_see(record.owner):
        raise Refusal("forbidden", f"avatar {avatar_id!r} belongs to another owner",
                      CLOSE_FORBIDDEN)
    return record


def private_room(ctx: ServerContext, principal: Principal | None, avatar_id: str) -> Room:
    """A plain session's room: one seat of ``avatar_id``, one participant (its owner), never
    listed; it goes when the session ends."""
    if principal is None:  # an invitation names a room, never an avatar
        raise Refusal("unauthorized", "invalid token", CLOSE_UNAUTHORIZED)
    record = _avatar(ctx, principal, avatar_id)
    room_id = uuid.uuid4().hex[:12]
    return Room(room_id, f"session {room_id[:6]}", principal.subject,
                [SeatSpec(0, record.id)], time.time(), private=True)


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
    """The room's runtime, made at its first join: its scene, each seat's avatar loaded once
    (here or on a render worker)."""
    async with room.opening:
        if room.live is None:
            kind = "session" if room.private else "room"
            scene = await ctx.render.open_scene(ctx, room, kind)
            room.live = LiveRoom(room, scene, ctx.settings)
        return room.live


async def join_stream(ws: WebSocket, ctx: ServerContext, avatar_id: str,
                      room_id: str | None) -> None:
    """``/v1/stream``: authenticate, pick the room (a named one, or a private one of
    ``avatar_id``), its role and seat, admit, then run the session until it ends."""
    admitted: Admitted | None = None
    try:
        who = await authenticate(ws, ctx, hello=room_id is not None)
        if room_id is None:
            room, (role, seat) = private_room(ctx, who.principal, avatar_id), ("perform", 0)
        else:
            room = _room(ctx, room_id)
            role, seat = choose_role(room, who.hello.role, who.hello.seat, who.principal,
                                     who.invitation)
        mix = who.hello is not None and bool(who.hello.voice_mix)
        if mix and role != "watch":
            raise Refusal("invalid", "voice_mix is for viewers: a performer hears the other "
                                     "seats each on its own (the one mix would hold its own "
                                     "voice)", CLOSE_BAD_HELLO)
        admitted = admit(ctx, who.principal, who.invitation)
        name = None if who.hello is None else who.hello.name
        session, welcome = await seat_participant(ctx, room, role, seat, name,
                                                  WebSocketTransport(ws))
        hear = who.hello is not None and bool(who.hello.voice)
        await serve(ctx, session, encode(welcome), hear_voices=hear, voice_mix=mix)
    except Refusal as refusal:
        await refuse(ws, refusal, ctx)
    except WebSocketDisconnect:
        return  # left before its session ran
    finally:
        if admitted is not None:
            admitted.release()
        if ws.application_state == WebSocketState.CONNECTED:
            with contextlib.suppress(Exception):
                await ws.close(1000)


async def seat_participant(ctx: ServerContext, room: Room, role: str, seat: int,
                           name: str | None, transport: Transport, *,
                           request: Request | None = None) -> tuple[Session, Welcome]:
    """A session made and admitted to the room (Refusal otherwise), and the welcome it is
    owed. ``name``: the display name (already validated), else "performer" / "viewer N".
    ``request`` updates the default request (already checked against the limits)."""
    s = ctx.settings
    spec = next(x for x in room.seats if x.index == seat)
    try:
        live = await open_live(ctx, room)
        tracker, rig = await asyncio.to_thread(
            lambda: (ctx.session_tracker(spec.avatar), ctx.rig(spec.avatar)))
        record = ctx.registry.get(spec.avatar)  # after the last wait: the welcome's is current
    except Exception as exc:  # noqa: BLE001 - a broken package must not take the server down
        log.exception("cannot open room %s", room.id)
        if room.private and room.live is not None:
            room.live.close("the session did not start")  # empty: its scene goes now
        what = f"avatar {spec.avatar!r}" if room.private else f"room {room.id!r}"
        raise Refusal("internal", f"cannot {'load' if room.private else 'open'} {what}: "
                                  f"{exc}", CLOSE_INTERNAL) from None
    effective = default_request(ctx, record)
    if request is not None:
        effective = Session.merged_request(effective, request, s.limits)
    name = name or live.default_name(role)
    session = Session(
        transport, live, role=role, seat_index=seat, name=name, tracker=tracker,
        track_scheduler=ctx.track_scheduler, metrics=ctx.metrics,
        config=SessionConfig(s.limits, s.jpeg_quality, s.jpeg_quality_moving,
                             s.stats_interval_s, inbound_limits(s),
                             MovingViewCost(s.moving_view_settle_ms / 1000,
                                            s.moving_view_scale, s.moving_view_quality),
                             s.frame_burst),
        request=effective, view=View(orbit=Orbit()), session_count=lambda: ctx.slots.count)
    try:
        live.join(session)
    except JoinRefused as exc:
        tracker.close()
        if room.private:
            live.close(exc.message)
        raise Refusal(exc.code, exc.message, JOIN_CLOSE_CODES[exc.code]) from None
    try:
        framing = await asyncio.to_thread(room_framing, room.seats, seat,
                                          lambda avatar: ctx.registry.open(avatar).animator)
        welcome = _welcome(session, record, rig.expression_names, room, role, seat, effective,
                           framing, s)
    except Exception:
        live.leave(session)  # admitted, never run: out again
        session.release()
        raise
    return session, welcome


def avatar_info(record: AvatarRecord, expression_names: tuple[str, ...] = ()) -> AvatarInfo:
    return AvatarInfo(id=record.id, name=record.name, num_gaussians=record.num_gaussians,
                      sh_degree=record.sh_degree, owner=record.owner, metadata=record.metadata,
                      expression_names=list(expression_names) or None)


def _welcome(session: Session, record: AvatarRecord, expression_names: tuple[str, ...],
             room: Room, role: str, seat: int, request: Request, framing: Framing,
             s: Any) -> Welcome:
    info = avatar_info(record, expression_names)
    if room.private:  # a plain session: no room in its welcome
        return Welcome(session=session.id, avatar=info, limits=s.limits, codecs=list(CODECS),
                       request=request, encoders=encoders_info(), framing=framing)
    return Welcome(session=session.id, minor=PROTOCOL_MINOR, avatar=info, limits=s.limits,
                   codecs=list(CODECS), request=request, encoders=encoders_info(),
                   framing=framing, room=RoomWelcome(id=room.id, name=room.name, role=role,
                                    seat=seat if role == "perform" else None),
                   voice=VoiceBounds(max_bitrate=s.voice_max_bitrate,
                                     max_packet_bytes=s.voice_max_packet_bytes))


async def serve(ctx: ServerContext, session: Session, welcome: bytes | None = None,
                hear_voices: bool = False, voice_mix: bool = False) -> None:
    """Send the welcome (where the transport has not) and run the session until it ends;
    then out of its room. ``hear_voices``: the other seats' voices as ``voice`` messages;
    ``voice_mix``: instead the room's one mix of them (server/rooms/voice_mix.py)."""
    live = session.live
    relay = None
    try:
        if welcome is not None:
            await session.transport.send(welcome)
        live.broadcast(live.presence("join", session))
        ctx.sessions[session.id] = session
        if voice_mix:
            relay = asyncio.get_running_loop().create_task(
                relay_mix(session, live, ctx.settings, ctx.metrics))
        elif hear_voices:
            relay = asyncio.get_running_loop().create_task(
                relay_voices(session, live, ctx.settings, ctx.metrics))
        await session.run()
    finally:
        if relay is not None:
            relay.cancel()
        ctx.sessions.pop(session.id, None)
        live.leave(session)
        session.release()
