"""WebSocket ``/v1/stream``: a plain session (``?avatar=ID``) or a room's (``?room=ID``).

The token comes in an ``Authorization: Bearer`` header or, from a browser (which cannot set
one), in the first message, a ``hello``; or a single-use ``?ticket=`` from
``POST /v1/stream/tickets`` stands in for it. ``?token=`` is still accepted from old clients
but keeps the token in URLs. Until it is authenticated a connection may send one small message
within a short time, and holds one of a few waiting slots per address and in total.

The gate (refusal codes, pre-auth admission, the hello) is server/stream/gate.py; the join
(a plain session is a private room of one seat) server/rooms/join.py.
"""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, WebSocket

from ..dependencies import Context, StreamPrincipal
from ..registry import DEMO_ID
from ..rooms.join import join_stream
from ..stream.tickets import TicketsExhausted

router = APIRouter()


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
    await join_stream(ws, ctx, avatar, room)
