"""An asyncio client for one streaming session (WebSocket ``/v1/stream``).

    async with await StreamClient.connect("http://127.0.0.1:8000", "demo", token) as client:
        seq = await client.drive(smplx={"jaw_pose": [0.2, 0, 0]})
        frame = await client.wait_frame(seq, timeout=5)
        rgb = decode_image(frame)

A reader task demultiplexes what the server sends: frames go to a bounded queue (the oldest is
dropped when the consumer falls behind, so memory stays flat), ``stats`` and ``error`` messages
are kept on the client, ``pong`` answers :meth:`ping`.

With ``reconnect=Backoff()`` the client reconnects by itself after error ``restarting``, a
connection closed with 1012 (service restart), 1001 (going away) or 1006 (dropped, as after a
``kill -9``), and after each failed try: waits of 0.25 s doubling to 4 s, each shortened by
a random part of up to half (jitter), at most ``attempts`` tries in a row. It joins the same
room with the same token, role and seat, then sends its last ``request`` and ``view`` again;
frames keep coming through the same queue, and sends made meanwhile wait for the new
connection. A room that is gone (``not_found`` 4404, ``gone`` 4410) or a token no longer
valid ends the retries at once with that error. :attr:`StreamClient.reconnections` records
each one (why, when the connection was lost, when it was back, how many tries).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import random
import time
from collections.abc import AsyncIterator, Callable, Mapping
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlencode, urlsplit, urlunsplit

import numpy as np
from pydantic import BaseModel, ValidationError

from protocol import (
    FAMILIES,
    AvatarReplaced,
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
    Voice,
    Welcome,
    decode_server,
    encode,
)

# Codes after which the server closes the session.
# A viewer's drive or image gets `forbidden` with `answers` set and the session goes on: only
# a refusal that answers nothing closes it.
FATAL_CODES = frozenset({"unauthorized", "forbidden", "not_found", "busy", "version", "gone"})
# Refusals that end reconnecting: the room, the token or the seat will not come back by waiting
# (``busy`` may: a full server is tried again).
FINAL_CODES = FATAL_CODES - {"busy"}
RESTARTING = "restarting"  # error code: the server restarts, the connection closes next
RECONNECT_CLOSE_CODES = frozenset({1001, 1006, 1012})  # going away, dropped, service restart
MAX_WIRE_BYTES = 64 * 1024 * 1024

log = logging.getLogger("telesplat.client")


@dataclass(frozen=True)
class Backoff:
    """How a client reconnects: try ``attempt`` (0-based) waits ``initial_s * 2**attempt``,
    at most ``max_s``, shortened by a random fraction of up to ``jitter`` (so clients that
    lost one server do not all come back at once); after ``attempts`` failed tries in a row
    it gives up. Defaults: 0.25 s, 0.5 s, 1 s, 2 s, 4 s, 4 s, ... for 10 tries (about 28 s
    at most, fewer with jitter)."""

    attempts: int = 10
    initial_s: float = 0.25
    max_s: float = 4.0
    jitter: float = 0.5

    def __post_init__(self) -> None:
        if self.attempts < 0 or not 0 < self.initial_s <= self.max_s or \
                not 0 <= self.jitter < 1:
            raise ValueError("Backoff wants attempts >= 0, 0 < initial_s <= max_s and "
                             "0 <= jitter < 1")

    def delay(self, attempt: int, rand: Callable[[], float] = random.random) -> float:
        """Seconds to wait before try ``attempt`` (0-based)."""
        base = min(self.max_s, self.initial_s * 2.0 ** min(attempt, 32))
        return base * (1.0 - self.jitter * rand())


@dataclass(frozen=True)
class Reconnection:
    """One reconnection: why (``restarting``, or the close code), when the connection was lost
    and when the new one had its welcome (monotonic seconds), and the tries it took."""

    reason: str
    lost_at: float
    back_at: float
    attempts: int

    @property
    def downtime_s(self) -> float:
        return self.back_at - self.lost_at


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
               seat: int | None = None, name: str | None = None,
               voice: bool | str = False) -> Hello:
    """The hello: role, seat, the display name ``name`` (what others see in presence;
    ValueError if the protocol refuses it) and voice (True: each seat's; "mix": the room's one
    mix, watching) only in a room (a plain session's hello stays as it was)."""
    if room is None:
        if role is not None or seat is not None or name is not None or voice:
            raise ValueError("role, seat, name and voice are for rooms only")
        return Hello(client=client_name)
    if role is not None and role not in ROLES:
        raise ValueError(f"role must be one of {ROLES}, not {role!r}")
    if voice not in (False, True, "mix"):
        raise ValueError(f"voice must be True, False or 'mix', not {voice!r}")
    fields = {k: v for k, v in (("role", role), ("seat", seat), ("name", name),
                                ("voice", bool(voice) or None),
                                ("voice_mix", voice == "mix" or None)) if v is not None}
    return Hello.model_validate({"client": client_name, **fields})


def _why_not(where: str, refusal: StreamError) -> str:
    """Why a rejoin will not be tried again, in words."""
    if refusal.code in ("not_found", "gone"):
        return f"{where} is gone"
    if refusal.code == "unauthorized":  # an invitation dies with its room
        return (f"cannot rejoin {where}: the token is no longer valid (revoked or expired, or "
                "an invitation of a room that was deleted)")
    return f"cannot rejoin {where}"


def _float32(values: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    # float32 halves the bytes on the wire; the renderer works in float32 anyway.
    return {k: np.asarray(v, dtype=np.float32) for k, v in values.items()}


def _model(cls: type[BaseModel], value: Any) -> BaseModel | None:
    if value is None or isinstance(value, cls):
        return value
    return cls.model_validate(value)


class StreamClient:
    """One session. Make it with :meth:`connect`; use it as an async context manager."""

    def __init__(self, ws: Any, welcome: Welcome, queue_size: int = 64, *,
                 join: dict[str, Any] | None = None, reconnect: Backoff | None = None) -> None:
        self._ws: Any = ws  # None while reconnecting
        self._join = dict(join or {})  # what _open needs to join the same room and seat again
        self._backoff = reconnect if join is not None else None
        self.reconnections: list[Reconnection] = []
        self._restart_notice = False  # error `restarting` on the current connection
        self._changed = asyncio.Event()  # set (and replaced) when the connection changes
        self._request_fields: dict[str, Any] = {}  # every request's fields, merged: replayed
        self._view: View | None = None              # the last view: replayed
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
        # Called with each voice message (join with voice=True) and time.monotonic() at arrival.
        self.on_voice: Callable[[Voice, float], None] | None = None
        self._voice_seq = 0
        self._keep_seat(welcome)
        self._reader = asyncio.create_task(self._read())

    # -- connecting -----------------------------------------------------------------------

    @classmethod
    async def connect(cls, server: str, avatar: str | None = None, token: str | None = None,
                      *, room: str | None = None, role: str | None = None,
                      seat: int | None = None, client_name: str = "telesplat-python",
                      timeout: float = 30.0, queue_size: int = 64,
                      reconnect: Backoff | None = None, name: str | None = None,
                      voice: bool | str = False) -> StreamClient:
        """Open a session on ``avatar``, or join ``room`` (``role`` "perform" or "watch" and
        ``seat``; both default to what the token allows; ``name``: the display name others
        see, default "performer" / "viewer N"); returns once ``welcome`` arrived
        (StreamError if the server refuses). ``server`` is the base URL (http://host:port) or
        a full ws:// URL. ``reconnect``: reconnect by itself after a restart or a dropped
        connection (see the module); None: the session ends with its connection. ``voice``:
        hear the room's other seats (``on_voice``); "mix": one mix of them all instead
        (``voice`` messages without a seat; viewers only)."""
        join = {"server": server, "avatar": avatar, "token": token, "room": room,
                "role": role, "seat": seat, "client_name": client_name, "timeout": timeout,
                "name": name, "voice": voice}
        ws, welcome = await cls._open(**join)
        return cls(ws, welcome, queue_size, join=join, reconnect=reconnect)

    @classmethod
    async def _open(cls, server: str, avatar: str | None, token: str | None, room: str | None,
                    role: str | None, seat: int | None, client_name: str,
                    timeout: float, name: str | None = None,
                    voice: bool | str = False) -> tuple[Any, Welcome]:
        """A connection and its welcome."""
        hello = room_hello(client_name, room=room, role=role, seat=seat, name=name,
                           voice=voice)
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
        return ws, welcome

    def _keep_seat(self, welcome: Welcome) -> None:
        """Rejoin as what the server made of us: the role it gave, a performer's seat."""
        if welcome.room is not None:
            self._join["role"] = welcome.room.role
            if welcome.room.role == "perform":
                self._join["seat"] = welcome.room.seat

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
        if self._ws is not None:
            await self._ws.close()

    @property
    def reconnecting(self) -> bool:
        """Between a lost connection and the next welcome."""
        return self._ws is None and self.closed is None

    def _notify(self) -> None:
        self._changed.set()
        self._changed = asyncio.Event()

    async def _until(self, ready: Callable[[], bool]) -> None:
        """Until ``ready()``; bounded by the reader, which notifies every change and gives up
        after its bounded tries (then ``closed`` is set)."""
        while not ready():
            await self._changed.wait()

    # -- sending --------------------------------------------------------------------------

    async def _send(self, message: BaseModel) -> None:
        from websockets.exceptions import ConnectionClosed

        data = encode(message)
        for _ in range(3):  # a connection lost under the send: again on the next one
            await self._until(lambda: self.closed is not None or self._ws is not None)
            if self.closed is not None:
                raise self.closed
            ws = self._ws
            try:
                await ws.send(data)
                return
            except ConnectionClosed:
                if self._backoff is None:
                    raise
                await self._until(lambda ws=ws: self.closed is not None or self._ws is not ws)
        raise StreamError("internal", "the connection was lost while sending, three times")

    def _next_seq(self) -> int:
        self._seq += 1
        return self._seq

    async def drive(self, smplx: Mapping[str, Any] | None = None, *,
                    flame: Mapping[str, Any] | None = None,
                    mano_left: Mapping[str, Any] | None = None,
                    mano_right: Mapping[str, Any] | None = None, reset: bool = False,
                    seq: int | None = None, t_capture: float | None = None,
                    **smplx_fields: Any) -> int:
        """Send (partial) parameters; returns the seq the matching frame will carry.

        SMPL-X fields may also come as keywords: ``drive(jaw_pose=[0.2, 0, 0])``.
        Parameters are validated here first, so a bad shape fails before it is sent.
        ``t_capture``: when their source was captured (this performer's monotonic clock, in
        seconds); the frames that show them carry it back, and voices sync to it.
        """
        if smplx_fields:
            smplx = {**(smplx or {}), **smplx_fields}
        seq = self._next_seq() if seq is None else seq
        try:
            message = Drive.model_validate(
                {"seq": seq, "smplx": smplx, "flame": flame, "mano_left": mano_left,
                 "mano_right": mano_right, "reset": reset, "t_capture": t_capture},
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
        self._view = View(orbit=_model(Orbit, orbit), camera=_model(CameraSpec, camera),
                          moving=moving)
        await self._send(self._view)

    async def request(self, **fields: Any) -> None:
        """Change what is rendered: width, height, outputs, background, quality, codec, ..."""
        message = Request.model_validate(fields, context={"limits": self.limits})
        self._request_fields.update(fields)
        await self._send(message)

    async def image(self, data: bytes, format: str = "jpeg",
                    t_capture: float | None = None) -> int:
        """Send an encoded webcam frame for server-side tracking; returns its seq.
        ``t_capture``: when the camera took it (the clock of this performer's voice): the
        drive tracked from it, and so the frames showing it, carry it (lip sync)."""
        seq = self._next_seq()
        self._sent_at[seq] = time.monotonic()
        await self._send(Image.model_validate({"seq": seq, "format": format, "data": data,
                                               "t_capture": t_capture},
                                              context={"limits": self.limits}))
        return seq

    async def voice(self, data: bytes, t_capture: float | None = None,
                    level_dbov: float | None = None) -> None:
        """One Opus packet of this performer's voice (``t_capture``: its first sample's
        capture time on the clock the drives' t_capture use; ``level_dbov``: its loudness,
        RFC 6464's dBov, -127..0, what presence's ``speaking`` follows)."""
        await self._send(Voice(seq=self._voice_seq, data=data, t_capture=t_capture,
                               level_dbov=level_dbov))
        self._voice_seq += 1

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
            while True:  # one pass per connection; reconnections end after bounded tries
                ws, lost = self._ws, None
                self._restart_notice = False
                try:
                    async for raw in ws:
                        self._dispatch(decode_server(raw))
                except ConnectionClosed as exc:
                    lost = StreamError("internal", f"connection closed: {exc}")
                except ProtocolError as exc:
                    self.closed = StreamError(exc.code,
                                              f"bad message from the server: {exc.message}")
                    return
                lost_at = time.monotonic()
                code = ws.close_code or 1006
                if self.closed is not None or self._backoff is None or not (
                        self._restart_notice or code in RECONNECT_CLOSE_CODES):
                    if self.closed is None:
                        self.closed = lost or StreamError("internal", "connection closed")
                    return
                reason = RESTARTING if self._restart_notice else f"closed {code}"
                if not await self._reconnect(reason, lost_at):
                    return
        finally:
            if self.closed is None:
                self.closed = StreamError("internal", "connection closed")
            self._put(None)
            self._frame_event.set()
            self._presence_event.set()
            self._notify()

    async def _reconnect(self, reason: str, lost_at: float) -> bool:
        """Join the same room and seat again (see the module); False (``closed`` set) when
        the room is gone, the token refused, or every try failed."""
        self._ws = None
        self._notify()
        where = f"room {self._join['room']}" if self._join.get("room") else "the session"
        tries, last = self._backoff.attempts, "no try allowed"
        for attempt in range(tries):
            delay = self._backoff.delay(attempt)
            log.warning("%s: connection lost (%s); reconnecting in %.2f s (try %d of %d)",
                        where, reason, delay, attempt + 1, tries)
            await asyncio.sleep(delay)
            try:
                ws, welcome = await self._open(**self._join)
            except StreamError as exc:
                if exc.code in FINAL_CODES:
                    self.closed = StreamError(exc.code, f"{_why_not(where, exc)}: "
                                                        f"{exc.message}; not reconnecting")
                    return False
                last = str(exc)
            except Exception as exc:  # noqa: BLE001 - refused, reset, timed out, HTTP 5xx...
                last = f"{type(exc).__name__}: {exc}"  # ...: tried again, a bounded number
            else:
                await self._adopt(ws, welcome)
                self.reconnections.append(Reconnection(reason, lost_at, time.monotonic(),
                                                       attempt + 1))
                log.warning("%s: reconnected after %.2f s (%d tries)", where,
                            time.monotonic() - lost_at, attempt + 1)
                return True
        self.closed = StreamError("internal", f"could not reconnect to {where} in {tries} "
                                              f"tries ({reason}); the last: {last}")
        return False

    async def _adopt(self, ws: Any, welcome: Welcome) -> None:
        """The new connection: its welcome, then our last request and view again."""
        from websockets.exceptions import ConnectionClosed

        self.welcome, self.limits, self.room = welcome, welcome.limits, welcome.room
        self._keep_seat(welcome)
        with contextlib.suppress(ConnectionClosed, ValidationError, ProtocolError):
            if self._request_fields:
                await ws.send(encode(Request.model_validate(
                    self._request_fields, context={"limits": self.limits})))
            if self._view is not None:
                await ws.send(encode(self._view))
        self._ws = ws
        self._notify()

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
        elif isinstance(message, Voice):
            if self.on_voice is not None:
                self.on_voice(message, time.monotonic())
        elif isinstance(message, AvatarReplaced):  # the trained demo, swapped in: same link
            if message.avatar.id == self.welcome.avatar.id:
                self.welcome = self.welcome.model_copy(update={"avatar": message.avatar})
        elif isinstance(message, Error):
            self.errors.append(message)
            if message.code == RESTARTING:
                self._restart_notice = True
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
