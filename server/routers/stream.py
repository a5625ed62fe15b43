"""WebSocket ``/v1/stream?avatar=ID``: authenticate, admit, welcome, then run the session.

The token comes in an ``Authorization: Bearer`` header or, from a browser (which cannot set
one), in the first message, a ``hello``; or a single-use ``?ticket=`` from
``POST /v1/stream/tickets`` stands in for it. ``?token=`` is still accepted from old clients
but keeps the token in URLs. Until it is authenticated a connection may send one small message
within a short time, and holds one of a few waiting slots per address and in total.

The handshake both this and a room's join share (refusal codes, pre-auth admission, the hello)
is server/handshake.py.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging

from fastapi import APIRouter, HTTPException, WebSocket
from starlette.websockets import WebSocketDisconnect, WebSocketState

from protocol import (
    CODECS,
    AvatarInfo,
    View,
    Welcome,
    encode,
)
from protocol.messages import Orbit

from ..auth import Principal
from ..context import ServerContext
from ..dependencies import Context, StreamPrincipal
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
from ..registry import DEMO_ID, AvatarNotFound, AvatarRecord
from ..rooms.join import join_room
from ..session import SessionConfig, StreamSession
from ..tickets import TicketsExhausted

log = logging.getLogger(__name__)
router = APIRouter()

async def _authenticate(ws: WebSocket, ctx: ServerContext) -> Principal:
    """The principal of a ``?ticket=``, else of the header's, the legacy ``?token=``'s or the
    hello's token (server/handshake.py)."""
    credentials = await read_credentials(ws, ctx, hello=False)
    principal = credentials.principal or ctx.tokens.principal(credentials.token)
    if principal is None:
        raise Refusal("unauthorized", "invalid token", CLOSE_UNAUTHORIZED)
    lift_preauth(ws)
    return principal


def _check_access(ctx: ServerContext, principal: Principal, avatar_id: str) -> AvatarRecord:
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



@router.post("/v1/stream/tickets", status_code=201)
def stream_ticket(ctx: Context, principal: StreamPrincipal) -> dict:
    """A single-use ticket for ``/v1/stream?ticket=...``, valid ``ticket_ttl_s`` seconds: for
    clients that can send neither an Authorization header nor a hello with the token."""
    try:
        ticket = ctx.admission.tickets.issue(principal)
    except TicketsExhausted as exc:
        raise HTTPException(429, str(exc)) from None
    return {"ticket": ticket, "expires_in_s": ctx.settings.ticket_ttl_s}


@router.websocket("/v1/stream")
async def stream(ws: WebSocket, ctx: Context, avatar: str = DEMO_ID,
                 room: str | None = None) -> None:
    """Drive an avatar and receive its frames (see protocol/ for the messages); with
    ``?room=ID``, join that room as a performer or a viewer (server/rooms/)."""
    await ws.accept()
    if room is not None:
        await join_room(ws, ctx, room)
        return
    subject = None  # holds a per-user slot while set
    try:
        principal = await _authenticate(ws, ctx)
        record = _check_access(ctx, principal, avatar)
        if not ctx.slots.try_acquire():
            raise Refusal("busy", f"server busy: {ctx.slots.limit} sessions are open; try "
                                  "again later", CLOSE_BUSY)
        if not principal.is_admin:
            if ctx.admission.sessions.try_acquire(principal.subject) is not None:
                ctx.slots.release()
                raise Refusal("busy", f"{principal.subject!r} has "
                                      f"{ctx.settings.max_sessions_per_user} sessions open, the "
                                      "most one user may have; close one first", CLOSE_TOO_MANY)
            subject = principal.subject
    except Refusal as refusal:
        await refuse(ws, refusal, ctx)
        return
    except WebSocketDisconnect:
        return  # left before authenticating
    ctx.metrics.sessions.set(ctx.slots.count)
    ctx.metrics.sessions_total.inc()
    try:
        await _serve(ws, ctx, record)
    finally:
        ctx.slots.release()
        if subject is not None:
            ctx.admission.sessions.release(subject)
        ctx.metrics.sessions.set(ctx.slots.count)
        if ws.application_state == WebSocketState.CONNECTED:
            with contextlib.suppress(Exception):
                await ws.close(1000)


async def _serve(ws: WebSocket, ctx: ServerContext, record: AvatarRecord) -> None:
    renderer = None
    try:
        renderer = await ctx.render.session_renderer(ctx, record)
        tracker = await asyncio.to_thread(ctx.session_tracker, record.id)
    except Exception as exc:  # noqa: BLE001 - a broken package must not take the server down
        if renderer is not None:
            renderer.close()  # a render worker's scene, an encoder
        log.exception("cannot load avatar %s", record.id)
        await refuse(ws, Refusal("internal", f"cannot load avatar {record.id!r}: {exc}",
                                  CLOSE_INTERNAL), ctx)
        return
    s = ctx.settings
    request = default_request(ctx, record)
    session = StreamSession(
        ws, renderer, tracker, ctx.scheduler, ctx.track_scheduler, ctx.metrics,
        SessionConfig(s.limits, s.jpeg_quality, s.jpeg_quality_moving, s.stats_interval_s,
                      inbound_limits(s)),
        request, View(orbit=Orbit()), session_count=lambda: ctx.slots.count)
    info = AvatarInfo(id=record.id, name=record.name, num_gaussians=record.num_gaussians,
                      sh_degree=record.sh_degree, owner=record.owner, metadata=record.metadata)
    try:
        await ws.send_bytes(encode(Welcome(session=session.id, avatar=info, limits=s.limits,
                                           codecs=list(CODECS), request=request,
                                           encoders=encoders_info())))
    except BaseException:  # the client left before its session ran: nothing else holds them
        renderer.close()
        tracker.close()
        raise
    ctx.sessions[session.id] = session
    try:
        await session.run()
    finally:
        ctx.sessions.pop(session.id, None)
