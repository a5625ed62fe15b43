"""Training jobs: the store, the worker, the REST routes (docs/jobs.md).

``router`` (the ``/v1/jobs`` APIRouter) and ``JobService`` (store + worker, ``start()`` /
``stop()`` in the app's lifespan) load lazily, so the training process
(``python -m server.jobs.run``) does not import FastAPI.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .routes import router
    from .service import JobService

__all__ = ["JobService", "router"]


def __getattr__(name: str) -> Any:
    if name == "router":
        from .routes import router

        return router
    if name == "JobService":
        from .service import JobService

        return JobService
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
