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
import re
import secrets
import stat
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

    def revoke_subject(self, subject: str, keep: str | None = None) -> int:
        """Remove every token of ``subject`` but ``keep`` (a plain token); how many went."""
        kept = _digest(keep) if keep else None
        with self._update():
            gone = [k for k, e in self._entries.items()
                    if e["subject"] == subject and k != kept]
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


# -- the local admin token (auth = "local") ------------------------------------------------
#
# Its plain text lives in data_dir/local_token (0600, in the 0700 data_dir), written once and
# read at every start, so the links printed with it survive restarts; the token store keeps
# its hash as for any token. `telesplat serve --rotate-local-token` replaces it.

LOCAL_TOKEN_MAX_BYTES = 256  # what is read of the file at most (a token is 47 characters)
_LOCAL_TOKEN = re.compile(re.escape(TOKEN_PREFIX) + r"[A-Za-z0-9_-]{32,128}")
ROTATE_HINT = "telesplat serve --rotate-local-token writes a new one"


@contextlib.contextmanager
def _local_token_lock(path: Path) -> Iterator[None]:
    """One process at a time reads or replaces the local token (two servers starting on one
    data dir, or a rotation during a start, agree on one token)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    lock_path = path.with_name(path.name + ".lock")
    fd = os.open(lock_path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o600)
    with os.fdopen(fd, "r+") as lock_file:
        os.fchmod(fd, 0o600)
        fcntl.flock(lock_file, fcntl.LOCK_EX)
        yield


def read_local_token(path: str | Path) -> str | None:
    """The local token kept in ``path`` (None when there is no file). A file that is a link,
    not a regular file, too large or not a token is a ValueError naming the file; one that
    others may read is made 0600 with a warning (it may have been read: rotate it)."""
    path = Path(path)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except FileNotFoundError:
        return None
    except OSError as exc:  # ELOOP: a symbolic link
        raise ValueError(f"{path}: cannot read the local token ({exc.strerror}); "
                         f"{ROTATE_HINT}") from None
    info = os.fstat(fd)
    if not stat.S_ISREG(info.st_mode):
        os.close(fd)
        raise ValueError(f"{path} is not a regular file; {ROTATE_HINT}")
    with os.fdopen(fd, "rb") as file:
        mode = stat.S_IMODE(info.st_mode)
        if mode & 0o077:
            os.fchmod(fd, 0o600)
            log.warning("%s was open to other users (mode %o), now 0600; if someone else may "
                        "have read it, rotate it (telesplat serve --rotate-local-token)",
                        path, mode)
        data = file.read(LOCAL_TOKEN_MAX_BYTES + 1)
    token = data.decode("ascii", errors="replace").strip()
    if len(data) > LOCAL_TOKEN_MAX_BYTES or not _LOCAL_TOKEN.fullmatch(token):
        raise ValueError(f"{path} does not hold a Telesplat token ({TOKEN_PREFIX}... on one "
                         f"line); {ROTATE_HINT}")
    return token


def _write_local_token(path: Path, token: str) -> None:
    """``token`` into ``path``, 0600 from its creation, replacing the old file atomically."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.unlink(missing_ok=True)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
    with os.fdopen(fd, "w") as file:
        file.write(token + "\n")
        file.flush()
        os.fsync(fd)
    tmp.replace(path)


def _new_local_token(tokens: TokenStore, path: Path) -> str:
    tokens.revoke_subject(LOCAL_SUBJECT)
    token = tokens.issue(LOCAL_SUBJECT, SCOPES)
    _write_local_token(path, token)
    return token


def local_admin_token(tokens: TokenStore, path: str | Path) -> str:
    """The local admin token (subject ``local``, every scope): the one kept in ``path`` while
    the token store still knows it, else a new one (written there). Any other token of subject
    ``local`` is revoked: one live local token."""
    path = Path(path)
    with _local_token_lock(path):
        token = read_local_token(path)
        if token is not None:
            principal = tokens.principal(token)
            if principal is not None and principal.subject == LOCAL_SUBJECT \
                    and principal.is_admin:
                tokens.revoke_subject(LOCAL_SUBJECT, keep=token)
                return token
            log.warning("the local token in %s is not in the token store %s (revoked, or "
                        "another store): a new one replaces it", path, tokens.path)
        return _new_local_token(tokens, path)


def rotate_local_token(tokens: TokenStore, path: str | Path) -> str:
    """Revoke every token of subject ``local``, write a new local admin token to ``path``
    and return it (a running server picks the change up within tokens_reload_interval_s).
    Works whatever ``path`` held, so it also mends a damaged file."""
    path = Path(path)
    with _local_token_lock(path):
        return _new_local_token(tokens, path)


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
