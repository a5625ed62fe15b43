"""The job store: state transitions, event order, cancel, reading back after a restart, two
writers (threads) at once, attempt records, resume and delete, quotas, and the migration of
a database written by the previous release."""

import dataclasses
import sqlite3
import threading

import pytest

from server.jobs.store import (
    MAX_ATTEMPT_LOG,
    InvalidTransition,
    JobNotFound,
    NewJob,
    QuotaExceeded,
    SQLiteJobStore,
)


def _new(owner="alice", total=100, **kw) -> NewJob:
    return NewJob(owner=owner, dataset="dataset:take1", dataset_path="/data/take1",
                  config={"iterations": total}, total=total, **kw)


@pytest.fixture
def store(tmp_path):
    s = SQLiteJobStore(tmp_path / "jobs.db")
    yield s
    s.close()


def _states(store, job_id):
    return [e.data["state"] for e in store.events(job_id) if e.type == "state"]


def test_lifecycle_and_events_in_order(store):
    job = store.create(_new(name="Alice"))
    assert job.state == "queued" and job.attempts == 0 and job.progress == 0
    assert job.name == "Alice" and job.config == {"iterations": 100}
    claimed = store.claim_next()
    assert claimed.id == job.id and claimed.state == "running" and claimed.attempts == 1
    assert claimed.started is not None and store.claim_next() is None
    store.report(job.id, {"type": "progress", "iteration": 40, "total": 100, "loss": 0.5})
    store.report(job.id, {"type": "progress", "iteration": 80, "total": 100,
                          "loss": float("nan")})  # NaN is stored as null, the last loss kept
    got = store.get(job.id)
    assert got.iteration == 80 and got.progress == pytest.approx(0.8) and got.loss == 0.5
    done = store.transition(job.id, "succeeded", avatar_id="av1")
    assert done.done and done.avatar_id == "av1" and done.finished >= done.started
    events = store.events(job.id)
    assert [e.seq for e in events] == list(range(1, len(events) + 1))
    assert [e.type for e in events] == ["state", "state", "progress", "progress", "state"]
    assert _states(store, job.id) == ["queued", "running", "succeeded"]
    assert events[3].data["loss"] is None and events[-1].data["avatar_id"] == "av1"
    assert [e.seq for e in store.events(job.id, after=3)] == [4, 5]
    with pytest.raises(InvalidTransition):
        store.transition(job.id, "running")


def test_invalid_transitions_and_unknown_ids(store):
    job = store.create(_new())
    with pytest.raises(InvalidTransition):
        store.transition(job.id, "succeeded")  # queued cannot succeed
    with pytest.raises(JobNotFound):
        store.get("nope")
    with pytest.raises(JobNotFound):
        store.report("nope", {"type": "progress"})


def test_cancel_queued_is_immediate_running_is_a_request(store):
    a, b = store.create(_new()), store.create(_new())
    assert store.claim_next().id == a.id  # oldest first
    cancelled = store.request_cancel(b.id)
    assert cancelled.state == "cancelled" and cancelled.error
    running = store.request_cancel(a.id)
    assert running.state == "running" and running.cancel_requested
    store.request_cancel(a.id)  # twice: one cancel_requested event
    assert [e.type for e in store.events(a.id)].count("cancel_requested") == 1
    store.transition(a.id, "cancelled")
    with pytest.raises(InvalidTransition):
        store.request_cancel(a.id)


def test_requeue_keeps_attempts_and_claims_oldest_first(store):
    first = store.create(_new())
    second = store.create(_new())
    store.claim_next()
    store.transition(first.id, "queued", note={"reason": "the server restarted"})
    again = store.claim_next()
    assert again.id == first.id and again.attempts == 2
    assert store.claim_next().id == second.id


def test_list_by_owner_and_state(store):
    a = store.create(_new("alice"))
    store.create(_new("bob"))
    c = store.create(_new("alice"))
    store.claim_next()
    assert [j.id for j in store.list(owner="alice")] == [c.id, a.id]  # newest first
    assert [j.id for j in store.list(state="running")] == [a.id]
    assert len(store.list()) == 3 and len(store.list(limit=2)) == 2


def test_everything_reads_back_after_a_restart(tmp_path):
    first = SQLiteJobStore(tmp_path / "jobs.db")
    job = first.create(_new())
    first.claim_next()
    first.report(job.id, {"type": "progress", "iteration": 10, "loss": 0.25})
    first.set_error(job.id, "boom")
    first.close()
    again = SQLiteJobStore(tmp_path / "jobs.db")
    got = again.get(job.id)
    assert (got.state, got.iteration, got.loss, got.error, got.attempts) == (
        "running", 10, 0.25, "boom", 1)
    assert [e.type for e in again.events(job.id)] == ["state", "state", "progress"]
    again.close()


def test_concurrent_writers_keep_one_sequence(store):
    job = store.create(_new())

    def write(n):
        for i in range(n):
            store.report(job.id, {"type": "progress", "iteration": i})

    threads = [threading.Thread(target=write, args=(25,)) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=30)
    seqs = [e.seq for e in store.events(job.id)]
    assert seqs == list(range(1, 102))


