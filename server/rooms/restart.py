"""A graceful restart: on SIGTERM (or Ctrl+C) every participant is told before it is closed.

uvicorn's own graceful shutdown closes each WebSocket with code 1012 and only then runs the
app's lifespan shutdown, so the app would speak too late. :class:`RestartingServer` (what
``telesplat serve`` and the tests' servers run) first stops accepting connections, then sends
every session in ``ctx.sessions`` (WebSocket and WebRTC alike) an ``error`` with code
``restarting`` followed by a close with code 1012 ("service restart"), waiting at most
``restart_notice_s`` for them, and then lets uvicorn finish. The lifespan's shutdown
(server/app.py) tells whoever is left the same (a server run some other way). Clients
(client/stream.py, client/web/app.js) reconnect into the same room and seat: rooms and
invitations are stored (server/rooms/store.py).
"""

from __future__ import annotations

import asyncio
import logging
import socket
from typing import TYPE_CHECKING

import uvicorn

if TYPE_CHECKING:
    from ..context import ServerContext

log = logging.getLogger(__name__)

CLOSE_RESTARTING = 1012  # RFC 6455 "service restart": clients reconnect
RESTART_MESSAGE = "the server is restarting: reconnect to the same room"


async def announce_restart(ctx: ServerContext, timeout_s: float) -> int:
    """Every session in ``ctx.sessions`` gets error ``restarting`` and close 1012, each
    within ``timeout_s`` (a client that does not read is closed without waiting for it).
    How many were told."""
    sessions = list(ctx.sessions.values())
    if not sessions:
        return 0

    async def tell(session) -> None:
        try:
            await asyncio.wait_for(
                session.close_with("restarting", RESTART_MESSAGE, CLOSE_RESTARTING), timeout_s)
        except TimeoutError:
            log.info("session %s was not told of the restart within %g s", session.id,
                     timeout_s)

    await asyncio.gather(*(tell(s) for s in sessions), return_exceptions=True)
    log.info("told %d participant(s) the server is restarting", len(sessions))
    return len(sessions)


class RestartingServer(uvicorn.Server):
    """uvicorn's server, whose shutdown first tells every participant (see the module)."""

    def __init__(self, config: uvicorn.Config, ctx: ServerContext) -> None:
        super().__init__(config)
        self.ctx = ctx

    async def shutdown(self, sockets: list[socket.socket] | None = None) -> None:
        for server in self.servers:  # no new connections while the old ones are told
            server.close()
        for sock in sockets or []:
            sock.close()
        if not self.force_exit:
            await announce_restart(self.ctx, self.ctx.settings.restart_notice_s)
        await super().shutdown(sockets)
