"""Rooms and their invitations, in memory behind one lock, written through to a store.

An invitation is a bearer token (``tsr_...``) for one room with one scope: ``perform`` (one
seat) or ``watch``. Only its sha256 is kept. An expired or revoked invitation no longer admits
anyone; participants already in stay.

With a :class:`~.store.RoomStore` (the server's: server/app.py) every change is committed to
it before it shows in memory (a failed write changes nothing and is a 503), and the rooms are
loaded from it when the registry is made: rooms and links survive a restart, ``kill -9``
included. A plain session's private room never reaches the registry, so it is never stored.
"""

from __future__ import annotations

import asyncio
import hashlib
import hmac
import logging
import secrets
import sqlite3
import threading
import time
import uuid
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal

from ..auth import INVITATION_PREFIX, Principal, is_invitation  # noqa: F401 - re-exported

if TYPE_CHECKING:
    from .live import LiveRoom
    from .store import RoomStore

log = logging.getLogger(__name__)

Scope = Literal["perform", "watch"]


class RoomError(Exception):
    """A refused room operation; ``status`` is the HTTP status it maps to."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


@dataclass(frozen=True)
class Placement:
    """A seat's rigid transform in the scene: axis-angle rotation, then translation (m)."""

    translation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class SeatSpec:
    index: int
    avatar: str
    placement: Placement = Placement()


@dataclass
class Invitation:
    id: str
    room_id: str
    digest: str
    scope: Scope
    seat: int | None
    expires_at: float  # unix time
    revoked: bool = False

    def valid(self, now: float) -> bool:
        return not self.revoked and now < self.expires_at


@dataclass
class Room:
    id: str
    name: str
    owner: str
    seats: list[SeatSpec]
    created: float
    pinned: bool = False  # never closed for idleness (the start-up room)
    private: bool = False  # a plain session's room of one: never listed, gone when it ends
    invitations: dict[str, Invitation] = field(default_factory=dict)
    live: LiveRoom | None = None  # the runtime while anyone is (or was recently) in it
    empty_since: float | None = None  # monotonic; None while someone is in it
    opening: asyncio.Lock = field(default_factory=asyncio.Lock, repr=False)  # makes `live`

    def visible_to(self, principal: Principal) -> bool:
        return principal.is_admin or principal.subject == self.owner


