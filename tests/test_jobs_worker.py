"""The worker with real training processes (the successful run is in test_jobs_api): a clean
stop checkpoints and re-queues, the next start resumes, cancel stops a running process; after
a real crash (the old server killed with SIGKILL) a running job resumes from its checkpoint
and the queued one stays queued; a running job left without a checkpoint starts again, one
out of attempts fails with the reason. (A killed training process: test_jobs_retry.)"""

import os
import shutil
import signal
import subprocess
import sys
import textwrap

import pytest

from server.jobs.run import OUT_DIR
from server.jobs.service import JobService
from server.jobs.store import NewJob, SQLiteJobStore
from server.jobs.worker import LOG_FILE

from . import test_jobs_support as support
from .test_jobs_support import (
    FAST,
    LONG,
    make_service,
    training_pids,
    wait_for,
    wait_state,
)

capture_dir = support.capture_dir  # the shared session fixture


def _named(service: JobService, capture_dir, name="take"):
    shutil.copytree(capture_dir, service.datasets_dir / name, dirs_exist_ok=True)
    return name


def _kinds(service, job_id):
    return [e.type for e in service.store.events(job_id)]


def test_a_clean_stop_checkpoints_and_a_cancel_stops_the_resumed_run(tmp_path, capture_dir,
                                                                     synthetic_files):
    first = make_service(tmp_path, synthetic_files)
    first.start()
    try:
        job = first.submit_named("alice", _named(first, capture_dir), LONG)
        wait_for(lambda: "progress" in _kinds(first, job.id), 60, what="training")
        # the server's session (one autogroup: job_nice yields to its live sessions), a
        # process group of its own (a Ctrl-C at the terminal reaches the server only)
        pid = first.worker.process_id(job.id)
        assert os.getsid(pid) == os.getsid(0) and os.getpgid(pid) == pid
    finally:
        first.stop(grace_s=30)  # SIGTERM: it checkpoints at its next progress event
    store = SQLiteJobStore(tmp_path / "jobs" / "jobs.db")
    stopped, last = store.get(job.id), store.events(job.id)[-1].data
    store.close()
    assert stopped.state == "queued" and stopped.iteration > 0
    assert last["reason"] == "the server stopped"
    assert last["resume_from"] == f"iter_{stopped.iteration:06d}.pt"  # not on the interval

    second = make_service(tmp_path, synthetic_files)
    second.start()
    try:
        resumed = wait_for(lambda: [e for e in second.store.events(job.id)
                                    if e.type == "resumed"], 60, what="the resume")
        assert resumed[0].data["iteration"] == stopped.iteration
        wait_for(lambda: second.store.get(job.id).iteration > stopped.iteration, 30,
                 what="training after the resume")
        assert second.cancel(job.id).cancel_requested
        done = wait_state(second, job.id, ("cancelled", "failed", "succeeded"), timeout=20)
        assert done.state == "cancelled" and done.avatar_id is None and done.attempts == 2
        assert second.worker.running() == []
        wait_for(lambda: not training_pids(job.id), 10, what="the process to end")
        log = (second.worker.job_dir(job.id) / LOG_FILE).read_text()
        assert "interrupted at iteration" in log and "cancelled at iteration" in log
        assert not (second.worker.job_dir(job.id) / "out" / "checkpoints").exists()
    finally:
        second.stop(grace_s=2)


_SERVER = textwrap.dedent("""
    import sys, threading
    sys.path.insert(0, {tests!r})
    from server.jobs.service import JobService
    from server.jobs.worker import WorkerConfig
    config = WorkerConfig(body_models={models!r}, nice=0, poll_s=0.05)
    JobService({data!r}, lambda job, package: "never", worker=config).start()
    print("started", flush=True)
    threading.Event().wait()
""")