def test_attempt_log_requeue_resume_and_delete(store):
    job = store.create(_new(max_attempts=2))
    assert (job.max_attempts, job.attempt_log) == (2, ())
    store.claim_next()
    store.report(job.id, {"type": "progress", "iteration": 17})
    store.set_error(job.id, "stale")
    end = {"attempt": 1, "reason": "killed by SIGKILL", "resume_from": "iter_000010.pt"}
    again = store.transition(job.id, "queued", attempt_end=end, iteration=10,
                             note={"reason": "killed by SIGKILL"})
    assert again.iteration == 10 and again.error is None and again.finished is None
    (logged,) = again.attempt_log
    assert logged["reason"] == "killed by SIGKILL" and logged["time"] > 0
    assert store.events(job.id)[-1].data["attempt_end"] == logged
    assert again.to_dict()["attempt_log"] == [logged]
    with pytest.raises(InvalidTransition):
        store.resume(job.id, 5)  # queued: not resumable
    store.claim_next()
    failed = store.transition(job.id, "failed", error="no attempts left")
    assert failed.finished is not None
    resumed = store.resume(job.id, 5, note={"reason": "resumed on request"})
    assert (resumed.state, resumed.max_attempts, resumed.error, resumed.finished) == (
        "queued", 5, None, None)
    assert resumed.attempts == 2 and len(resumed.attempt_log) == 1
    assert store.events(job.id)[-1].data["reason"] == "resumed on request"
    with pytest.raises(InvalidTransition):
        store.delete(job.id)  # active
    store.request_cancel(job.id)
    store.delete(job.id)
    with pytest.raises(JobNotFound):
        store.get(job.id)
    assert store.events(job.id) == []


def test_the_attempt_log_keeps_the_newest_records(store):
    job = store.create(_new())
    for attempt in range(1, MAX_ATTEMPT_LOG + 6):
        store.claim_next()
        store.transition(job.id, "queued", attempt_end={"attempt": attempt, "reason": "x"})
    log = store.get(job.id).attempt_log
    assert len(log) == MAX_ATTEMPT_LOG and log[-1]["attempt"] == MAX_ATTEMPT_LOG + 5


def test_quotas_are_checked_with_the_insert(store):
    store.create(_new("alice"), max_active=1)
    with pytest.raises(QuotaExceeded, match="at most 1"):
        store.create(_new("alice"), max_active=1)
    store.create(_new("bob"), max_active=1)  # per owner
    assert store.count("alice") == {"queued": 1}
    store.request_cancel(store.list(owner="alice")[0].id)
    store.create(_new("alice"), max_active=1, max_stored=2)  # the cancelled one is not active
    with pytest.raises(QuotaExceeded, match="stored"):
        store.create(_new("alice"), max_stored=2)
    assert len(store.list(owner="alice")) == 2


_OLD_SCHEMA = """
CREATE TABLE jobs (
    id TEXT PRIMARY KEY, owner TEXT NOT NULL, name TEXT,
    state TEXT NOT NULL CHECK (state IN ('queued','running','succeeded','failed','cancelled')),
    dataset TEXT NOT NULL, dataset_path TEXT NOT NULL, config TEXT NOT NULL,
    created REAL NOT NULL, started REAL, finished REAL,
    iteration INTEGER NOT NULL DEFAULT 0, total INTEGER NOT NULL, loss REAL, error TEXT,
    avatar_id TEXT, attempts INTEGER NOT NULL DEFAULT 0,
    cancel_requested INTEGER NOT NULL DEFAULT 0);
CREATE TABLE events (job_id TEXT NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
    seq INTEGER NOT NULL, time REAL NOT NULL, data TEXT NOT NULL, PRIMARY KEY (job_id, seq));
INSERT INTO jobs (id, owner, state, dataset, dataset_path, config, created, total, attempts)
    VALUES ('old1', 'alice', 'running', 'upload', '/x', '{"iterations": 5}', 1.0, 5, 1);
"""


def test_a_database_of_the_previous_release_is_migrated(tmp_path):
    path = tmp_path / "jobs.db"
    with sqlite3.connect(path) as db:
        db.executescript(_OLD_SCHEMA)
    db.close()
    store = SQLiteJobStore(path)
    old = store.get("old1")
    assert (old.state, old.attempts, old.max_attempts, old.attempt_log, old.kind) == (
        "running", 1, None, (), "train")  # every job before enrollment trained a dataset
    store.transition("old1", "queued", attempt_end={"attempt": 1, "reason": "restart"})
    store.close()
    again = SQLiteJobStore(path)  # opening a migrated database changes nothing
    assert again.get("old1").attempt_log[0]["reason"] == "restart"
    assert again.create(_new(max_attempts=3)).max_attempts == 3
    enroll = again.create(dataclasses.replace(_new(), kind="enroll"))
    assert again.get(enroll.id).kind == "enroll"
    again.close()
