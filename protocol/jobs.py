"""Training-job events, defined once: the job store writes them, ``GET /v1/jobs/{id}/events``
streams them (SSE: ``id`` the seq, ``event`` the ``type``, ``data`` the JSON object), and
``telesplat-client jobs submit --watch`` / ``jobs watch`` read them.

Every event has a ``type`` (:data:`JOB_EVENT_TYPES`). Trainer events (``progress``,
``densify``, ``checkpoint``, ``done``, ``resumed``) are :class:`JobProgress`: ``iteration`` of
``total`` iterations, and ``progress``, their ratio in 0..1, set by the server
(:func:`progress_event`) so that a reader never computes it from field names of its own.
``state`` events carry the job's new ``state`` (and ``error`` / ``avatar_id`` when set); the
stream ends with an ``end`` event (``state``, ``avatar_id``, ``error``) once the job has ended.
Unknown fields are kept (the trainer adds some per type), so the schema only names the
fields that readers rely on.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

__all__ = ["JOB_EVENT_TYPES", "JOB_STATES", "MIN_USABLE_ITERATIONS", "PRESET_NAMES",
           "PROGRESS_TYPES",
           "TERMINAL_JOB_STATES", "small_job_warning",
           "JobEnd", "JobProgress", "progress_event", "progress_of"]

# The training presets' names (avatar_core.train.config.PRESETS, which a test holds them to),
# here for the clients, which do not import the engine's trainer.
PRESET_NAMES = ("default", "quick", "demo", "test", "enroll")
PROGRESS_TYPES = ("progress", "densify", "checkpoint", "done", "resumed")
JOB_EVENT_TYPES = (*PROGRESS_TYPES, "state", "cancel_requested", "message", "error", "end")
JOB_STATES = ("queued", "running", "succeeded", "failed", "cancelled")
TERMINAL_JOB_STATES = ("succeeded", "failed", "cancelled")


class JobProgress(BaseModel):
    """A trainer event: where training is. ``progress`` = ``iteration / total`` (0..1)."""

    model_config = ConfigDict(extra="allow")

    type: Literal["progress", "densify", "checkpoint", "done", "resumed"]
    iteration: int = Field(ge=0)
    total: int = Field(ge=1)
    progress: float = Field(default=0.0, ge=0.0, le=1.0)
    loss: float | None = None
    psnr: float | None = None
    num_gaussians: int | None = None

    @model_validator(mode="before")
    @classmethod
    def _ratio(cls, data: Any) -> Any:
        if isinstance(data, dict) and isinstance(data.get("iteration"), int) \
                and isinstance(data.get("total"), int) and data["total"] >= 1:
            data = {**data, "progress": min(1.0, max(0.0, data["iteration"] / data["total"]))}
        return data


class JobEnd(BaseModel):
    """The stream's last event: the job has ended."""

    model_config = ConfigDict(extra="allow")

    state: Literal["queued", "running", "succeeded", "failed", "cancelled"]
    avatar_id: str | None = None
    error: str | None = None


def progress_event(event: dict[str, Any]) -> dict[str, Any]:
    """``event`` as it is stored and streamed: a trainer event is checked against
    :class:`JobProgress` and gets its ``progress``; other events pass unchanged. ValueError
    for a trainer event that breaks the schema."""
    if event.get("type") not in PROGRESS_TYPES:
        return event
    try:
        return JobProgress.model_validate(event).model_dump()
    except ValidationError as exc:
        raise ValueError(f"job event {event.get('type')!r} breaks the schema: {exc}") from None


def progress_of(event_type: str, data: Any) -> float | None:
    """The 0..1 progress an event reports, None if it reports none. A ``state`` / ``end``
    event of a succeeded job is 1.0 (all iterations done)."""
    if not isinstance(data, dict):
        return None
    if event_type in PROGRESS_TYPES:
        try:
            return JobProgress.model_validate({"type": event_type, **data}).progress
        except ValidationError:
            return None
    if event_type in ("state", "end") and data.get("state") == "succeeded":
        return 1.0
    return None


# The smallest schedule that gives a usable avatar: the ``demo`` preset's 2,000 iterations
# (33.6 dB novel-view PSNR on the synthetic capture, docs/results.md). Fewer (the ``test``
# preset's 300, a config's ``iterations``) leaves a smeared face: the CLIs warn.
MIN_USABLE_ITERATIONS = 2_000


def small_job_warning(iterations: int) -> str | None:
    """A warning for a training run too short to give a usable avatar, else None."""
    if iterations >= MIN_USABLE_ITERATIONS:
        return None
    return (f"warning: {iterations} iterations is too few for a usable avatar (a smeared "
            f"face); the demo preset's {MIN_USABLE_ITERATIONS} are the least that give one. "
            "Presets below that ('test') are for tests and smoke runs.")