def test_a_restart_resumes_the_running_job_and_keeps_the_queued_one(tmp_path, capture_dir,
                                                                     synthetic_files):
    first = make_service(tmp_path, synthetic_files)  # used to submit only: not started
    name = _named(first, capture_dir)
    running = first.submit_named("alice", name, {**FAST, "iterations": 30})
    queued = first.submit_named("bob", name, FAST)
    first.store.close()
    code = _SERVER.format(tests=os.path.dirname(os.path.dirname(__file__)),
                          models=str(synthetic_files.root), data=str(tmp_path))
    server = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE)
    store = SQLiteJobStore(tmp_path / "jobs" / "jobs.db")
    try:
        wait_for(lambda: any(e.type == "checkpoint" for e in store.events(running.id)), 60,
                 what="the first checkpoint")
        assert store.get(queued.id).state == "queued"
    finally:
        server.send_signal(signal.SIGKILL)  # the server dies; its training process follows
        server.wait(timeout=10)
        server.stdout.close()
    wait_for(lambda: not training_pids(running.id), 10, what="the orphan to exit")
    assert store.get(running.id).state == "running"  # as the dead server left it
    store.close()

    second = make_service(tmp_path, synthetic_files)
    second.start()
    try:
        resumed = wait_state(second, running.id, ("succeeded", "failed"))
        assert resumed.state == "succeeded", resumed.error
        assert resumed.attempts == 2 and resumed.iteration == resumed.total
        record = second.registry.get(resumed.avatar_id)  # registered for its owner, loads
        assert record.owner == "alice" and record.source == f"job:{running.id}"
        assert second.registry.open(record.id).package.avatar.num == record.num_gaussians
        events = second.store.events(running.id)
        requeue = next(e for e in events if e.data.get("reason") == "the server restarted")
        assert requeue.data["resume_from"].startswith("iter_")
        (resume,) = [e for e in events if e.type == "resumed"]
        assert 10 <= resume.data["iteration"] < 30
        # the queued job stayed queued and runs next; a clean stop re-queues it
        wait_state(second, queued.id, "running", timeout=30)
    finally:
        second.stop(grace_s=5)
    after = SQLiteJobStore(tmp_path / "jobs" / "jobs.db")
    assert after.get(queued.id).state == "queued"
    assert after.events(queued.id)[-1].data["reason"] == "the server stopped"
    after.close()


@pytest.mark.parametrize("case", ["no_checkpoint", "cancel_requested", "too_many_attempts"])
def test_running_jobs_left_by_a_dead_server_are_settled_at_start(tmp_path, synthetic_files,
                                                                  case):
    store = SQLiteJobStore(tmp_path / "jobs" / "jobs.db")
    job = store.create(NewJob("alice", "upload", str(tmp_path), {"iterations": 5}, 5))
    for _ in range(3 if case == "too_many_attempts" else 1):
        store.claim_next()
        if case == "too_many_attempts":
            ckpt = tmp_path / "jobs" / job.id / OUT_DIR / "checkpoints" / "iter_000002.pt"
            ckpt.parent.mkdir(parents=True, exist_ok=True)
            ckpt.write_bytes(b"")
            if store.get(job.id).attempts < 3:
                store.transition(job.id, "queued")
    if case == "cancel_requested":
        store.request_cancel(job.id)
    store.close()
    service = make_service(tmp_path, synthetic_files)
    service.worker.recover()  # what start() does first (without then running the job)
    got = service.store.get(job.id)
    service.store.close()
    expected = {"no_checkpoint": ("queued", None),  # attempts left: from the start
                "cancel_requested": ("cancelled", "cancelled"),
                "too_many_attempts": ("failed", "no attempts left")}[case]
    assert got.state == expected[0]
    assert got.error is None if expected[1] is None else expected[1] in got.error
    if case != "cancel_requested":
        (end,) = got.attempt_log
        assert end["reason"] == "the server restarted" and end["attempt"] == got.attempts
        assert end["resume_from"] == (None if case == "no_checkpoint" else "iter_000002.pt")
        assert end["outcome"] == ("requeued" if case == "no_checkpoint" else "failed")


def test_one_worker_per_data_dir(tmp_path, synthetic_files):
    """A second server on the same data_dir accepts submissions but neither recovers nor
    runs jobs while the first holds the worker lock."""
    import fcntl

    store = SQLiteJobStore(tmp_path / "jobs" / "jobs.db")
    job = store.create(NewJob("alice", "upload", str(tmp_path), {"iterations": 5}, 5))
    store.claim_next()  # left running, no checkpoint
    store.close()
    with open(tmp_path / "jobs" / "worker.lock", "a+b") as held:
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)  # the "first server"
        second = make_service(tmp_path, synthetic_files)
        second.start()
        assert second.store.get(job.id).state == "running"  # not touched
        second.stop(grace_s=1)
    third = make_service(tmp_path, synthetic_files)
    third.start()
    try:  # recovered: re-queued to start again (its dataset then fails it)
        assert any(e.data.get("reason") == "the server restarted"
                   for e in third.store.events(job.id))
    finally:
        third.stop(grace_s=1)
