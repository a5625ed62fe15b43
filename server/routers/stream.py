"""WebSocket ``/v1/stream?avatar=ID``: authenticate, admit, welcome, then run the session.

The token comes in an ``Authorization: Bearer`` header or, from a browser (which cannot set
one), in the first message, a ``hello``; or a single-use ``?ticket=`` from
``POST /v1/stream/tickets`` stands in for it. ``?token=`` is still accepted from old clients
but keeps the token in URLs. Until it is authenticated a connection may send one small message
within a short time, and holds one of a few waiting slots per address and in total.

Refusals are sent as an ``error`` message and then a close with one of the codes below, since
a browser sees neither the status nor the body of a refused WebSocket handshake.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging

from fastapi import APIRouter, HTTPException, WebSocket
from starlette.websockets import WebSocketDisconnect, WebSocketState

from protocol import (
    CODECS,
    PROTOCOL_VERSION,
    AvatarInfo,
    Hello,
    ProtocolError,
    Request,
    View,
    Welcome,
    decode_client,
    encode,
)
from protocol.messages import Orbit

from ..auth import Principal, token_from_websocket
from ..context import ServerContext
from ..dependencies import Context, StreamPrincipal
from ..inbound import InboundLimits
from ..net import PREAUTH_EXTENSION
from ..registry import DEMO_ID, AvatarNotFound, AvatarRecord
from ..renderer import SessionRenderer
from ..session import SessionConfig, StreamSession, error_message
from ..tickets import TicketsExhausted

log = logging.getLogger(__name__)
router = APIRouter()

# Close codes: 4000 + the HTTP status the refusal would have had; 1013 "try again later".
CLOSE_BAD_HELLO = 4400
CLOSE_UNAUTHORIZED = 4401
CLOSE_FORBIDDEN = 4403
CLOSE_NOT_FOUND = 4404
CLOSE_HELLO_TIMEOUT = 4408
CLOSE_TOO_LARGE = 4413
CLOSE_TOO_MANY = 4429  # this address waiting, or this user streaming, too much already
CLOSE_BUSY = 1013
CLOSE_INTERNAL = 1011


class Refusal(Exception):
    def __init__(self, code: str, message: str, close_code: int) -> None:
        super().__init__(message)
        self.code, self.message, self.close_code = code, message, close_code


def _client_address(ws: WebSocket) -> str:
    return ws.client.host if ws.client else "unknown"


def _admit_unauthenticated(ctx: ServerContext, address: str) -> None:
    """Take a waiting slot for ``address`` (Refusal past the per-address or total cap)."""
    refused = ctx.admission.waiting.try_acquire(address)
    s = ctx.settings
    if refused == "total":
        raise Refusal("busy", f"server busy: {s.max_unauthenticated} connections are waiting "
                              "to authenticate; try again later", CLOSE_BUSY)
    if refused == "key":
        raise Refusal("busy", f"too many connections waiting to authenticate from this address "
                              f"(limit {s.max_unauthenticated_per_address})", CLOSE_TOO_MANY)


async def _hello_token(ws: WebSocket, ctx: ServerContext) -> str:
    """The token of the first message, a ``hello``."""
    hello = await read_hello(ws, ctx)
    if not hello.token:
        raise Refusal("unauthorized", "no token: the first message must be a hello with a "
                                      "token", CLOSE_UNAUTHORIZED)
    return hello.token


async def read_hello(ws: WebSocket, ctx: ServerContext) -> Hello:
    """The first message, a ``hello``; read under the pre-auth limits: a short timeout and a
    small size, checked on the frame's length before anything is decoded."""
    s = ctx.settings
    try:
        # Not wait_for: it would run receive() as a task and leave a loop turn between the
        # read and the caller, in which the next frame could meet the parser's pre-auth limit.
        async with asyncio.timeout(s.hello_timeout_s):
            message = await ws.receive()
    except TimeoutError:
        raise Refusal("unauthorized", f"no hello within {s.hello_timeout_s:g} s: send a hello "
                                      "with a token first (or an Authorization header)",
                      CLOSE_HELLO_TIMEOUT) from None
    if message["type"] == "websocket.disconnect":
        raise WebSocketDisconnect(message.get("code", 1000))
    data = message.get("bytes")
    if data is None:
        raise Refusal("bad_message", "messages are binary msgpack frames", CLOSE_BAD_HELLO)
    if len(data) > s.hello_max_bytes:  # before any decoding: an unknown peer costs nothing
        raise Refusal("too_large", f"a message of {len(data)} bytes before authentication; "
                                   f"the hello is limited to {s.hello_max_bytes}",
                      CLOSE_TOO_LARGE)
    hello_limits = s.limits.model_copy(update={"max_message_bytes": s.hello_max_bytes})
    try:
        hello = decode_client(data, hello_limits)
    except ProtocolError as exc:
        raise Refusal(exc.code, exc.message, CLOSE_BAD_HELLO) from None
    if not isinstance(hello, Hello):
        raise Refusal("unauthorized", "no token: the first message must be a hello with a "
                                      "token", CLOSE_UNAUTHORIZED)
    if hello.version != PROTOCOL_VERSION:
        raise Refusal("version", f"this server speaks protocol version {PROTOCOL_VERSION}, "
                                 f"not {hello.version}", CLOSE_BAD_HELLO)
    return hello


