"""Bearer tokens with scopes: a JSON token store (sha256 hashes only), principals, parsing.

Scopes: ``stream`` (open sessions), ``train`` (submit jobs), ``admin`` (implies all, sees every
avatar). HTTP routes depend on ``require_scope(scope)`` (server/dependencies.py); WebSockets
use ``token_from_websocket`` and ``TokenStore.principal``, since a token may also come in the
first ``hello`` message.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import hmac
import json
import logging
import os
import secrets
import threading
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fastapi import WebSocket

log = logging.getLogger(__name__)

SCOPES = ("stream", "train", "admin")
PUBLIC_OWNER = "public"  # avatars any stream-scoped token may see and stream
LOCAL_SUBJECT = "local"
TOKEN_PREFIX = "tsk_"
INVITATION_PREFIX = "tsr_"  # a room's invitation (server/rooms/registry.py)


@dataclass(frozen=True)
class Principal:
    """Who a token belongs to and what it may do."""

    subject: str
    scopes: frozenset[str]

    @property
    def is_admin(self) -> bool:
        return "admin" in self.scopes

    def has(self, scope: str) -> bool:
        return self.is_admin or scope in self.scopes

    def can_see(self, owner: str) -> bool:
        """Whether an avatar of ``owner`` is visible (and streamable) to this principal."""
        return self.is_admin or owner in (self.subject, PUBLIC_OWNER)

    def can_modify(self, owner: str) -> bool:
        return self.is_admin or owner == self.subject


def _digest(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


class TokenStore:
    """Tokens in a JSON file: ``{"tokens": [{"sha256", "subject", "scopes", "created"}]}``.

    Only hashes are stored, so the file leaks nothing usable. Thread-safe; every write replaces
    the file atomically, under an advisory lock so that a server and ``telesplat serve
    --issue-token`` writing at once lose nothing. Another process's changes are picked up
    without a restart: at most every ``reload_interval_s`` the file's stat is compared with
    the one last read, and a changed file is read again (a broken one keeps the old tokens).
    """

    def __init__(self, path: str | Path, reload_interval_s: float = 1.0) -> None:
        self.path = Path(path)
        self.reload_interval_s = reload_interval_s
        self._lock = threading.Lock()
        self._entries: dict[str, dict[str, Any]] = {}
        self._stat: tuple[int, int, int] | None = None  # (inode, size, mtime_ns) last read
        self._checked = 0.0
        with self._lock:
            self._load(strict=True)

    def _file_stat(self) -> tuple[int, int, int] | None:
        try:
            st = self.path.stat()
        except FileNotFoundError:
            return None
        return st.st_ino, st.st_size, st.st_mtime_ns

    def _load(self, strict: bool = False) -> None:
        """Read the file into ``_entries`` (lock held). A malformed file raises at start-up
        (``strict``) and is logged and skipped on a reload."""
        stat = self._file_stat()
        self._checked = time.monotonic()
        if stat is None:
            self._entries, self._stat = {}, None
            return
        try:
            data = json.loads(self.path.read_text())
            entries = {entry["sha256"]: entry for entry in data.get("tokens", [])}
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
            if strict:
                raise ValueError(f"{self.path}: not a token file: {exc}") from exc
            log.warning("token file %s unreadable (%s): keeping the tokens loaded before",
                        self.path, exc)
            self._stat = stat  # do not retry until it changes again
            return
        self._entries, self._stat = entries, stat

    def _refresh(self) -> None:
        """Reload if the file changed since it was read (lock held; cheap: one stat)."""
        if time.monotonic() - self._checked < self.reload_interval_s:
            return
        self._checked = time.monotonic()
        if self._file_stat() != self._stat:
            self._load()

    @contextlib.contextmanager
    def _update(self) -> Iterator[None]:
        """Read-modify-write: the newest file in, the changed entries out, all under both
        the thread lock and the file lock."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        lock_path = self.path.with_name(self.path.name + ".lock")
        with self._lock, open(lock_path, "a") as lock_file:
            os.chmod(lock_path, 0o600)
            fcntl.flock(lock_file, fcntl.LOCK_EX)
            self._load(strict=True)
            yield
            self._save()

    def _save(self) -> None:
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text(json.dumps({"tokens": list(self._entries.values())}, indent=2))
        os.chmod(tmp, 0o600)
        tmp.replace(self.path)
        self._stat = self._file_stat()

    def issue(self, subject: str, scopes: Iterable[str]) -> str:
        """A new token for ``subject`` with ``scopes``; the plain token is returned once."""
        scopes = sorted(set(scopes))
        bad = [s for s in scopes if s not in SCOPES]
        if bad or not scopes:
            raise ValueError(f"scopes must be a non-empty subset of {SCOPES}, got {scopes}")
        if not subject or subject == PUBLIC_OWNER:
            raise ValueError(f"subject must be non-empty and not {PUBLIC_OWNER!r}")
        token = TOKEN_PREFIX + secrets.token_urlsafe(32)
        with self._update():
            self._entries[_digest(token)] = {"sha256": _digest(token), "subject": subject,
                                             "scopes": scopes, "created": time.time()}
        return token

    def revoke_subject(self, subject: str) -> int:
        """Remove every token of ``subject``; how many there were."""
        with self._update():
            gone = [k for k, e in self._entries.items() if e["subject"] == subject]
            for key in gone:
                del self._entries[key]
        return len(gone)

    def revoke(self, token: str) -> bool:
        with self._update():
            found = self._entries.pop(_digest(token), None) is not None
        return found

    def principal(self, token: str | None) -> Principal | None:
        """The principal of a token, or None when it is missing or unknown."""
        if not token:
            return None
        digest = _digest(token)
        with self._lock:
            self._refresh()
            for key, entry in self._entries.items():
                if hmac.compare_digest(key, digest):  # constant time per comparison
                    return Principal(entry["subject"], frozenset(entry["scopes"]))
        return None


def bearer_token(authorization: str | None) -> str | None:
    if not authorization:
        return None
    kind, _, value = authorization.partition(" ")
    return value.strip() or None if kind.lower() == "bearer" else None


def token_from_websocket(ws: WebSocket) -> str | None:
    """A WebSocket's token from ``?token=`` or ``Authorization: Bearer`` (None: wait for hello)."""
    return ws.query_params.get("token") or bearer_token(ws.headers.get("authorization"))


def is_invitation(token: str | None) -> bool:
    """A room invitation's token (resolved by the room registry), not a bearer token."""
    return bool(token) and token.startswith(INVITATION_PREFIX)
