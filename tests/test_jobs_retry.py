"""Faults and quotas of training jobs on a real server (uvicorn on 127.0.0.1) with the real
worker: a training process killed with SIGKILL (what the out-of-memory killer does) is
retried from its last checkpoint and the job succeeds; with no attempts left the job fails
with the reason and POST .../resume finishes it; past the per-user quotas a submission is
429, and deleting finished jobs frees the quota."""

import dataclasses
import os
import shutil
import signal

import pytest

from server.jobs.service import JobQuota

from . import test_jobs_support as support
from .server_fixtures import run_server
from .test_jobs_api import _client, _sse, _upload
from .test_jobs_support import FAST, LONG, training_pids, wait_for, zip_dataset

capture_dir = support.capture_dir  # the shared session fixture

# long enough (~40 iterations at 5-10/s) that the kill lands after the first checkpoint
# (iteration 10) and well before the end
KILLABLE = {**FAST, "iterations": 40}
KILL_REASON = "killed by SIGKILL (likely out of memory)"


@pytest.fixture(scope="module")
def srv(tmp_path_factory, capture_dir):
    with run_server(tmp_path_factory.mktemp("jobs-retry")) as server:
        jobs = server.app.state.ctx.jobs
        jobs.worker.config = dataclasses.replace(jobs.worker.config, nice=0, poll_s=0.05)
        shutil.copytree(capture_dir, jobs.datasets_dir / "take")
        server.alice = server.issue("alice", ("train",))
        server.bob = server.issue("bob", ("train",))
        server.viewer = server.issue("carol", ("stream",))
        yield server


def _kill_after_first_checkpoint(jobs, job_id: str) -> int:
    """SIGKILL the job's training process once it has written a checkpoint; that
    checkpoint's iteration."""
    first = wait_for(lambda: next((e for e in jobs.store.events(job_id)
                                   if e.type == "checkpoint"), None), 120,
                     what="the first checkpoint")
    pid = jobs.worker.process_id(job_id)
    assert pid is not None and pid in training_pids(job_id)
    os.kill(pid, signal.SIGKILL)
    return first.data["iteration"]


def _states(events) -> list[str]:
    return [e["data"]["state"] for e in events if e["event"] == "state"]


def test_a_killed_trainer_resumes_from_its_checkpoint(srv):
    jobs, alice = srv.app.state.ctx.jobs, _client(srv, srv.alice)
    r = alice.post("/v1/jobs", json={"dataset": "take", "config": KILLABLE, "name": "Phoenix"})
    assert r.status_code == 201, r.text
    job = r.json()
    assert (job["attempts"], job["max_attempts"], job["attempt_log"]) == (0, 3, [])
    checkpointed = _kill_after_first_checkpoint(jobs, job["id"])

    events = _sse(alice, job["id"])
    assert events[-1]["data"]["state"] == "succeeded", alice.get(
        f"/v1/jobs/{job['id']}/logs").text
    assert _states(events) == ["queued", "running", "queued", "running", "succeeded"]
    requeue = [e["data"] for e in events if e["event"] == "state"][2]
    assert requeue["reason"] == KILL_REASON
    end = requeue["attempt_end"]
    assert (end["attempt"], end["exit_code"], end["outcome"]) == (1, -signal.SIGKILL,
                                                                  "requeued")
    assert end["resume_iteration"] >= checkpointed
    assert end["resume_from"] == requeue["resume_from"] == (
        f"iter_{end['resume_iteration']:06d}.pt")
    kinds = [e["event"] for e in events]
    resumed = events[kinds.index("resumed")]["data"]
    assert kinds.count("resumed") == 1 and resumed["iteration"] == end["resume_iteration"]
    # the second run goes on from there: it does not train the first iterations again
    after = [e["data"]["iteration"] for e in events[kinds.index("resumed"):]
             if e["event"] == "progress"]
    assert after and min(after) > resumed["iteration"]

    status = alice.get(f"/v1/jobs/{job['id']}").json()
    assert (status["state"], status["attempts"], status["iteration"]) == (
        "succeeded", 2, KILLABLE["iterations"])
    assert [a["reason"] for a in status["attempt_log"]] == [KILL_REASON]
    record = srv.app.state.ctx.registry.get(status["avatar_id"])
    assert (record.owner, record.name, record.source) == ("alice", "Phoenix",
                                                          f"job:{job['id']}")
    log = alice.get(f"/v1/jobs/{job['id']}/logs").text
    assert "attempt 1" in log and "attempt 2" in log and "resumed job" in log


