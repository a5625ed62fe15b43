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
from its header (close 1009) and never read. ``/v1/stream`` lifts the limit once the hello's
token is valid (through the ASGI scope extension ``PREAUTH_EXTENSION``).
"""

from __future__ import annotations

import socket
from typing import Any
from urllib.parse import parse_qs

PREAUTH_EXTENSION = "telesplat.preauth"  # scope["extensions"][...]["lift"]() -> full size


def listen_socket(host: str, port: int, send_buffer_bytes: int = 0) -> socket.socket:
    """A bound TCP socket for ``uvicorn.Server.run(sockets=[...])`` (uvicorn listens on it)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    if send_buffer_bytes > 0:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, send_buffer_bytes)
    sock.bind((host, port))
    return sock


def _carries_credentials(path: str, headers: Any) -> bool:
    query = parse_qs(path.partition("?")[2])
    return "authorization" in headers or "token" in query or "ticket" in query


def websocket_protocol(preauth_max_bytes: int) -> Any:
    """A uvicorn ``ws`` protocol class that bounds the first message of connections without
    credentials to ``preauth_max_bytes``; ``"auto"`` if uvicorn's websockets-sansio protocol
    is not there (the app's own length check still refuses, after the read)."""
    try:
        from uvicorn.protocols.websockets.websockets_sansio_impl import (
            WebSocketsSansIOProtocol,
        )
    except ImportError:  # another uvicorn: the app-level check alone
        return "auto"

    class PreAuthBoundedProtocol(WebSocketsSansIOProtocol):
        def handle_connect(self, event: Any) -> None:
            super().handle_connect(event)
            if self.response.status_code != 101 or _carries_credentials(event.path,
                                                                        event.headers):
                return  # refused, or authenticated before any message is read
            full = self.conn.max_message_size
            self.conn.max_message_size = preauth_max_bytes

            def lift() -> None:
                self.conn.max_message_size = full

            self.scope["extensions"][PREAUTH_EXTENSION] = {"lift": lift,
                                                           "max_bytes": preauth_max_bytes}

    return PreAuthBoundedProtocol
