"""The gate of the WebSocket entry (``/v1/stream``, a plain session or a room): the refusal
codes, the pre-auth admission (a waiting slot per address, one small ``hello`` within a
deadline, checked before anything is decoded), who the credentials name (a principal or a
room's invitation), and refusing with an ``error`` then a close. WHEP / WHIP take the same
credentials from their Authorization header (server/routers/webrtc.py); every entry is
admitted by the one :func:`server.stream.admission.admit`.

Refusals are sent as an ``error`` message and then a close with one of the codes below, since
a browser sees neither the status nor the body of a refused WebSocket handshake.
"""

from __future__ import annotations

import asyncio
import contextlib
from dataclasses import dataclass
from typing import TYPE_CHECKING

from fastapi import WebSocket
from starlette.websockets import WebSocketDisconnect

from protocol import PROTOCOL_VERSION, Hello, ProtocolError, Request, decode_client, encode

from ..auth import Principal, is_invitation, token_from_websocket
from ..registry import AvatarRecord
from .inbound import InboundLimits
from .net import PREAUTH_EXTENSION
from .session import error_message

if TYPE_CHECKING:
    from ..context import ServerContext
    from ..rooms.registry import Invitation

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


def client_address(ws: WebSocket) -> str:
    return ws.client.host if ws.client else "unknown"


def admit_unauthenticated(ctx: ServerContext, address: str) -> None:
    """Take a waiting slot for ``address`` (Refusal past the per-address or total cap)."""
    refused = ctx.admission.waiting.try_acquire(address)
    s = ctx.settings
    if refused == "total":
        raise Refusal("busy", f"server busy: {s.max_unauthenticated} connections are waiting "
                              "to authenticate; try again later", CLOSE_BUSY)
    if refused == "key":
        raise Refusal("busy", f"too many connections waiting to authenticate from this address "
                              f"(limit {s.max_unauthenticated_per_address})", CLOSE_TOO_MANY)


@dataclass(frozen=True)
class Who:
    """Whom a connection's credentials name, and its hello when one was read."""

    hello: Hello | None
    principal: Principal | None    # a bearer token's (or a ticket's) principal
    invitation: Invitation | None  # else a room's invitation


async def authenticate(ws: WebSocket, ctx: ServerContext, *, hello: bool) -> Who:
    """Who sent the credentials: a ``?ticket=``'s principal, else the header's (or a legacy
    ``?token=``'s) token, else the hello's. Credentials in the handshake are validated before
    anything is read: a bad one is refused at once (``unauthorized``), never lifting the
    pre-auth limits. Without any, the hello must carry a valid token, read under the pre-auth
    limits while the connection holds a waiting slot of its address. The message size limit
    is lifted only once the credentials are valid. With ``hello`` the hello is read in any
    case (a room's carries role and seat)."""
    ticket = ws.query_params.get("ticket")
    if ticket:
        principal = ctx.admission.tickets.redeem(ticket)
        if principal is None:
            raise Refusal("unauthorized", "invalid, spent or expired ticket", CLOSE_UNAUTHORIZED)
        lift_preauth(ws)
        return Who(await read_hello(ws, ctx) if hello else None, principal, None)
    token = token_from_websocket(ws)
    if token:
        principal, invitation = _valid(ctx, token)
        lift_preauth(ws)
        return Who(await read_hello(ws, ctx) if hello else None, principal, invitation)
    address = client_address(ws)
    admit_unauthenticated(ctx, address)
    try:
        first = await read_hello(ws, ctx)
    finally:
        ctx.admission.waiting.release(address)
    if not first.token:
        raise Refusal("unauthorized", "no token: the first message must be a hello with a "
                                      "token", CLOSE_UNAUTHORIZED)
    principal, invitation = _valid(ctx, first.token)
    lift_preauth(ws)
    return Who(first, principal, invitation)


def _valid(ctx: ServerContext, token: str) -> tuple[Principal | None, Invitation | None]:
    principal, invitation = ctx.credential(token)
    if principal is None and invitation is None:
        raise Refusal("unauthorized", "invalid, expired or revoked invitation"
                      if is_invitation(token) else "invalid token", CLOSE_UNAUTHORIZED)
    return principal, invitation


def handshake_check(ctx: ServerContext):
    """For the WebSocket protocol (server/stream/net.py): whether a handshake's credentials
    are valid, checked before any message is read (a ticket is looked at, not spent)."""
    def valid(token: str | None, ticket: str | None) -> bool:
        if ticket:
            return ctx.admission.tickets.valid(ticket)
        principal, invitation = ctx.credential(token)
        return principal is not None or invitation is not None

    return valid


def lift_preauth(ws: WebSocket) -> None:
    """Authenticated: the full message size from now on (a no-op where none was set)."""
    preauth = ws.scope.get("extensions", {}).get(PREAUTH_EXTENSION)
    if preauth is not None:
        preauth["lift"]()


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
