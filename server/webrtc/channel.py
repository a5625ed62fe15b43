"""The data channel that carries a WebRTC session's messages (server/webrtc/transport.py).

:class:`DataChannel` is the peer's data channel labelled ``telesplat``: the session's
receiver, rate limits, decoding and control sender are the WebSocket path's. Messages are the
WebSocket protocol's msgpack messages. The ``welcome`` goes first, as soon as the channel
opens. A peer whose offer has no data channel (a plain WHEP player) still gets its video; its
control messages are dropped.

The channel ends the session only when the peer ends (``disconnect``): a client that closes
just its channel keeps watching. What reaches ``_message`` was reassembled within the peer's
SCTP budgets (server/webrtc/sctp.py); the inbox bounds the messages waiting for the session.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable
from typing import Any

log = logging.getLogger(__name__)

LABEL = "telesplat"
INBOX = 64                   # messages received, not yet read; past it new ones are dropped
MAX_BUFFERED_BYTES = 2**20   # unsent bytes on the channel past which a message is dropped


class DataChannel:
    def __init__(self, on_close: Callable[[str], None], metrics: Any = None) -> None:
        self._on_close = on_close
        self._metrics = metrics
        self._inbox: asyncio.Queue[bytes | str | None] = asyncio.Queue(INBOX)  # None: gone
        self._ready = asyncio.Event()  # open, or disconnected
        self._channel: Any = None
        self.welcome: bytes | None = None  # set before the channel can open
        self.disconnected = False
        self.dropped_in = 0
        self.dropped_out = 0

    @property
    def open(self) -> bool:
        return self._channel is not None and self._channel.readyState == "open"

    def attach(self, channel: Any) -> None:
        """A data channel the client opened; only the first ``telesplat`` one is used."""
        if channel.label != LABEL or self._channel is not None or self.disconnected:
            log.info("ignoring data channel %r", channel.label)
            channel.close()
            return
        self._channel = channel
        channel.on("message", self._message)
        if channel.readyState == "open":
            self._opened()
        else:
            channel.on("open", self._opened)

    def absent(self) -> None:
        """The offer has no data channel (a plain WHEP player): none will ever open, so the
        session's control messages are dropped at once instead of waiting for it (a send
        waiting here would hold the session's send lock, and its frames, forever)."""
        self._ready.set()

    def _opened(self) -> None:
        if self.welcome is not None:
            self._channel.send(self.welcome)
        self._ready.set()

    def _message(self, data: bytes | str) -> None:
        if self.disconnected:
            return
        item = bytes(data) if isinstance(data, (bytes, bytearray)) else data
        try:
            self._inbox.put_nowait(item)
        except asyncio.QueueFull:
            self.dropped_in += 1  # the participant reads slower than the client sends
            if self._metrics is not None:
                self._metrics.webrtc_dc_inbox_dropped.inc()

    # -- what the session's transport calls -----------------------------------------------------

    async def receive(self) -> bytes | str | None:
        """The next message; None once the peer is gone."""
        return await self._inbox.get()

    async def send(self, data: bytes) -> None:
        await self._ready.wait()
        if self.disconnected:
            raise ConnectionResetError("the WebRTC peer is closed")
        channel = self._channel
        if channel is None:  # no data channel in the offer: the video goes on alone
            self.dropped_out += 1
            return
        if channel.readyState != "open":
            return  # the client closed its channel; the video goes on
        if channel.bufferedAmount > MAX_BUFFERED_BYTES:
            self.dropped_out += 1  # the client does not read its channel
            return
        channel.send(data)

    def send_last(self, data: bytes) -> None:
        """Queue ``data`` at once, ahead of a close (it goes out before the peer's teardown
        aborts the association); nothing when the channel is not open."""
        if self.open and not self.disconnected:
            with contextlib.suppress(Exception):
                self._channel.send(data)

    def close(self, reason: str) -> None:
        """The session ends the peer (its room closed)."""
        self._on_close(reason)

    # -- the peer's side ------------------------------------------------------------------------

    def disconnect(self) -> None:
        """The peer is gone: the participant's receiver sees a disconnect next."""
        if self.disconnected:
            return
        self.disconnected = True
        while not self._inbox.empty():
            self._inbox.get_nowait()
        self._inbox.put_nowait(None)
        self._ready.set()
        if self._channel is not None:
            with contextlib.suppress(Exception):
                self._channel.close()
