"""Training jobs: the store, the worker, the service (docs/jobs.md); the REST routes are
server/routers/jobs.py.

``JobService`` (store + worker, ``start()`` / ``stop()`` in the app's lifespan) loads lazily,
so the training process (``python -m server.jobs.run``) does not import FastAPI.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .service import JobService

__all__ = ["JobService"]


def __getattr__(name: str) -> Any:
    if name == "JobService":
        from .service import JobService

        return JobService
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
