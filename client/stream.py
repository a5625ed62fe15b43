"""An asyncio client for one streaming session (WebSocket ``/v1/stream``).

    async with await StreamClient.connect("http://127.0.0.1:8000", "demo", token) as client:
        seq = await client.drive(smplx={"jaw_pose": [0.2, 0, 0]})
        frame = await client.wait_frame(seq, timeout=5)
        rgb = decode_image(frame)

A reader task demultiplexes what the server sends: frames go to a bounded queue (the oldest is
dropped when the consumer falls behind, so memory stays flat), ``stats`` and ``error`` messages
are kept on the client, ``pong`` answers :meth:`ping`.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import time
from collections.abc import AsyncIterator, Callable, Mapping
from typing import Any
from urllib.parse import urlencode, urlsplit, urlunsplit

import numpy as np
from pydantic import BaseModel, ValidationError

from protocol import (
    FAMILIES,
    CameraSpec,
    Drive,
    Error,
    Frame,
    Hello,
    Image,
    Orbit,
    Ping,
    Pong,
    Presence,
    ProtocolError,
    Request,
    RoomWelcome,
    Stats,
    View,
    Welcome,
    decode_server,
    encode,
)

# Codes after which the server closes the session.
# A viewer's drive or image gets `forbidden` with `answers` set and the session goes on: only
# a refusal that answers nothing closes it.
FATAL_CODES = frozenset({"unauthorized", "forbidden", "not_found", "busy", "version", "gone"})
MAX_WIRE_BYTES = 64 * 1024 * 1024


class StreamError(RuntimeError):
    """The server refused the session or closed it; ``code`` is a protocol error code."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message


def stream_url(server: str, avatar: str | None = None, *, room: str | None = None) -> str:
    """``ws(s)://host/v1/stream?avatar=...`` (or ``?room=...``) from an http(s) or ws(s) base
    URL. Never with the token: URLs end up in logs; it goes in the ``Authorization`` header."""
    if (avatar is None) == (room is None):
        raise ValueError("give exactly one of avatar and room")
    parts = urlsplit(server if "://" in server else f"http://{server}")
    scheme = {"http": "ws", "https": "wss"}.get(parts.scheme, parts.scheme)
    path = parts.path.rstrip("/")
    if not path.endswith("/v1/stream"):
        path += "/v1/stream"
    query = urlencode({"room": room} if room is not None else {"avatar": avatar})
    return urlunsplit((scheme, parts.netloc, path, query, ""))


ROLES = ("perform", "watch")


def room_hello(client_name: str, *, room: str | None = None, role: str | None = None,
               seat: int | None = None) -> Hello:
    """The hello: role and seat only in a room (a plain session's hello stays as it was)."""
    if room is None:
        if role is not None or seat is not None:
            raise ValueError("role and seat are for rooms only")
        return Hello(client=client_name)
    if role is not None and role not in ROLES:
        raise ValueError(f"role must be one of {ROLES}, not {role!r}")
    fields = {k: v for k, v in (("role", role), ("seat", seat)) if v is not None}
    return Hello.model_validate({"client": client_name, **fields})