def test_out_of_attempts_fails_with_the_reason_and_resume_finishes_it(srv):
    jobs = srv.app.state.ctx.jobs
    alice, bob, viewer = (_client(srv, t) for t in (srv.alice, srv.bob, srv.viewer))
    config = jobs.worker.config
    jobs.worker.config = dataclasses.replace(config, max_attempts=1)
    try:
        job = alice.post("/v1/jobs", json={"dataset": "take", "config": KILLABLE}).json()
    finally:
        jobs.worker.config = config
    assert job["max_attempts"] == 1  # the budget is the job's, fixed at submit
    checkpointed = _kill_after_first_checkpoint(jobs, job["id"])
    failed_events = _sse(alice, job["id"])
    assert _states(failed_events) == ["queued", "running", "failed"]
    failed = alice.get(f"/v1/jobs/{job['id']}").json()
    assert failed["state"] == "failed" and KILL_REASON in failed["error"]
    assert "no attempts left" in failed["error"]
    (end,) = failed["attempt_log"]
    assert end["outcome"] == "failed" and end["resume_iteration"] >= checkpointed
    assert failed_events[-1]["data"]["error"] == failed["error"]

    url = f"/v1/jobs/{job['id']}/resume"
    assert viewer.post(url).status_code == 403
    assert bob.post(url).status_code == 404  # another owner's job does not exist for bob
    r = alice.post(url)
    assert r.status_code == 202, r.text
    queued = r.json()
    assert (queued["state"], queued["error"], queued["max_attempts"]) == (
        "queued", None, 1 + config.max_attempts)
    events = _sse(alice, job["id"], params={"after": int(failed_events[-2]["id"])})
    assert _states(events) == ["queued", "running", "succeeded"], events
    assert events[0]["data"]["reason"] == "resumed on request"
    assert events[0]["data"]["resume_from"] == end["resume_from"]
    (resumed,) = [e["data"] for e in events if e["event"] == "resumed"]
    assert resumed["iteration"] == end["resume_iteration"]
    done = alice.get(f"/v1/jobs/{job['id']}").json()
    assert done["state"] == "succeeded" and done["attempts"] == 2 and done["avatar_id"]
    assert srv.app.state.ctx.registry.get(done["avatar_id"]).owner == "alice"
    r = alice.post(url)  # succeeded: nothing to resume
    assert r.status_code == 409 and "only a failed job" in r.json()["detail"]


def test_job_quotas_answer_429_and_deleting_frees_them(srv, capture_dir):
    jobs = srv.app.state.ctx.jobs
    alice, admin = _client(srv, srv.alice), _client(srv, srv.token)
    quota = jobs.quota
    running = []
    try:
        jobs.quota = JobQuota(max_active=1, max_stored=None)
        first = alice.post("/v1/jobs", json={"dataset": "take", "config": LONG})
        assert first.status_code == 201, first.text
        running.append(first.json()["id"])
        r = alice.post("/v1/jobs", json={"dataset": "take", "config": LONG})
        assert r.status_code == 429 and "at most 1" in r.json()["detail"], r.text
        before = {p.name for p in jobs.jobs_dir.iterdir()}
        r = _upload(alice, zip_dataset(capture_dir), FAST)
        assert r.status_code == 429, r.text
        assert {p.name for p in jobs.jobs_dir.iterdir()} == before  # nothing unpacked
        r = admin.post("/v1/jobs", json={"dataset": "take", "config": LONG})
        assert r.status_code == 201, r.text  # admins are exempt
        running.append(r.json()["id"])
        assert alice.delete(f"/v1/jobs/{running[0]}").status_code == 409  # still active

        stored = len(alice.get("/v1/jobs", params={"limit": 1000}).json()["jobs"])
        jobs.quota = JobQuota(max_active=None, max_stored=stored)
        r = alice.post("/v1/jobs", json={"dataset": "take", "config": LONG})
        assert r.status_code == 429 and "stored" in r.json()["detail"], r.text
        for job_id in running:
            assert admin.post(f"/v1/jobs/{job_id}/cancel").status_code == 202
        wait_for(lambda: all(jobs.store.get(j).done for j in running), 30,
                 what="the cancels")
        assert alice.delete(f"/v1/jobs/{running[0]}").status_code == 204
        assert alice.get(f"/v1/jobs/{running[0]}").status_code == 404
        assert not jobs.worker.job_dir(running[0]).exists()
        r = alice.post("/v1/jobs", json={"dataset": "take", "config": FAST})
        assert r.status_code == 201, r.text  # one stored job fewer: room for one
        wait_for(lambda: jobs.store.get(r.json()["id"]).done, 120, what="the last job")
    finally:
        jobs.quota = quota
        for job_id in running:
            if any(j.id == job_id and not j.done for j in jobs.store.list(limit=1000)):
                jobs.cancel(job_id)
