"""The job store: jobs, their states and their events.

:class:`JobStore` is the interface the worker and the routes use; :class:`SQLiteJobStore` is
the embedded default (stdlib sqlite3, WAL, one connection per thread). The training process
opens the same database file, so a store must be safe across processes: every write is one
``BEGIN IMMEDIATE`` transaction, and each state change appends its ``state`` event in the same
transaction, so the event order is the order things happened. Another backend (a Ray
cluster's, say) implements the same interface.

Each run of a job is an attempt; how an attempt ended (exit code or signal, the checkpoint
the next attempt resumes from) is appended to the job's ``attempt_log``. Databases written
before a column existed are migrated on open (``ALTER TABLE ... ADD COLUMN``).
"""

from __future__ import annotations

import json
import secrets
import sqlite3
import time
from abc import ABC, abstractmethod
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from protocol.jobs import PROGRESS_TYPES, progress_event

from ..sqlite import SQLiteFile

__all__ = ["ACTIVE", "MAX_ATTEMPT_LOG", "RESUMABLE", "STATES", "TERMINAL", "Event",
           "InvalidTransition", "Job", "JobNotFound", "JobStore", "NewJob", "QuotaExceeded",
           "SQLiteJobStore", "check_quota"]

STATES = ("queued", "running", "succeeded", "failed", "cancelled")
ACTIVE = ("queued", "running")
TERMINAL = ("succeeded", "failed", "cancelled")
# Only failed jobs resume on request: a cancelled one was stopped on purpose and its
# checkpoints and upload are deleted.
RESUMABLE = ("failed",)
MAX_ATTEMPT_LOG = 50  # attempt records kept per job (the newest): resumes can add many
# Allowed transitions; running -> queued is the requeue of an interrupted run.
_NEXT = {"queued": {"running", "cancelled", "failed"},
         "running": {"succeeded", "failed", "cancelled", "queued"}}


class JobNotFound(KeyError):
    pass


class InvalidTransition(ValueError):
    pass


class QuotaExceeded(ValueError):
    """A submission past the owner's job quota (the message says which)."""


@dataclass(frozen=True)
class NewJob:
    """What a submission gives the store."""

    owner: str
    dataset: str          # shown to users: "upload" or "dataset:<name>"
    dataset_path: str     # where the worker reads it
    config: dict[str, Any]  # the resolved TrainConfig as plain JSON types
    total: int            # config["iterations"]
    name: str | None = None
    id: str | None = None  # None: a fresh random id
    max_attempts: int | None = None  # None: the worker's default
    kind: str = "train"   # "train" (a dataset) or "enroll" (one video: server/jobs/enrollment.py)


@dataclass(frozen=True)
class Job:
    id: str
    owner: str
    name: str | None
    state: str
    dataset: str
    dataset_path: str
    config: dict[str, Any]
    created: float
    started: float | None
    finished: float | None
    iteration: int
    total: int
    loss: float | None
    error: str | None
    avatar_id: str | None
    attempts: int
    cancel_requested: bool
    max_attempts: int | None = None  # runs allowed; None: the worker's default
    attempt_log: tuple[dict[str, Any], ...] = ()  # how earlier attempts ended, oldest first
    kind: str = "train"   # "train" or "enroll"

    @property
    def progress(self) -> float:
        return min(1.0, self.iteration / self.total) if self.total > 0 else 0.0

    @property
    def done(self) -> bool:
        return self.state in TERMINAL

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "attempt_log": [dict(a) for a in self.attempt_log],
                "progress": self.progress}


@dataclass(frozen=True)
class Event:
    job_id: str
    seq: int      # 1, 2, ... per job
    time: float
    data: dict[str, Any]  # always has "type"

    @property
    def type(self) -> str:
        return str(self.data.get("type", "message"))


def new_job_id() -> str:
    return secrets.token_hex(8)


