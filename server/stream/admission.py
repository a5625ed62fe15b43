"""Who may hold a session: connections waiting to authenticate, sessions in all and per
principal, tickets; and :func:`admit`, the one admission of every entry (a WebSocket plain
session or room join, a WHEP / WHIP peer).

All are counters behind a lock, taken before the work they guard and released in a
``finally``; nothing here touches a socket.
"""

from __future__ import annotations

import threading
from collections import Counter
from dataclasses import dataclass
from typing import TYPE_CHECKING

from ..auth import Principal
from .gate import CLOSE_BUSY, CLOSE_TOO_MANY, Refusal
from .tickets import TicketBook

if TYPE_CHECKING:
    from ..context import ServerContext
    from ..rooms.registry import Invitation


class KeyedSlots:
    """At most ``per_key`` held per key and, if given, ``total`` held over all keys."""

    def __init__(self, per_key: int, total: int | None = None) -> None:
        self.per_key = per_key
        self.total = total
        self._held: Counter[str] = Counter()
        self._total = 0
        self._lock = threading.Lock()

    def try_acquire(self, key: str) -> str | None:
        """None when acquired, else which limit refused it: ``"key"`` or ``"total"``."""
        with self._lock:
            if self.total is not None and self._total >= self.total:
                return "total"
            if self._held[key] >= self.per_key:
                return "key"
            self._held[key] += 1
            self._total += 1
            return None

    def release(self, key: str) -> None:
        with self._lock:
            if self._held[key] <= 0:
                return  # not held: a release without an acquire changes nothing
            self._held[key] -= 1
            self._total -= 1
            if not self._held[key]:
                del self._held[key]

    def count(self, key: str | None = None) -> int:
        with self._lock:
            return self._total if key is None else self._held.get(key, 0)


@dataclass
class Admission:
    """The server's WebSocket admission state (see Settings for the limits)."""

    waiting: KeyedSlots      # per client address, and in total, until authenticated
    sessions: KeyedSlots     # per token subject
    invitations: KeyedSlots  # per room invitation (an invitation is a principal of its own)
    tickets: TicketBook      # single-use stand-ins for a token in a WebSocket URL

    @classmethod
    def from_settings(cls, settings) -> Admission:
        return cls(waiting=KeyedSlots(settings.max_unauthenticated_per_address,
                                      settings.max_unauthenticated),
                   sessions=KeyedSlots(settings.max_sessions_per_user),
                   invitations=KeyedSlots(settings.max_sessions_per_invitation),
                   tickets=TicketBook(settings.ticket_ttl_s, settings.max_tickets_per_user))


class SessionSlots:
    """At most ``limit`` sessions at once."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.count = 0
        self._lock = threading.Lock()

    def try_acquire(self, reserved: int = 0) -> bool:
        """A slot, unless fewer than ``reserved`` + 1 are free."""
        with self._lock:
            if self.count >= self.limit - reserved:
                return False
            self.count += 1
            return True

    def release(self) -> None:
        with self._lock:
            self.count = max(0, self.count - 1)


class Admitted:
    """A session's place on the server: a ``max_sessions`` slot and one of its principal's
    (a token subject's ``max_sessions_per_user``, an invitation's
    ``max_sessions_per_invitation``). ``release`` gives them back (once)."""

    def __init__(self, ctx: ServerContext, counts: KeyedSlots | None, key: str | None) -> None:
        self._ctx, self._counts, self._key = ctx, counts, key
        self._held = True

    def release(self) -> None:
        if not self._held:
            return
        self._held = False
        ctx = self._ctx
        ctx.slots.release()
        if self._counts is not None:
            self._counts.release(self._key)
        ctx.metrics.sessions.set(ctx.slots.count)


def admit(ctx: ServerContext, principal: Principal | None,
          invitation: Invitation | None) -> Admitted:
    """A session slot for whoever the credentials name (Refusal ``busy`` otherwise): the one
    admission of the WebSocket and WebRTC entries. A token subject counts against
    ``max_sessions_per_user`` (admins exempt), an invitation against
    ``max_sessions_per_invitation``; invitation holders never take the ``reserved_sessions``
    kept for token holders (a room's owner, an admin)."""
    s = ctx.settings
    reserved = s.reserved_sessions if invitation is not None else 0
    if not ctx.slots.try_acquire(reserved):
        extra = (f" ({reserved} of {ctx.slots.limit} are kept for room owners and admins)"
                 if reserved else "")
        raise Refusal("busy", f"server busy: {ctx.slots.limit} sessions are open{extra}; "
                              "try again later", CLOSE_BUSY)
    counts, key = None, None
    if invitation is not None:
        counts, key = ctx.admission.invitations, invitation.id
        limit, who = s.max_sessions_per_invitation, "this invitation"
    elif principal is not None and not principal.is_admin:
        counts, key = ctx.admission.sessions, principal.subject
        limit, who = s.max_sessions_per_user, repr(principal.subject)
    if counts is not None and counts.try_acquire(key) is not None:
        ctx.slots.release()
        raise Refusal("busy", f"{who} has {limit} sessions open, the most one "
                              f"{'invitation' if invitation is not None else 'user'} may "
                              "have; close one first", CLOSE_TOO_MANY)
    ctx.metrics.sessions.set(ctx.slots.count)
    ctx.metrics.sessions_total.inc()
    return Admitted(ctx, counts, key)
