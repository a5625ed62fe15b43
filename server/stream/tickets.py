"""Stream tickets: single-use, short-lived stand-ins for a token in a WebSocket URL.

For a client that can send neither an ``Authorization`` header nor a ``hello`` with the token:
``POST /v1/stream/tickets`` (with the token in the header) gives a ticket that opens one
``/v1/stream?ticket=...`` within ``ttl_s``. A ticket in a log line or a history is spent or
expired; the log redacts it anyway. Only hashes are kept, in memory.
"""

from __future__ import annotations

import hashlib
import secrets
import threading
import time
from collections import Counter

from ..auth import Principal

TICKET_PREFIX = "tkt_"


def _digest(ticket: str) -> str:
    return hashlib.sha256(ticket.encode()).hexdigest()


class TicketsExhausted(Exception):
    """The subject holds as many unspent tickets as it may."""


class TicketBook:
    def __init__(self, ttl_s: float, max_per_subject: int) -> None:
        self.ttl_s = ttl_s
        self.max_per_subject = max_per_subject
        self._tickets: dict[str, tuple[Principal, float]] = {}  # digest -> (who, expires at)
        self._lock = threading.Lock()

    def _prune(self, now: float) -> None:
        for key in [k for k, (_, expires) in self._tickets.items() if expires <= now]:
            del self._tickets[key]

    def issue(self, principal: Principal) -> str:
        """A new ticket for ``principal`` (TicketsExhausted past the per-subject cap)."""
        now = time.monotonic()
        with self._lock:
            self._prune(now)
            held = Counter(p.subject for p, _ in self._tickets.values())
            if held[principal.subject] >= self.max_per_subject:
                raise TicketsExhausted(f"{principal.subject!r} holds {self.max_per_subject} "
                                       "unspent tickets already")
            ticket = TICKET_PREFIX + secrets.token_urlsafe(24)
            self._tickets[_digest(ticket)] = (principal, now + self.ttl_s)
        return ticket

    def valid(self, ticket: str) -> bool:
        """Whether the ticket is unspent and unexpired (looked at, not spent)."""
        with self._lock:
            entry = self._tickets.get(_digest(ticket))
        return entry is not None and entry[1] > time.monotonic()

    def redeem(self, ticket: str) -> Principal | None:
        """The ticket's principal, once; None when unknown, spent or expired."""
        with self._lock:
            entry = self._tickets.pop(_digest(ticket), None)
        if entry is None or entry[1] <= time.monotonic():
            return None
        return entry[0]

    def __len__(self) -> int:
        with self._lock:
            return len(self._tickets)
