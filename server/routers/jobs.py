"""REST API of training jobs: ``/v1/jobs`` (docs/jobs.md).

Every route needs the ``train`` scope (``admin`` implies it). A job of another owner is
answered 404, exactly like a job that does not exist, so ids leak nothing; admins see all.
The service is the context's ``jobs`` (a :class:`JobService`, the ``Jobs`` dependency), set
up by :func:`lifespan`, which server/app.py runs inside its own.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import AsyncIterator
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Header, HTTPException, Query, Request, Response
from fastapi.responses import PlainTextResponse, StreamingResponse
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from starlette.concurrency import run_in_threadpool

from protocol.jobs import JobEnd

from ..auth import Principal
from ..context import ServerContext
from ..dependencies import Jobs, TrainPrincipal
from ..jobs.service import JobService, SubmitError
from ..jobs.store import InvalidTransition, Job, JobNotFound
from ..jobs.worker import LOG_FILE
from ..uploads import receive_form

__all__ = ["AttemptEnd", "JobList", "JobOut", "JobResult", "JobSubmit", "lifespan", "router"]

router = APIRouter(prefix="/v1/jobs", tags=["jobs"])

MAX_JSON_BODY = 1 << 20
MAX_NAME_FIELD = 1024         # bytes of the form's name field (the name is checked after)
INCOMING_DIR = "tmp"          # under the service's data_dir: uploads while they arrive
MAX_LOG_BYTES = 1 << 20
MAX_TAIL_LINES = 10_000
MAX_STREAM_S = 600.0
POLL_S = 0.25
KEEPALIVE_S = 15.0
EVENT_PAGE = 500

StateName = Literal["queued", "running", "succeeded", "failed", "cancelled"]
_NOT_FOUND = "no such job"
_ERRORS: dict[int | str, dict[str, Any]] = {
    401: {"description": "No or an unknown bearer token."},
    403: {"description": "The token lacks the 'train' scope."},
    404: {"description": "No such job, or the job belongs to another owner."},
}


class AttemptEnd(BaseModel):
    """How one run of a job ended."""

    attempt: int = Field(description="Which run (1, 2, ...).")
    reason: str = Field(description="Why it ended, e.g. 'killed by SIGKILL (likely out of "
                                    "memory)'.")
    exit_code: int | None = Field(None, description="The process's exit status (negative: "
                                                    "the signal); None when unknown.")
    resume_from: str | None = Field(None, description="The checkpoint the next run starts "
                                                      "from (None: from the start).")
    resume_iteration: int | None = Field(None, description="That checkpoint's iteration.")
    outcome: str | None = Field(None, description="'requeued' or 'failed'.")
    time: float = Field(description="Unix seconds.")


class JobOut(BaseModel):
    """A job as clients see it."""

    id: str
    owner: str
    name: str | None = Field(description="The avatar's name (None: the dataset's subject).")
    state: StateName
    kind: Literal["train", "enroll"] = Field(
        "train", description="'train' (a dataset) or 'enroll' (one video).")
    dataset: str = Field(description="'upload', 'dataset:<name>', or 'video' (enrollment).")
    created: float = Field(description="Unix seconds.")
    started: float | None
    finished: float | None
    progress: float = Field(description="iteration / total, in [0, 1] (an enrollment counts "
                                        "thousandths: total 1000).")
    iteration: int
    total: int
    loss: float | None = Field(description="The last reported training loss.")
    error: str | None = Field(description="Why the job failed or was cancelled.")
    avatar_id: str | None = Field(description="The registered avatar, once succeeded.")
    attempts: int = Field(description="Runs so far (a resume after a restart is one more).")
    max_attempts: int | None = Field(description="Runs allowed before the job fails (None: "
                                                 "the server's default).")
    attempt_log: list[AttemptEnd] = Field(description="How earlier runs ended, oldest first.")
    cancel_requested: bool
    config: dict[str, Any] = Field(description="The resolved training config (enrollment: "
                                               "preset 'enroll', the EnrollConfig fields and "
                                               "the video limits it decodes within).")

    @classmethod
    def of(cls, job: Job) -> JobOut:
        d = job.to_dict()
        d.pop("dataset_path")  # a server path
        # fields a newer server may add to a record are not an error for this one
        d["attempt_log"] = [{k: v for k, v in a.items() if k in AttemptEnd.model_fields}
                            for a in d["attempt_log"]]
        return cls(**d)


class JobList(BaseModel):
    jobs: list[JobOut]


class JobResult(BaseModel):
    job_id: str
    avatar_id: str


class JobSubmit(BaseModel):
    """A job on a dataset that is on the server (``data_dir/datasets/<name>``)."""

    model_config = ConfigDict(extra="forbid")

    dataset: str = Field(description="The dataset's name.")
    config: dict[str, Any] | str | None = Field(
        None, description="A preset name ('default', 'quick', 'test') or a TrainConfig object "
                          "(nested keys, optional 'preset'); default 'default'.")
    name: str | None = Field(None, description="The avatar's name.")


_SUBMIT_BODY = {"requestBody": {"required": True, "content": {
    "application/json": {"schema": JobSubmit.model_json_schema()},
    "multipart/form-data": {"schema": {
        "type": "object",
        "properties": {
            "archive": {"type": "string", "format": "binary",
                        "description": "A zip of one Format v1 dataset (a training job)."},
            "video": {"type": "string", "format": "binary",
                      "description": "One person turning before a fixed camera, 20-60 s "
                                     "(MP4, MOV, WebM): an enrollment job (preset 'enroll'). "
                                     "Send 'archive' or 'video', not both."},
            "config": {"type": "string", "description": "JSON: a preset name or a "
                                                        "TrainConfig object; with a video "
                                                        "'enroll' or EnrollConfig fields."},
            "name": {"type": "string", "description": "The avatar's name."}}}},
}}}


@contextlib.asynccontextmanager
async def lifespan(ctx: ServerContext) -> AsyncIterator[None]:
    """Runs inside the app's lifespan (server/app.py): the JobService on the context's
    settings and registry, as ``ctx.jobs``; queued and interrupted jobs resume at start,
    running ones are checkpointed and re-queued at stop."""
    service = JobService.from_settings(ctx.settings, ctx.registry)
    await asyncio.to_thread(service.start)
    ctx.jobs = service
    try:
        yield
    finally:
        ctx.jobs = None
        await asyncio.to_thread(service.stop)


def _visible(service: JobService, principal: Principal, job_id: str) -> Job:
    try:
        job = service.store.get(job_id)
    except JobNotFound:
        raise HTTPException(404, _NOT_FOUND) from None
    if not (principal.is_admin or job.owner == principal.subject):
        raise HTTPException(404, _NOT_FOUND)
    return job


async def _limited_body(request: Request, limit: int) -> Request:
    """The request with a receive channel that answers 413 past ``limit`` bytes (also for
    chunked bodies, which carry no Content-Length)."""
    length = request.headers.get("content-length")
    if length is not None and length.isdigit() and int(length) > limit:
        raise HTTPException(413, f"the request body is larger than {limit} bytes")
    received = 0

    async def receive() -> Any:
        nonlocal received
        message = await request.receive()
        if message["type"] == "http.request":
            received += len(message.get("body", b""))
            if received > limit:
                raise HTTPException(413, f"the request body is larger than {limit} bytes")
        return message

    return Request(request.scope, receive)


def _form_config(text: str | None) -> Any:
    """The multipart ``config`` field: JSON (an object or a preset name) or a bare name."""
    if text is None or not text.strip():
        return None
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        if text.strip().isidentifier():
            return text.strip()
        raise HTTPException(422, "config must be JSON (an object or a preset name)") from None


async def _submit_upload(request: Request, service: JobService, owner: str,
                         exempt: bool) -> Job:
    """A multipart upload: a dataset ``archive`` (a training job) or a ``video`` (an
    enrollment job), each bounded by its own limit while the bytes arrive."""
    form = await receive_form(
        request, service.data_dir / INCOMING_DIR,
        files={"archive": service.limits.max_upload_bytes,
               "video": service.video_limits.max_bytes},
        texts={"config": MAX_JSON_BODY, "name": MAX_NAME_FIELD})
    try:
        if form.overflow:
            raise HTTPException(413, f"the form field {sorted(form.overflow)[0]!r} is too long")
        config = _form_config(form.fields.get("config"))
        name = form.fields.get("name")
        if form.part == "video":
            return await run_in_threadpool(service.submit_video, owner, form.path, config,
                                           name, filename=form.filename, exempt=exempt)
        return await run_in_threadpool(service.submit_archive, owner, form.path, config, name,
                                       exempt=exempt)
    finally:
        form.path.unlink(missing_ok=True)


async def _submit_named(request: Request, service: JobService, owner: str,
                        exempt: bool) -> Job:
    limited = await _limited_body(request, MAX_JSON_BODY)
    try:
        body = JobSubmit.model_validate_json(await limited.body())
    except ValidationError as exc:
        raise HTTPException(422, json.loads(exc.json(include_url=False))) from None
    return await run_in_threadpool(service.submit_named, owner, body.dataset, body.config,
                                   body.name, exempt=exempt)


@router.post("", status_code=201, response_model=JobOut, openapi_extra=_SUBMIT_BODY,
             summary="Submit a training job",
             responses={**_ERRORS,
                        400: {"description": "Bad dataset or upload (the detail says why)."},
                        404: {"description": "No dataset of that name on the server."},
                        413: {"description": "Upload larger than the limits."},
                        415: {"description": "Neither JSON nor multipart/form-data."},
                        422: {"description": "Bad training config (the detail names the "
                                             "key)."},
                        429: {"description": "The owner's job quota is used up (the detail "
                                             "says which)."}})
async def submit_job(request: Request, response: Response, principal: TrainPrincipal,
                     service: Jobs) -> JobOut:
    """Train an avatar: on a dataset on the server (JSON ``{"dataset", "config", "name"}``)
    or on an uploaded zip (multipart: ``archive``, ``config``, ``name``), or enroll one
    uploaded video (multipart: ``video``, ``config`` 'enroll' or EnrollConfig fields,
    ``name``; probed first: a refused video is 413 / 422 with ``detail`` {reason, message,
    what_to_do}, and nothing is kept). Past the per-user
    job quotas (admins exempt): 429."""
    kind = request.headers.get("content-type", "").split(";")[0].strip().lower()
    try:
        # before reading (and unpacking) a body that would be refused anyway
        await run_in_threadpool(service.check_quota, principal.subject, principal.is_admin)
        if kind == "application/json":
            job = await _submit_named(request, service, principal.subject,
                                      principal.is_admin)
        elif kind == "multipart/form-data":
            job = await _submit_upload(request, service, principal.subject,
                                       principal.is_admin)
        else:
            raise HTTPException(415, "send application/json (a dataset on the server) or "
                                     "multipart/form-data (an 'archive' zip or a 'video')")
    except SubmitError as exc:
        raise HTTPException(exc.status, exc.detail) from None
    response.headers["Location"] = f"{router.prefix}/{job.id}"
    return JobOut.of(job)


@router.get("", response_model=JobList, summary="List jobs", responses=_ERRORS)
def list_jobs(principal: TrainPrincipal, service: Jobs,
              state: Annotated[StateName | None, Query()] = None,
              limit: Annotated[int, Query(ge=1, le=1000)] = 100) -> JobList:
    """Your jobs, newest first (admins: everyone's)."""
    owner = None if principal.is_admin else principal.subject
    jobs = service.store.list(owner=owner, state=state, limit=limit)
    return JobList(jobs=[JobOut.of(j) for j in jobs])


@router.get("/{job_id}", response_model=JobOut, summary="A job's status and progress",
            responses=_ERRORS)
def get_job(job_id: str, principal: TrainPrincipal, service: Jobs) -> JobOut:
    return JobOut.of(_visible(service, principal, job_id))


@router.post("/{job_id}/cancel", status_code=202, response_model=JobOut, summary="Cancel a job",
             responses={**_ERRORS, 409: {"description": "The job has already finished."}})
def cancel_job(job_id: str, principal: TrainPrincipal, service: Jobs) -> JobOut:
    """A queued job is cancelled at once; a running one when its process stops (within
    seconds: ``cancel_requested`` is set meanwhile)."""
    _visible(service, principal, job_id)
    try:
        return JobOut.of(service.cancel(job_id))
    except InvalidTransition as exc:
        raise HTTPException(409, str(exc)) from None


@router.post("/{job_id}/resume", status_code=202, response_model=JobOut,
             summary="Run a failed job again from its last checkpoint",
             responses={**_ERRORS,
                        409: {"description": "The job is not failed, or its dataset is gone."},
                        429: {"description": "The owner has the most active jobs allowed."}})
def resume_job(job_id: str, principal: TrainPrincipal, service: Jobs) -> JobOut:
    """A failed job goes back to the queue and goes on from its latest checkpoint (from the
    start without one), with a fresh budget of attempts."""
    _visible(service, principal, job_id)
    try:
        return JobOut.of(service.resume(job_id, exempt=principal.is_admin))
    except InvalidTransition as exc:
        raise HTTPException(409, str(exc)) from None
    except SubmitError as exc:
        raise HTTPException(exc.status, str(exc)) from None


@router.delete("/{job_id}", status_code=204, summary="Delete a finished job",
               responses={**_ERRORS, 409: {"description": "The job is queued or running."}})
def delete_job(job_id: str, principal: TrainPrincipal, service: Jobs) -> Response:
    """Forgets the job, its events, log and files; its avatar, if any, stays registered."""
    _visible(service, principal, job_id)
    try:
        service.delete(job_id)
    except InvalidTransition as exc:
        raise HTTPException(409, str(exc)) from None
    except JobNotFound:
        raise HTTPException(404, _NOT_FOUND) from None
    return Response(status_code=204)


@router.get("/{job_id}/result", response_model=JobResult, summary="The trained avatar",
            responses={**_ERRORS, 409: {"description": "The job has not succeeded (yet)."}})
def job_result(job_id: str, principal: TrainPrincipal, service: Jobs) -> JobResult:
    job = _visible(service, principal, job_id)
    if job.state != "succeeded" or job.avatar_id is None:
        why = f": {job.error}" if job.error else ""
        raise HTTPException(409, f"job {job.id} is {job.state}{why}; no avatar")
    return JobResult(job_id=job.id, avatar_id=job.avatar_id)


@router.get("/{job_id}/logs", response_class=PlainTextResponse, summary="The training log",
            responses={**_ERRORS, 200: {"content": {"text/plain": {}}}})
def job_logs(job_id: str, principal: TrainPrincipal, service: Jobs,
             tail: Annotated[int | None, Query(ge=1, le=MAX_TAIL_LINES)] = None
             ) -> PlainTextResponse:
    """The log (at most its last 1 MiB); ``tail``: only the last N lines."""
    _visible(service, principal, job_id)
    path = service.worker.job_dir(job_id) / LOG_FILE
    text = ""
    if path.is_file():
        with open(path, "rb") as f:
            size = f.seek(0, 2)
            f.seek(max(0, size - MAX_LOG_BYTES))
            data = f.read(MAX_LOG_BYTES)
        text = data.decode("utf-8", errors="replace")
        if size > MAX_LOG_BYTES:  # drop the cut first line
            text = text.partition("\n")[2]
    if tail is not None:
        lines = text.splitlines()[-tail:]
        text = "\n".join(lines) + ("\n" if lines else "")
    return PlainTextResponse(text)


def _sse(event_id: int | None, kind: str, data: dict[str, Any]) -> str:
    head = f"id: {event_id}\n" if event_id is not None else ""
    return f"{head}event: {kind}\ndata: {json.dumps(data, separators=(',', ':'))}\n\n"


@router.get("/{job_id}/events", summary="Job events (Server-Sent Events)",
            response_class=StreamingResponse,
            responses={**_ERRORS, 200: {"content": {"text/event-stream": {}},
                                        "description": "id: seq, event: type, data: JSON; "
                                                       "a last 'end' event when the job ends."}})
def job_events(job_id: str, request: Request, principal: TrainPrincipal, service: Jobs,
               after: Annotated[int, Query(ge=0)] = 0,
               timeout: Annotated[float, Query(gt=0, le=MAX_STREAM_S)] = MAX_STREAM_S,
               last_event_id: Annotated[str | None, Header()] = None) -> StreamingResponse:
    """Replays the events after ``after`` / ``Last-Event-ID`` (the larger), then streams new
    ones; ends with an ``end`` event once the job has finished, or after ``timeout`` s
    (reconnect with Last-Event-ID)."""
    _visible(service, principal, job_id)
    start = after
    if last_event_id is not None and last_event_id.strip().isdigit():
        start = max(start, int(last_event_id.strip()))
    store = service.store

    async def stream() -> Any:
        loop = asyncio.get_running_loop()
        seq, deadline = start, loop.time() + timeout
        quiet_since = loop.time()
        while True:
            events = await run_in_threadpool(store.events, job_id, seq, EVENT_PAGE)
            for ev in events:
                yield _sse(ev.seq, ev.type, ev.data)
                seq = ev.seq
            now = loop.time()
            if events:
                quiet_since = now
                if len(events) == EVENT_PAGE:
                    continue
            else:
                try:
                    job = await run_in_threadpool(store.get, job_id)
                except JobNotFound:  # deleted meanwhile
                    return
                # its last state event is written with the state: only a resume follows it
                if job.done and not await run_in_threadpool(store.events, job_id, seq, 1):
                    yield _sse(None, "end", JobEnd(state=job.state, avatar_id=job.avatar_id,
                                                   error=job.error).model_dump())
                    return
            if now >= deadline or await request.is_disconnected():
                return
            if now - quiet_since >= KEEPALIVE_S:
                quiet_since = now
                yield ": keepalive\n\n"
            await asyncio.sleep(POLL_S)

    return StreamingResponse(stream(), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})
