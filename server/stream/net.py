"""Transport: the listening socket, and the WebSocket protocol that bounds unknown peers.

The socket is made here (not by uvicorn) so that its send buffer can be bounded. Why: the
kernel's send buffer is where a slow client's frames pile up out of the server's sight.
Accepted connections inherit the listener's ``SO_SNDBUF``, so a small one bounds that backlog
(and the lag it means) to about two frames' worth of bytes at 512 px, while loopback and LAN
throughput stay far above what a session sends.

The WebSocket protocol: uvicorn reads a whole message (up to ``ws_max_size``, 8 MiB) before
the app sees it, so an app-level size check still lets every unauthenticated peer make the
server read and buffer that much. A connection whose handshake carries no credentials
(``Authorization`` header, ``?token=``, ``?ticket=``) must authenticate with its first message,
so until it has, the frame parser's own limit is the hello's size: a larger frame is refused
from its header (close 1009) and never read. Credentials in the handshake count only when
they are valid (``valid_credentials``, checked before any message is read): a garbage
``Authorization`` header gets the same limit as none. ``/v1/stream`` lifts the limit once the
credentials are valid (through the ASGI scope extension ``PREAUTH_EXTENSION``).
"""

from __future__ import annotations

import socket
from collections.abc import Callable
from typing import Any
from urllib.parse import parse_qs

from ..auth import bearer_token

PREAUTH_EXTENSION = "telesplat.preauth"  # scope["extensions"][...]["lift"]() -> full size


LISTEN_BACKLOG = 2048  # uvicorn's own default


def listen_socket(host: str, port: int, send_buffer_bytes: int = 0) -> socket.socket:
    """A bound, listening TCP socket for ``uvicorn.Server.run(sockets=[...])``. Listening
    from the start: the address is announced before uvicorn's start-up ends, and a client
    that connects then (a performer started with the server, a loaded machine) waits in the
    backlog instead of being refused."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    if send_buffer_bytes > 0:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, send_buffer_bytes)
    sock.bind((host, port))
    sock.listen(LISTEN_BACKLOG)
    return sock


CredentialCheck = Callable[[str | None, str | None], bool]  # (token, ticket) -> valid


def _handshake_credentials(path: str, headers: Any) -> tuple[str | None, str | None]:
    """(bearer token, ticket) a WebSocket handshake carries: the Authorization header or a
    legacy ``?token=``, and ``?ticket=``."""
    query = parse_qs(path.partition("?")[2])
    token = (query["token"][0] if query.get("token") else None) or \
        bearer_token(headers.get("authorization"))  # as server/auth.py token_from_websocket
    ticket = query["ticket"][0] if query.get("ticket") else None
    return token, ticket


def websocket_protocol(preauth_max_bytes: int,
                       valid_credentials: CredentialCheck | None = None) -> Any:
    """A uvicorn ``ws`` protocol class that bounds the first message of connections without
    valid credentials to ``preauth_max_bytes`` (``valid_credentials(token, ticket)``; None:
    every connection is bounded until the app lifts it); ``"auto"`` if uvicorn's
    websockets-sansio protocol is not there (the app's own length check still refuses, after
    the read)."""
    try:
        from uvicorn.protocols.websockets.websockets_sansio_impl import (
            WebSocketsSansIOProtocol,
        )
    except ImportError:  # another uvicorn: the app-level check alone
        return "auto"

    class PreAuthBoundedProtocol(WebSocketsSansIOProtocol):
        def handle_connect(self, event: Any) -> None:
            super().handle_connect(event)
            if self.response.status_code != 101:
                return  # refused
            token, ticket = _handshake_credentials(event.path, event.headers)
            if (token or ticket) and valid_credentials is not None and \
                    valid_credentials(token, ticket):
                return  # authenticated before any message is read
            full = self.conn.max_message_size
            self.conn.max_message_size = preauth_max_bytes

            def lift() -> None:
                self.conn.max_message_size = full

            self.scope["extensions"][PREAUTH_EXTENSION] = {"lift": lift,
                                                           "max_bytes": preauth_max_bytes}

    return PreAuthBoundedProtocol