class JobStore(ABC):
    """Where jobs and their events live. Raises JobNotFound for an unknown id and
    InvalidTransition for a state change the lifecycle does not allow."""

    @abstractmethod
    def create(self, new: NewJob, *, max_active: int | None = None,
               max_stored: int | None = None) -> Job:
        """A queued job; QuotaExceeded (nothing created) when the owner already has
        ``max_active`` queued or running jobs, or ``max_stored`` jobs in all (None: no cap).
        The count and the insert are one transaction."""

    @abstractmethod
    def count(self, owner: str) -> dict[str, int]:
        """The owner's jobs per state (states without jobs absent)."""

    @abstractmethod
    def get(self, job_id: str) -> Job: ...

    @abstractmethod
    def list(self, owner: str | None = None, state: str | None = None,
             limit: int = 100) -> list[Job]:
        """Newest first; ``owner`` None: every owner."""

    @abstractmethod
    def claim_next(self) -> Job | None:
        """The oldest queued job, now running (attempts + 1); None when none is queued."""

    @abstractmethod
    def transition(self, job_id: str, state: str, *, error: str | None = None,
                   avatar_id: str | None = None, note: dict[str, Any] | None = None,
                   attempt_end: dict[str, Any] | None = None,
                   iteration: int | None = None) -> Job:
        """Change the state (with a ``state`` event carrying ``note``). ``attempt_end``: how
        the run ended, appended to ``attempt_log`` and put in the event; ``iteration``: the
        job's iteration from now on (where a re-queued job resumes). Back to ``queued``
        clears ``error`` and ``finished``."""

    @abstractmethod
    def resume(self, job_id: str, max_attempts: int,
               note: dict[str, Any] | None = None) -> Job:
        """A failed job back to ``queued`` with ``max_attempts`` runs allowed in all;
        InvalidTransition when it is not in RESUMABLE."""

    @abstractmethod
    def delete(self, job_id: str) -> None:
        """Forget a finished job and its events; InvalidTransition while it is active."""

    @abstractmethod
    def request_cancel(self, job_id: str) -> Job:
        """Queued: cancelled at once. Running: flagged for the worker. Finished:
        InvalidTransition."""

    @abstractmethod
    def report(self, job_id: str, event: dict[str, Any]) -> int:
        """Append a trainer event (its ``iteration`` / ``loss`` update the job); its seq."""

    @abstractmethod
    def set_error(self, job_id: str, error: str) -> None:
        """Record why a run is failing (the worker finishes the job)."""

    @abstractmethod
    def events(self, job_id: str, after: int = 0, limit: int = 1000) -> list[Event]: ...

    def close(self) -> None:  # noqa: B027 - optional for backends without resources
        pass


_SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
    id TEXT PRIMARY KEY,
    owner TEXT NOT NULL,
    name TEXT,
    state TEXT NOT NULL CHECK (state IN ('queued','running','succeeded','failed','cancelled')),
    dataset TEXT NOT NULL,
    dataset_path TEXT NOT NULL,
    config TEXT NOT NULL,
    created REAL NOT NULL,
    started REAL,
    finished REAL,
    iteration INTEGER NOT NULL DEFAULT 0,
    total INTEGER NOT NULL,
    loss REAL,
    error TEXT,
    avatar_id TEXT,
    attempts INTEGER NOT NULL DEFAULT 0,
    cancel_requested INTEGER NOT NULL DEFAULT 0,
    max_attempts INTEGER,
    attempt_log TEXT NOT NULL DEFAULT '[]',
    kind TEXT NOT NULL DEFAULT 'train'
);
CREATE INDEX IF NOT EXISTS jobs_state ON jobs (state, created);
CREATE INDEX IF NOT EXISTS jobs_owner ON jobs (owner, created);
CREATE TABLE IF NOT EXISTS events (
    job_id TEXT NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
    seq INTEGER NOT NULL,
    time REAL NOT NULL,
    data TEXT NOT NULL,
    PRIMARY KEY (job_id, seq)
);
"""
# Columns added after the first release: (name, declaration), added to older databases.
_ADDED_COLUMNS = (("max_attempts", "INTEGER"), ("attempt_log", "TEXT NOT NULL DEFAULT '[]'"),
                  ("kind", "TEXT NOT NULL DEFAULT 'train'"))
_COLUMNS = ("id, owner, name, state, dataset, dataset_path, config, created, started, "
            "finished, iteration, total, loss, error, avatar_id, attempts, cancel_requested, "
            "max_attempts, attempt_log, kind")


def _job(row: sqlite3.Row) -> Job:
    values = dict(row)
    values["config"] = json.loads(values["config"])
    values["cancel_requested"] = bool(values["cancel_requested"])
    values["attempt_log"] = tuple(json.loads(values["attempt_log"] or "[]"))
    return Job(**values)


def _finite(x: Any) -> float | None:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if v == v and abs(v) != float("inf") else None


class SQLiteJobStore(SQLiteFile, JobStore):
    """Jobs in one SQLite file; usable from many threads and processes at once."""

    def __init__(self, path: str | Path, *, timeout_s: float = 30.0) -> None:
        SQLiteFile.__init__(self, path, _SCHEMA, timeout_s=timeout_s)
        self._migrate()

    def _migrate(self) -> None:
        """Add the columns a database from an older release lacks. Under the write lock, so
        the server and a training process opening it at once do not both add one."""
        with self._write() as db:
            have = {row["name"] for row in db.execute("PRAGMA table_info(jobs)")}
            for name, declaration in _ADDED_COLUMNS:
                if name not in have:
                    db.execute(f"ALTER TABLE jobs ADD COLUMN {name} {declaration}")


    # -- helpers ---------------------------------------------------------------------------

    def _get(self, db: sqlite3.Connection, job_id: str) -> Job:
        row = db.execute(f"SELECT {_COLUMNS} FROM jobs WHERE id = ?", (job_id,)).fetchone()
        if row is None:
            raise JobNotFound(job_id)
        return _job(row)

    @staticmethod
    def _append(db: sqlite3.Connection, job_id: str, data: dict[str, Any], now: float) -> int:
        seq = db.execute("SELECT COALESCE(MAX(seq), 0) + 1 FROM events WHERE job_id = ?",
                         (job_id,)).fetchone()[0]
        db.execute("INSERT INTO events (job_id, seq, time, data) VALUES (?, ?, ?, ?)",
                   (job_id, seq, now, json.dumps({**data, "time": now}, allow_nan=False)))
        return int(seq)

    def _move(self, db: sqlite3.Connection, job: Job, state: str, now: float, *,
              note: dict[str, Any] | None = None, **columns: Any) -> None:
        if state not in _NEXT.get(job.state, ()):
            raise InvalidTransition(f"job {job.id} is {job.state}; it cannot become {state}")
        columns["state"] = state
        if state in TERMINAL:
            columns["finished"] = now
        elif state == "queued":  # to run again: no longer finished nor failing
            columns.setdefault("error", None)
            columns["finished"] = None
        sets = ", ".join(f"{k} = ?" for k in columns)
        db.execute(f"UPDATE jobs SET {sets} WHERE id = ?", (*columns.values(), job.id))
        event = {"type": "state", "state": state, **(note or {})}
        if columns.get("error"):
            event["error"] = columns["error"]
        if columns.get("avatar_id"):
            event["avatar_id"] = columns["avatar_id"]
        self._append(db, job.id, event, now)

    # -- the interface ---------------------------------------------------------------------

    def create(self, new: NewJob, *, max_active: int | None = None,
               max_stored: int | None = None) -> Job:
        job_id = new.id or new_job_id()
        now = time.time()
        with self._write() as db:
            check_quota(self._count(db, new.owner), new.owner, max_active, max_stored)
            db.execute(
                "INSERT INTO jobs (id, owner, name, state, dataset, dataset_path, config, "
                "created, total, max_attempts, kind) "
                "VALUES (?, ?, ?, 'queued', ?, ?, ?, ?, ?, ?, ?)",
                (job_id, new.owner, new.name, new.dataset, new.dataset_path,
                 json.dumps(new.config), now, int(new.total), new.max_attempts, new.kind))
            self._append(db, job_id, {"type": "state", "state": "queued"}, now)
            return self._get(db, job_id)

    def get(self, job_id: str) -> Job:
        return self._get(self._db(), job_id)

    @staticmethod
    def _count(db: sqlite3.Connection, owner: str) -> dict[str, int]:
        rows = db.execute("SELECT state, COUNT(*) FROM jobs WHERE owner = ? GROUP BY state",
                          (owner,))
        return {state: int(n) for state, n in rows}

    def count(self, owner: str) -> dict[str, int]:
        return self._count(self._db(), owner)

    def list(self, owner: str | None = None, state: str | None = None,
             limit: int = 100) -> list[Job]:
        where, args = [], []
        if owner is not None:
            where.append("owner = ?")
            args.append(owner)
        if state is not None:
            where.append("state = ?")
            args.append(state)
        sql = f"SELECT {_COLUMNS} FROM jobs"
        if where:
            sql += " WHERE " + " AND ".join(where)
        sql += " ORDER BY created DESC, rowid DESC LIMIT ?"
        return [_job(r) for r in self._db().execute(sql, (*args, int(limit)))]

    def claim_next(self) -> Job | None:
        now = time.time()
        with self._write() as db:
            row = db.execute(f"SELECT {_COLUMNS} FROM jobs WHERE state = 'queued' "
                             "ORDER BY created, rowid LIMIT 1").fetchone()
            if row is None:
                return None
            job = _job(row)
            self._move(db, job, "running", now, note={"attempt": job.attempts + 1},
                       started=job.started or now, attempts=job.attempts + 1)
            return self._get(db, job.id)

    def transition(self, job_id: str, state: str, *, error: str | None = None,
                   avatar_id: str | None = None, note: dict[str, Any] | None = None,
                   attempt_end: dict[str, Any] | None = None,
                   iteration: int | None = None) -> Job:
        now = time.time()
        columns: dict[str, Any] = {}
        if error is not None:
            columns["error"] = error
        if avatar_id is not None:
            columns["avatar_id"] = avatar_id
        if iteration is not None:
            columns["iteration"] = int(iteration)
        with self._write() as db:
            job = self._get(db, job_id)
            if attempt_end is not None:
                record = {**attempt_end, "time": now}
                kept = [*job.attempt_log, record][-MAX_ATTEMPT_LOG:]
                columns["attempt_log"] = json.dumps(kept, allow_nan=False)
                note = {**(note or {}), "attempt_end": record}
            self._move(db, job, state, now, note=note, **columns)
            return self._get(db, job_id)

    def resume(self, job_id: str, max_attempts: int,
               note: dict[str, Any] | None = None) -> Job:
        now = time.time()
        with self._write() as db:
            job = self._get(db, job_id)
            if job.state not in RESUMABLE:
                raise InvalidTransition(f"job {job_id} is {job.state}; only a failed job can "
                                        "be resumed")
            db.execute("UPDATE jobs SET state = 'queued', error = NULL, finished = NULL, "
                       "cancel_requested = 0, max_attempts = ? WHERE id = ?",
                       (int(max_attempts), job_id))
            self._append(db, job_id, {"type": "state", "state": "queued",
                                      "max_attempts": int(max_attempts), **(note or {})}, now)
            return self._get(db, job_id)

    def delete(self, job_id: str) -> None:
        with self._write() as db:
            job = self._get(db, job_id)
            if not job.done:
                raise InvalidTransition(f"job {job_id} is {job.state}; cancel it first")
            db.execute("DELETE FROM events WHERE job_id = ?", (job_id,))
            db.execute("DELETE FROM jobs WHERE id = ?", (job_id,))

    def request_cancel(self, job_id: str) -> Job:
        now = time.time()
        with self._write() as db:
            job = self._get(db, job_id)
            if job.state == "queued":
                self._move(db, job, "cancelled", now, error="cancelled before it ran",
                           cancel_requested=1)
            elif job.state == "running":
                if not job.cancel_requested:
                    db.execute("UPDATE jobs SET cancel_requested = 1 WHERE id = ?", (job_id,))
                    self._append(db, job_id, {"type": "cancel_requested"}, now)
            else:
                raise InvalidTransition(f"job {job_id} has already finished ({job.state})")
            return self._get(db, job_id)

    def report(self, job_id: str, event: dict[str, Any]) -> int:
        now = time.time()
        data = {k: (_finite(v) if isinstance(v, float) else v) for k, v in event.items()}
        data.setdefault("type", "message")
        with self._write() as db:
            job = self._get(db, job_id)
            if data["type"] in PROGRESS_TYPES:  # the one schema (protocol.jobs): + progress
                data.setdefault("iteration", job.iteration)
                data.setdefault("total", job.total)
                data = progress_event(data)
            if isinstance(data.get("iteration"), int):
                db.execute("UPDATE jobs SET iteration = ?, loss = COALESCE(?, loss) "
                           "WHERE id = ?", (data["iteration"], _finite(data.get("loss")),
                                            job_id))
            return self._append(db, job_id, data, now)

    def set_error(self, job_id: str, error: str) -> None:
        with self._write() as db:
            self._get(db, job_id)
            db.execute("UPDATE jobs SET error = ? WHERE id = ?", (error, job_id))

    def events(self, job_id: str, after: int = 0, limit: int = 1000) -> list[Event]:
        rows = self._db().execute(
            "SELECT job_id, seq, time, data FROM events WHERE job_id = ? AND seq > ? "
            "ORDER BY seq LIMIT ?", (job_id, int(after), int(limit)))
        return [Event(r["job_id"], r["seq"], r["time"], json.loads(r["data"])) for r in rows]


def check_quota(counts: dict[str, int], owner: str, max_active: int | None,
                max_stored: int | None) -> None:
    """QuotaExceeded when ``owner``, with ``counts`` jobs per state, may not add one."""
    active = sum(counts.get(state, 0) for state in ACTIVE)
    if max_active is not None and active >= max_active:
        raise QuotaExceeded(f"{owner} already has {active} queued or running jobs (at most "
                            f"{max_active}): wait for one to finish or cancel one")
    stored = sum(counts.values())
    if max_stored is not None and stored >= max_stored:
        raise QuotaExceeded(f"{owner} already has {stored} jobs stored (at most {max_stored}):"
                            " delete finished ones (DELETE /v1/jobs/{id})")