def _digest(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


class RoomRegistry:
    """``store`` None: in memory only (tests of the registry alone)."""

    def __init__(self, settings, store: RoomStore | None = None) -> None:
        self.settings = settings
        self.store = store
        self._rooms: dict[str, Room] = {}
        self._lock = threading.Lock()
        if store is not None:  # after a restart nobody is in a room: idle from now on
            self._rooms = {room.id: room for room in store.load(time.monotonic())}

    def _stored(self, write: str, *args) -> None:
        """The store's ``write(*args)`` (no store: nothing to do); a failure is a RoomError
        503, and the caller makes no change."""
        if self.store is None:
            return
        try:
            getattr(self.store, write)(*args)
        except sqlite3.Error as exc:
            log.error("the room store refused a write: %s", exc)
            raise RoomError(503, "rooms cannot be stored right now; try again") from None

    # -- rooms ----------------------------------------------------------------------------------

    def create(self, principal: Principal, name: str | None, seats: list[SeatSpec],
               pinned: bool = False) -> Room:
        s = self.settings
        if not 1 <= len(seats) <= s.max_seats_per_room:
            raise RoomError(422, f"a room has 1 to {s.max_seats_per_room} seats, not "
                                 f"{len(seats)} (max_seats_per_room)")
        with self._lock:
            owned = sum(r.owner == principal.subject for r in self._rooms.values())
            if not principal.is_admin and owned >= s.max_rooms_per_user:
                raise RoomError(429, f"{principal.subject!r} owns {owned} rooms, the most one "
                                     "user may have (max_rooms_per_user); delete one first")
            room_id = uuid.uuid4().hex[:12]
            room = Room(room_id, name or f"room {room_id[:6]}", principal.subject, seats,
                        time.time(), pinned, empty_since=time.monotonic())
            self._stored("add_room", room)
            self._rooms[room_id] = room
        return room

    def get(self, room_id: str) -> Room:
        with self._lock:
            room = self._rooms.get(room_id)
        if room is None:
            raise RoomError(404, f"no room {room_id!r}")
        return room

    def list(self, principal: Principal) -> list[Room]:
        with self._lock:
            return [r for r in self._rooms.values() if r.visible_to(principal)]

    def remove(self, room_id: str) -> Room | None:
        with self._lock:
            if room_id in self._rooms:
                self._stored("remove_rooms", [room_id])
            return self._rooms.pop(room_id, None)

    def live_rooms(self) -> list[Room]:
        """Rooms with a runtime (someone is or was recently in them)."""
        with self._lock:
            return [r for r in self._rooms.values() if r.live is not None]

    def idle_rooms(self, now: float) -> list[Room]:
        """Rooms empty for room_idle_timeout_s (not pinned): taken out of the registry."""
        timeout = self.settings.room_idle_timeout_s
        with self._lock:
            idle = [r for r in self._rooms.values() if not r.pinned
                    and r.empty_since is not None and now - r.empty_since >= timeout]
            try:
                self._stored("remove_rooms", [r.id for r in idle])
            except RoomError:
                return []  # kept, in memory and stored alike: the next sweep tries again
            for room in idle:
                del self._rooms[room.id]
        return idle

    def __len__(self) -> int:
        with self._lock:
            return len(self._rooms)

    # -- invitations ----------------------------------------------------------------------------

    def invite(self, room: Room, scope: Scope, seat: int | None,
               ttl_s: float | None) -> tuple[Invitation, str]:
        """A new invitation and its token (returned once, never stored)."""
        s = self.settings
        if scope == "watch" and seat is not None:
            raise RoomError(422, "a watch invitation has no seat")
        if scope == "perform":
            seat = min(spec.index for spec in room.seats) if seat is None else seat
            if seat not in {spec.index for spec in room.seats}:
                raise RoomError(422, f"room {room.id!r} has no seat {seat}")
        ttl = s.room_invitation_ttl_s if ttl_s is None else ttl_s
        if not 0 < ttl <= s.room_invitation_max_ttl_s:
            raise RoomError(422, f"ttl_s must be in (0, {s.room_invitation_max_ttl_s:g}] "
                                 "(room_invitation_max_ttl_s)")
        token = INVITATION_PREFIX + secrets.token_urlsafe(32)
        now = time.time()
        with self._lock:
            live = [i for i in room.invitations.values() if i.valid(now)]
            if len(live) >= s.max_invitations_per_room:
                raise RoomError(429, f"room {room.id!r} has {len(live)} valid invitations, the "
                                     "most it may have (max_invitations_per_room)")
            inv = Invitation(uuid.uuid4().hex[:12], room.id, _digest(token), scope, seat,
                             now + ttl)
            pruned = [i for i in room.invitations if not room.invitations[i].valid(now)]
            if room.id in self._rooms:  # not deleted meanwhile
                self._stored("add_invitation", inv, pruned)
            room.invitations = {i.id: i for i in live}  # expired / revoked ones pruned
            room.invitations[inv.id] = inv
        return inv, token

    def revoke(self, room: Room, invitation_id: str) -> None:
        with self._lock:
            inv = room.invitations.get(invitation_id)
            if inv is None:
                raise RoomError(404, f"room {room.id!r} has no invitation {invitation_id!r}")
            if room.id in self._rooms:
                self._stored("revoke_invitation", invitation_id)
            inv.revoked = True

    def resolve(self, token: str) -> Invitation | None:
        """The valid invitation of ``token``; None when unknown, expired or revoked."""
        digest, now = _digest(token), time.time()
        with self._lock:
            for room in self._rooms.values():
                for inv in room.invitations.values():
                    if hmac.compare_digest(inv.digest, digest):
                        return inv if inv.valid(now) else None
        return None
