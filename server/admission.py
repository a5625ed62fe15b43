"""Who may hold a WebSocket: connections waiting to authenticate, sessions per user, tickets.

Both are counters behind a lock, taken before the work they guard and released in a
``finally``; nothing here touches the socket.
"""

from __future__ import annotations

import threading
from collections import Counter
from dataclasses import dataclass

from .tickets import TicketBook


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

    waiting: KeyedSlots   # per client address, and in total, until authenticated
    sessions: KeyedSlots  # per token subject
    tickets: TicketBook   # single-use stand-ins for a token in a WebSocket URL

    @classmethod
    def from_settings(cls, settings) -> Admission:
        return cls(waiting=KeyedSlots(settings.max_unauthenticated_per_address,
                                      settings.max_unauthenticated),
                   sessions=KeyedSlots(settings.max_sessions_per_user),
                   tickets=TicketBook(settings.ticket_ttl_s, settings.max_tickets_per_user))
