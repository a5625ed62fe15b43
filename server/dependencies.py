"""The dependencies routes declare (FastAPI ``Depends``, typed with ``Annotated``): the server
context, the caller's principal with a scope, and the job service.

``app.state.ctx`` (a :class:`ServerContext`) is the one thing the app carries; everything a
route needs is reached through it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, HTTPException, Request, params
from starlette.requests import HTTPConnection

from .auth import SCOPES, Principal, bearer_token
from .context import ServerContext
from .jobs.service import JobService


def get_context(conn: HTTPConnection) -> ServerContext:
    """The app's context, for HTTP requests and WebSockets alike."""
    return conn.app.state.ctx


Context = Annotated[ServerContext, Depends(get_context)]


def authenticate(request: Request, scope: str | None = None) -> Principal:
    """The request's principal; HTTP 401 without a valid token, 403 without ``scope``."""
    tokens = get_context(request).tokens
    principal = tokens.principal(bearer_token(request.headers.get("authorization")))
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

    Use ``principal: Annotated[Principal, require_scope("train")]`` (as the aliases below do).
    """
    if scope not in SCOPES:
        raise ValueError(f"unknown scope {scope!r}; expected one of {SCOPES}")

    def check(request: Request) -> Principal:
        return authenticate(request, scope)

    return _ScopeDependency(dependency=check, required=scope)


StreamPrincipal = Annotated[Principal, require_scope("stream")]  # reading, streaming
TrainPrincipal = Annotated[Principal, require_scope("train")]    # creating, deleting, jobs


def get_job_service(ctx: Context) -> JobService:
    """The running job service; 503 outside the app's lifespan."""
    if ctx.jobs is None:
        raise HTTPException(503, "the job service is not running")
    return ctx.jobs


Jobs = Annotated[JobService, Depends(get_job_service)]
