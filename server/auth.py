"""Bearer tokens with scopes: a JSON token store (sha256 hashes only) and FastAPI dependencies.

Scopes: ``stream`` (open sessions), ``train`` (submit jobs), ``admin`` (implies all, sees every
avatar). HTTP routes use ``require_scope(scope)``; WebSockets use ``token_from_websocket`` and
``TokenStore.principal``, since a token may also come in the first ``hello`` message.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import os
import secrets
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fastapi import HTTPException, Request, WebSocket, params

SCOPES = ("stream", "train", "admin")
PUBLIC_OWNER = "public"  # avatars any stream-scoped token may see and stream
LOCAL_SUBJECT = "local"
TOKEN_PREFIX = "tsk_"


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
    the file atomically.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._lock = threading.Lock()
        self._entries: dict[str, dict[str, Any]] = {}
        self._load()

    def _load(self) -> None:
        if not self.path.is_file():
            return
        data = json.loads(self.path.read_text())
        for entry in data.get("tokens", []):
            self._entries[entry["sha256"]] = entry

    def _save(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text(json.dumps({"tokens": list(self._entries.values())}, indent=2))
        os.chmod(tmp, 0o600)
        tmp.replace(self.path)

    def issue(self, subject: str, scopes: Iterable[str]) -> str:
        """A new token for ``subject`` with ``scopes``; the plain token is returned once."""
        scopes = sorted(set(scopes))
        bad = [s for s in scopes if s not in SCOPES]
        if bad or not scopes:
            raise ValueError(f"scopes must be a non-empty subset of {SCOPES}, got {scopes}")
        if not subject or subject == PUBLIC_OWNER:
            raise ValueError(f"subject must be non-empty and not {PUBLIC_OWNER!r}")
        token = TOKEN_PREFIX + secrets.token_urlsafe(32)
        with self._lock:
            self._entries[_digest(token)] = {"sha256": _digest(token), "subject": subject,
                                             "scopes": scopes, "created": time.time()}
            self._save()
        return token

    def revoke_subject(self, subject: str) -> int:
        """Remove every token of ``subject``; how many there were."""
        with self._lock:
            gone = [k for k, e in self._entries.items() if e["subject"] == subject]
            for key in gone:
                del self._entries[key]
            if gone:
                self._save()
        return len(gone)

    def revoke(self, token: str) -> bool:
        with self._lock:
            found = self._entries.pop(_digest(token), None) is not None
            if found:
                self._save()
        return found

    def principal(self, token: str | None) -> Principal | None:
        """The principal of a token, or None when it is missing or unknown."""
        if not token:
            return None
        digest = _digest(token)
        with self._lock:
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


def _store(request: Request) -> TokenStore:
    return request.app.state.tokens


def authenticate(request: Request, scope: str | None = None) -> Principal:
    """The request's principal; HTTP 401 without a valid token, 403 without ``scope``."""
    principal = _store(request).principal(bearer_token(request.headers.get("authorization")))
    if principal is None:
        raise HTTPException(401, "missing or invalid bearer token",
                            headers={"WWW-Authenticate": "Bearer"})
    if scope is not None and not principal.has(scope):
        raise HTTPException(403, f"this token lacks the {scope!r} scope")
    return principal


@dataclass(frozen=True)
class _ScopeDependency(params.Depends):
    """``Depends`` on a scope check that also works wrapped in another ``Depends(...)``."""

    required: str = "stream"

    def __call__(self, request: Request) -> Principal:
        return authenticate(request, self.required)


def require_scope(scope: str) -> params.Depends:
    """A FastAPI dependency giving the caller's :class:`Principal` (401 / 403 otherwise).

    Use ``principal: Principal = require_scope("train")`` (or wrapped in ``Depends(...)``,
    which also works).
    """
    if scope not in SCOPES:
        raise ValueError(f"unknown scope {scope!r}; expected one of {SCOPES}")

    def check(request: Request) -> Principal:
        return authenticate(request, scope)

    return _ScopeDependency(dependency=check, required=scope)


def optional_principal(request: Request) -> Principal | None:
    """The caller's principal if a valid token came, else None (never raises)."""
    return _store(request).principal(bearer_token(request.headers.get("authorization")))