async def _authenticate(ws: WebSocket, ctx: ServerContext) -> Principal:
    """The principal of a ``?ticket=``, else of the header's (or a legacy ``?token=``'s)
    token, else of the hello's; while the hello is awaited the connection holds a waiting
    slot of its address."""
    ticket = ws.query_params.get("ticket")
    if ticket:
        principal = ctx.admission.tickets.redeem(ticket)
        if principal is None:
            raise Refusal("unauthorized", "invalid, spent or expired ticket", CLOSE_UNAUTHORIZED)
        return principal
    token = token_from_websocket(ws)
    if not token:
        address = _client_address(ws)
        _admit_unauthenticated(ctx, address)
        try:
            token = await _hello_token(ws, ctx)
        finally:
            ctx.admission.waiting.release(address)
    principal = ctx.tokens.principal(token)
    if principal is None:
        raise Refusal("unauthorized", "invalid token", CLOSE_UNAUTHORIZED)
    preauth = ws.scope.get("extensions", {}).get(PREAUTH_EXTENSION)
    if preauth is not None:
        preauth["lift"]()  # authenticated: the full message size from now on
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


def inbound_limits(s) -> InboundLimits:
    return InboundLimits(max_message_objects=s.max_message_objects,
                         decode_offload_bytes=s.decode_offload_bytes,
                         max_bytes_per_s=s.max_inbound_bytes_per_s)


def default_request(ctx: ServerContext, record: AvatarRecord) -> Request:
    s = ctx.settings
    return Request(outputs=["rgb"], width=s.default_width, height=s.default_height,
                   background=(1.0, 1.0, 1.0), sh_degree=record.sh_degree, quality=1.0,
                   jpeg_quality=s.jpeg_quality, codec="jpeg",
                   max_fps=min(s.default_max_fps, s.limits.max_fps))


async def refuse(ws: WebSocket, refusal: Refusal, ctx: ServerContext) -> None:
    ctx.metrics.sessions_refused.labels(refusal.code).inc()
    ctx.metrics.errors.labels(refusal.code).inc()
    with contextlib.suppress(Exception):  # the client may be gone already
        await ws.send_bytes(encode(error_message(refusal.code, refusal.message)))
        await ws.close(refusal.close_code, refusal.message[:120])


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
        from ..rooms.join import join_room  # it builds on this module's helpers

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
    try:
        animator, manos = await asyncio.to_thread(ctx.session_models, record.id)
        tracker = await asyncio.to_thread(ctx.session_tracker, record.id)
    except Exception as exc:  # noqa: BLE001 - a broken package must not take the server down
        log.exception("cannot load avatar %s", record.id)
        await refuse(ws, Refusal("internal", f"cannot load avatar {record.id!r}: {exc}",
                                  CLOSE_INTERNAL), ctx)
        return
    s = ctx.settings
    renderer = SessionRenderer(animator, manos, backend=s.backend)
    request = default_request(ctx, record)
    session = StreamSession(
        ws, renderer, tracker, ctx.scheduler, ctx.track_scheduler, ctx.metrics,
        SessionConfig(s.limits, s.jpeg_quality, s.jpeg_quality_moving, s.stats_interval_s,
                      inbound_limits(s)),
        request, View(orbit=Orbit()), session_count=lambda: ctx.slots.count)
    info = AvatarInfo(id=record.id, name=record.name, num_gaussians=record.num_gaussians,
                      sh_degree=record.sh_degree, owner=record.owner, metadata=record.metadata)
    await ws.send_bytes(encode(Welcome(session=session.id, avatar=info, limits=s.limits,
                                       codecs=list(CODECS), request=request)))
    ctx.sessions[session.id] = session
    try:
        await session.run()
    finally:
        ctx.sessions.pop(session.id, None)
