"""The listening socket, made here (not by uvicorn) so that its send buffer can be bounded.

Why: the kernel's send buffer is where a slow client's frames pile up out of the server's
sight. Accepted connections inherit the listener's ``SO_SNDBUF``, so a small one bounds that
backlog (and the lag it means) to about two frames' worth of bytes at 512 px, while loopback
and LAN throughput stay far above what a session sends.
"""

from __future__ import annotations

import socket


def listen_socket(host: str, port: int, send_buffer_bytes: int = 0) -> socket.socket:
    """A bound TCP socket for ``uvicorn.Server.run(sockets=[...])`` (uvicorn listens on it)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    if send_buffer_bytes > 0:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, send_buffer_bytes)
    sock.bind((host, port))
    return sock
