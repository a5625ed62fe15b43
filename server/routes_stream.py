"""WebSocket ``/v1/stream?avatar=ID``: authenticate, admit, welcome, then run the session.

Refusals are sent as an ``error`` message and then a close with one of the codes below, since
a browser sees neither the status nor the body of a refused WebSocket handshake.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging

from fastapi import APIRouter, WebSocket
from starlette.websockets import WebSocketState

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

from .auth import Principal, token_from_websocket
from .context import ServerContext
from .registry import DEMO_ID, AvatarNotFound, AvatarRecord
from .renderer import SessionRenderer
from .session import SessionConfig, StreamSession, error_message

log = logging.getLogger(__name__)
router = APIRouter()

HELLO_TIMEOUT_S = 10.0
# Close codes: 4000 + the HTTP status the refusal would have had; 1013 "try again later".
CLOSE_BAD_HELLO = 4400
CLOSE_UNAUTHORIZED = 4401
CLOSE_FORBIDDEN = 4403
CLOSE_NOT_FOUND = 4404
CLOSE_BUSY = 1013
CLOSE_INTERNAL = 1011


class Refusal(Exception):
    def __init__(self, code: str, message: str, close_code: int) -> None:
        super().__init__(message)
        self.code, self.message, self.close_code = code, message, close_code


async def _token(ws: WebSocket, ctx: ServerContext) -> str:
    """The token from the URL or header, else from a first ``hello`` message."""
    token = token_from_websocket(ws)
    if token:
        return token
    try:
        message = await asyncio.wait_for(ws.receive(), HELLO_TIMEOUT_S)
    except TimeoutError:
        raise Refusal("unauthorized", "no token: give ?token=, an Authorization header or a "
                                      "hello message with a token", CLOSE_UNAUTHORIZED) from None
    data = message.get("bytes")
    try:
        hello = decode_client(data, ctx.settings.limits) if data is not None else None
    except ProtocolError as exc:
        raise Refusal(exc.code, exc.message, CLOSE_BAD_HELLO) from None
    if not isinstance(hello, Hello) or not hello.token:
        raise Refusal("unauthorized", "no token: the first message must be a hello with a "
                                      "token when the URL carries none", CLOSE_UNAUTHORIZED)
    if hello.version != PROTOCOL_VERSION:
        raise Refusal("version", f"this server speaks protocol version {PROTOCOL_VERSION}, "
                                 f"not {hello.version}", CLOSE_BAD_HELLO)
    return hello.token


def _check_access(ctx: ServerContext, principal: Principal | None,
                  avatar_id: str) -> AvatarRecord:
    if principal is None:
        raise Refusal("unauthorized", "invalid token", CLOSE_UNAUTHORIZED)
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


def default_request(ctx: ServerContext, record: AvatarRecord) -> Request:
    s = ctx.settings
    return Request(outputs=["rgb"], width=s.default_width, height=s.default_height,
                   background=(1.0, 1.0, 1.0), sh_degree=record.sh_degree, quality=1.0,
                   jpeg_quality=s.jpeg_quality, codec="jpeg",
                   max_fps=min(s.default_max_fps, s.limits.max_fps))


async def _refuse(ws: WebSocket, refusal: Refusal, ctx: ServerContext) -> None:
    ctx.metrics.sessions_refused.labels(refusal.code).inc()
    ctx.metrics.errors.labels(refusal.code).inc()
    with contextlib.suppress(Exception):  # the client may be gone already
        await ws.send_bytes(encode(error_message(refusal.code, refusal.message)))
        await ws.close(refusal.close_code, refusal.message[:120])


@router.websocket("/v1/stream")
async def stream(ws: WebSocket, avatar: str = DEMO_ID) -> None:
    """Drive an avatar and receive its frames (see protocol/ for the messages)."""
    ctx: ServerContext = ws.app.state.ctx
    await ws.accept()
    try:
        principal = ctx.tokens.principal(await _token(ws, ctx))
        record = _check_access(ctx, principal, avatar)
        if not ctx.slots.try_acquire():
            raise Refusal("busy", f"server busy: {ctx.slots.limit} sessions are open; try "
                                  "again later", CLOSE_BUSY)
    except Refusal as refusal:
        await _refuse(ws, refusal, ctx)
        return
    ctx.metrics.sessions.set(ctx.slots.count)
    ctx.metrics.sessions_total.inc()
    try:
        await _serve(ws, ctx, record)
    finally:
        ctx.slots.release()
        ctx.metrics.sessions.set(ctx.slots.count)
        if ws.application_state == WebSocketState.CONNECTED:
            with contextlib.suppress(Exception):
                await ws.close(1000)


async def _serve(ws: WebSocket, ctx: ServerContext, record: AvatarRecord) -> None:
    try:
        loaded, animator, manos = await asyncio.to_thread(ctx.session_models, record.id)
    except Exception as exc:  # noqa: BLE001 - a broken package must not take the server down
        log.exception("cannot load avatar %s", record.id)
        await _refuse(ws, Refusal("internal", f"cannot load avatar {record.id!r}: {exc}",
                                  CLOSE_INTERNAL), ctx)
        return
    s = ctx.settings
    renderer = SessionRenderer(loaded, animator, manos, backend=s.backend)
    request = default_request(ctx, record)
    session = StreamSession(
        ws, renderer, ctx.scheduler, ctx.track_scheduler, ctx.metrics,
        SessionConfig(s.limits, s.jpeg_quality, s.jpeg_quality_moving, s.stats_interval_s),
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