def _float32(values: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    # float32 halves the bytes on the wire; the renderer works in float32 anyway.
    return {k: np.asarray(v, dtype=np.float32) for k, v in values.items()}


def _model(cls: type[BaseModel], value: Any) -> BaseModel | None:
    if value is None or isinstance(value, cls):
        return value
    return cls.model_validate(value)


class StreamClient:
    """One session. Make it with :meth:`connect`; use it as an async context manager."""

    def __init__(self, ws: Any, welcome: Welcome, queue_size: int = 64) -> None:
        self._ws = ws
        self.welcome = welcome
        self.limits = welcome.limits
        self.stats: Stats | None = None       # the latest stats message
        self.errors: list[Error] = []         # every error message, oldest first
        self.frames_dropped = 0               # frames the consumer did not take in time
        self.closed: StreamError | None = None
        self.latencies: collections.deque[float] = collections.deque(maxlen=1000)  # seconds
        self._seq = 0
        self._sent_at: dict[int, float] = {}  # seq -> monotonic time sent
        self._frames: asyncio.Queue[Frame | None] = asyncio.Queue(maxsize=queue_size)
        self._pongs: dict[float, asyncio.Future[float]] = {}
        self._frame_event = asyncio.Event()
        self.room: RoomWelcome | None = welcome.room  # None outside rooms
        self.presence: Presence | None = None  # the latest presence message (rooms only)
        self._presence_event = asyncio.Event()
        self._reader = asyncio.create_task(self._read())

    # -- connecting -----------------------------------------------------------------------

    @classmethod
    async def connect(cls, server: str, avatar: str | None = None, token: str | None = None,
                      *, room: str | None = None, role: str | None = None,
                      seat: int | None = None, client_name: str = "telesplat-python",
                      timeout: float = 30.0, queue_size: int = 64) -> StreamClient:
        """Open a session on ``avatar``, or join ``room`` (``role`` "perform" or "watch" and
        ``seat``; both default to what the token allows); returns once ``welcome`` arrived
        (StreamError if the server refuses). ``server`` is the base URL (http://host:port) or
        a full ws:// URL."""
        hello = room_hello(client_name, room=room, role=role, seat=seat)
        from websockets.asyncio.client import connect
        from websockets.exceptions import ConnectionClosed

        # The token in the header: authenticated at the handshake, so the server's limits on
        # connections still waiting for a hello (a few per address and in total) never apply.
        headers = {"Authorization": f"Bearer {token}"} if token else None
        ws = await connect(stream_url(server, avatar, room=room), compression=None,
                           max_size=MAX_WIRE_BYTES, proxy=None, open_timeout=timeout,
                           user_agent_header=client_name, additional_headers=headers)
        try:
            with contextlib.suppress(ConnectionClosed):  # refused already: read why below
                await ws.send(encode(hello))
            welcome = await asyncio.wait_for(cls._first(ws), timeout)
        except BaseException:
            await ws.close()
            raise
        return cls(ws, welcome, queue_size)

    @staticmethod
    async def _first(ws: Any) -> Welcome:
        from websockets.exceptions import ConnectionClosed

        try:
            while True:  # bounded by the caller's timeout
                message = decode_server(await ws.recv())
                if isinstance(message, Welcome):
                    return message
                if isinstance(message, Error):
                    raise StreamError(message.code, message.message)
        except ConnectionClosed as exc:
            raise StreamError("internal", f"the server closed the connection: {exc}") from exc

    async def __aenter__(self) -> StreamClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def close(self) -> None:
        self._reader.cancel()
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await self._reader
        await self._ws.close()

    # -- sending --------------------------------------------------------------------------

    async def _send(self, message: BaseModel) -> None:
        if self.closed is not None:
            raise self.closed
        await self._ws.send(encode(message))

    def _next_seq(self) -> int:
        self._seq += 1
        return self._seq

    async def drive(self, smplx: Mapping[str, Any] | None = None, *,
                    flame: Mapping[str, Any] | None = None,
                    mano_left: Mapping[str, Any] | None = None,
                    mano_right: Mapping[str, Any] | None = None, reset: bool = False,
                    seq: int | None = None, **smplx_fields: Any) -> int:
        """Send (partial) parameters; returns the seq the matching frame will carry.

        SMPL-X fields may also come as keywords: ``drive(jaw_pose=[0.2, 0, 0])``.
        Parameters are validated here first, so a bad shape fails before it is sent.
        """
        if smplx_fields:
            smplx = {**(smplx or {}), **smplx_fields}
        seq = self._next_seq() if seq is None else seq
        try:
            message = Drive.model_validate(
                {"seq": seq, "smplx": smplx, "flame": flame, "mano_left": mano_left,
                 "mano_right": mano_right, "reset": reset},
                context={"limits": self.limits})
        except ValidationError as exc:
            raise ProtocolError("invalid", str(exc)) from exc
        update = {name: _float32(values) for name, values in message.families().items()}
        message = message.model_copy(update=update)
        self._sent_at[seq] = time.monotonic()
        if len(self._sent_at) > 4096:  # forget the oldest: frames skip coalesced seqs
            for old in sorted(self._sent_at)[:2048]:
                del self._sent_at[old]
        await self._send(message)
        return seq

    async def view(self, orbit: Orbit | Mapping[str, Any] | None = None, *,
                   camera: CameraSpec | Mapping[str, Any] | None = None,
                   moving: bool = False) -> None:
        """Look from an orbit (yaw_deg, pitch_deg, distance, fov_y_deg, target) or a camera."""
        await self._send(View(orbit=_model(Orbit, orbit), camera=_model(CameraSpec, camera),
                              moving=moving))

    async def request(self, **fields: Any) -> None:
        """Change what is rendered: width, height, outputs, background, quality, codec, ..."""
        await self._send(Request.model_validate(fields, context={"limits": self.limits}))

    async def image(self, data: bytes, format: str = "jpeg") -> int:
        """Send an encoded webcam frame for server-side tracking; returns its seq."""
        seq = self._next_seq()
        self._sent_at[seq] = time.monotonic()
        await self._send(Image.model_validate({"seq": seq, "format": format, "data": data},
                                              context={"limits": self.limits}))
        return seq

    async def ping(self, timeout: float = 5.0) -> float:
        """Round-trip time in seconds."""
        t = time.monotonic()
        future: asyncio.Future[float] = asyncio.get_running_loop().create_future()
        self._pongs[t] = future
        try:
            await self._send(Ping(t=t))
            return await asyncio.wait_for(future, timeout)
        finally:
            self._pongs.pop(t, None)

    # -- receiving ------------------------------------------------------------------------

    async def _read(self) -> None:
        from websockets.exceptions import ConnectionClosed

        try:
            async for raw in self._ws:
                self._dispatch(decode_server(raw))
        except ConnectionClosed as exc:
            self.closed = StreamError("internal", f"connection closed: {exc}")
        except ProtocolError as exc:
            self.closed = StreamError(exc.code, f"bad message from the server: {exc.message}")
        else:
            self.closed = StreamError("internal", "connection closed")
        finally:
            if self.closed is None:
                self.closed = StreamError("internal", "connection closed")
            self._put(None)
            self._frame_event.set()
            self._presence_event.set()

    def _dispatch(self, message: Any) -> None:
        if isinstance(message, Frame):
            sent = self._sent_at.pop(message.seq, None)
            if sent is not None:
                self.latencies.append(time.monotonic() - sent)
            self._put(message)
            self._frame_event.set()
        elif isinstance(message, Stats):
            self.stats = message
        elif isinstance(message, Pong):
            future = self._pongs.get(message.t)
            if future is not None and not future.done():
                future.set_result(time.monotonic() - message.t)
        elif isinstance(message, Presence):
            self.presence = message
            self._presence_event.set()
        elif isinstance(message, Error):
            self.errors.append(message)
            if message.code in FATAL_CODES and message.answers is None:
                self.closed = StreamError(message.code, message.message)

    def _put(self, frame: Frame | None) -> None:
        while True:  # at most maxsize iterations: each one frees a slot
            try:
                self._frames.put_nowait(frame)
                return
            except asyncio.QueueFull:
                self._frames.get_nowait()
                self.frames_dropped += 1

    def __aiter__(self) -> AsyncIterator[Frame]:
        return self.frames()

    async def frames(self) -> AsyncIterator[Frame]:
        """Frames as they arrive, until the session ends (then StreamError if it failed)."""
        while True:
            frame = await self._frames.get()
            if frame is None:
                self._frames.put_nowait(None)  # later iterators end too
                if self.closed is not None and self.closed.code != "internal":
                    raise self.closed
                return
            yield frame

    async def next_frame(self, timeout: float = 10.0) -> Frame:
        """The next frame from the queue; StreamError if the session ended first."""
        frame = await asyncio.wait_for(self._frames.get(), timeout)
        if frame is None:
            self._frames.put_nowait(None)
            raise self.closed or StreamError("internal", "connection closed")
        return frame

    async def wait_frame(self, seq: int, timeout: float = 10.0) -> Frame:
        """The first frame reflecting drive ``seq`` or a later one (frames may coalesce seqs).

        Frames taken from the queue on the way are consumed.
        """
        deadline = time.monotonic() + timeout
        while True:  # bounded by the deadline
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"no frame for seq {seq} within {timeout} s")
            frame = await self.next_frame(left)
            if frame.seq >= seq:
                return frame

    async def wait_presence(self, predicate: Callable[[Presence], bool],
                            timeout: float = 10.0) -> Presence:
        """The first presence (the latest one included) for which ``predicate`` is true."""
        deadline = time.monotonic() + timeout
        while True:  # bounded by the deadline
            if self.presence is not None and predicate(self.presence):
                return self.presence
            if self.closed is not None:
                raise self.closed
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"no matching presence within {timeout} s")
            self._presence_event.clear()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._presence_event.wait(), left)

    def errors_for(self, seq: int) -> list[Error]:
        """Errors that answer the message with ``seq``."""
        return [e for e in self.errors if e.answers is not None and e.answers.seq == seq]


def params_of(frame: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """A per-frame dict (family-keyed, or plain SMPL-X fields) as drive keyword arguments."""
    out: dict[str, dict[str, Any]] = {}
    for key, value in frame.items():
        if key in FAMILIES:
            out.setdefault(key, {}).update(value)
        elif key in FAMILIES["smplx"]:
            out.setdefault("smplx", {})[key] = value
        else:
            raise ProtocolError("invalid", f"unknown parameter {key!r}; expected a family "
                                           f"{sorted(FAMILIES)} or an SMPL-X field")
    return out
