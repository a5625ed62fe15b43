"""Training jobs on a real local Ray cluster (job_backend "ray"), through the REST API of a
real server (uvicorn on 127.0.0.1): a job trains on a Ray actor to completion, streams its
events and its avatar streams (the same test on the local backend too); jobs run side by
side while the cluster has room and the rest wait queued; cancel ends the actor's process; a
killed Ray worker process resumes from its last checkpoint (or fails with the reason when no
attempts are left); a server stopped, or a ``telesplat serve --cluster`` process killed,
mid-job: the next server resumes the job from its checkpoint on Ray. The local backend's
faults are tested in test_jobs_retry.py, with the same assertions."""

from __future__ import annotations

import asyncio
import dataclasses
import os
import shutil
import signal
import subprocess
import sys
import threading
from pathlib import Path

import httpx
import pytest

from protocol import Frame

from . import test_jobs_support as support
from .ray_cluster import REPO, ray_cluster, requires_ray
from .server_fixtures import is_type, recv_until, run_server, stream
from .test_jobs_api import _client, _sse, _upload
from .test_jobs_support import FAST, LONG, wait_for, zip_dataset

# one Ray cluster for the module: under pytest -n 2 --dist loadgroup, all on one worker
pytestmark = [requires_ray, pytest.mark.xdist_group("cluster_jobs")]

capture_dir = support.capture_dir  # the shared session fixture
KILLABLE = {**FAST, "iterations": 40}  # the kill lands after the first checkpoint (10)
RAY_DIED = "the Ray worker process died"
CLUSTER_CPUS = 2  # room for two 1-CPU jobs at once


@pytest.fixture(scope="module")
def ray_head():
    with ray_cluster(num_cpus=CLUSTER_CPUS) as head:
        yield head


def _serve(data_dir: Path, backend: str, head=None, **overrides):
    extra = {"job_backend": "ray", "cluster_address": head.address} if backend == "ray" else {}
    # no warm-up render: the numba kernels are cached on disk, and the jobs are the point;
    # one thread per job: two jobs share the 2-CPU test cluster (a Ray job asks its threads)
    return run_server(data_dir, warmup=False, **{"job_threads": 1, **extra, **overrides})


def _tune(server, capture_dir) -> None:
    jobs = server.app.state.ctx.jobs
    # full speed in tests (the default lowers the training process's priority)
    jobs.worker.config = dataclasses.replace(jobs.worker.config, nice=0, poll_s=0.05)
    if not (jobs.datasets_dir / "take").exists():
        shutil.copytree(capture_dir, jobs.datasets_dir / "take")


def _server(request, tmp_path_factory, capture_dir, backend: str):
    head = request.getfixturevalue("ray_head") if backend == "ray" else None
    # on Ray, job folders and datasets live apart from data_dir: where every node reaches
    shared = {"cluster_storage": tmp_path_factory.mktemp("shared")} if head else {}
    with _serve(tmp_path_factory.mktemp(f"cluster-jobs-{backend}"), backend, head,
                **shared) as server:
        _tune(server, capture_dir)
        server.backend = backend
        server.alice = server.issue("alice", ("train", "stream"))
        yield server


@pytest.fixture(scope="module")
def ray_srv(request, tmp_path_factory, capture_dir):
    yield from _server(request, tmp_path_factory, capture_dir, "ray")


@pytest.fixture(params=["ray", "local"])
def srv(request, tmp_path_factory, capture_dir):
    """The Ray server of the module, or a server on the local backend."""
    if request.param == "ray":
        yield request.getfixturevalue("ray_srv")
    else:
        yield from _server(request, tmp_path_factory, capture_dir, "local")


def _states(events) -> list[str]:
    return [e["data"]["state"] for e in events if e["event"] == "state"]


def _alive(pid: int) -> bool:
    """A live (not zombie) process with this pid."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def _first_checkpoint(jobs, job_id: str) -> int:
    return wait_for(lambda: next((e.data["iteration"] for e in jobs.store.events(job_id)
                                  if e.type == "checkpoint"), None), 120,
                    what="the first checkpoint")


def _pid(jobs, job_id: str) -> int:
    return wait_for(lambda: jobs.worker.process_id(job_id), 120, what="the job's process")


def test_a_job_trains_streams_events_and_its_avatar_streams(srv, capture_dir):
    alice = _client(srv, srv.alice)
    r = _upload(alice, zip_dataset(capture_dir), FAST, name="Remote")
    assert r.status_code == 201, r.text
    job = r.json()
    events = _sse(alice, job["id"])
    log = alice.get(f"/v1/jobs/{job['id']}/logs").text
    assert events[-1]["data"]["state"] == "succeeded", log
    assert _states(events) == ["queued", "running", "succeeded"]
    kinds = [e["event"] for e in events]
    assert kinds.count("progress") == 4 and "checkpoint" in kinds and "done" in kinds
    ids = [int(e["id"]) for e in events[:-1]]
    assert ids == list(range(1, len(ids) + 1))  # the actor's events, in order, no gaps
    assert all("path" not in e["data"] for e in events)

    status = alice.get(f"/v1/jobs/{job['id']}").json()
    assert (status["iteration"], status["attempts"]) == (20, 1) and status["loss"] is not None
    record = srv.ctx.registry.get(status["avatar_id"])
    assert (record.owner, record.name) == ("alice", "Remote")
    assert "attempt 1" in log and "trained" in log
    folder = srv.ctx.jobs.worker.job_dir(job["id"])  # the upload and checkpoints freed
    if srv.backend == "ray":
        assert "on Ray" in log and "Ray worker process" in log
        assert folder.is_relative_to(srv.settings.cluster_storage)
        assert (folder / "out" / "avatar").is_dir()  # the package, on the shared storage
        assert (srv.settings.data_dir / "jobs" / "jobs.db").is_file()  # the store stays
    assert not (folder / "dataset").exists() and not (folder / "out" / "checkpoints").exists()

    async def one_frame():
        async with stream(srv, avatar=status["avatar_id"], token=srv.alice) as ws:
            return await recv_until(ws, is_type("frame"), timeout=60)

    assert isinstance(asyncio.run(one_frame()), Frame)


def test_a_killed_worker_process_resumes_from_its_checkpoint(ray_srv):
    srv = ray_srv
    jobs, alice = srv.ctx.jobs, _client(srv, srv.alice)
    job = alice.post("/v1/jobs", json={"dataset": "take", "config": KILLABLE}).json()
    checkpointed = _first_checkpoint(jobs, job["id"])
    pid = _pid(jobs, job["id"])
    os.kill(pid, signal.SIGKILL)

    events = _sse(alice, job["id"])
    assert _states(events) == ["queued", "running", "queued", "running", "succeeded"], \
        alice.get(f"/v1/jobs/{job['id']}/logs").text
    requeue = [e["data"] for e in events if e["event"] == "state"][2]
    end = requeue["attempt_end"]
    assert end["outcome"] == "requeued" and end["resume_iteration"] >= checkpointed
    assert end["resume_from"] == f"iter_{end['resume_iteration']:06d}.pt"
    assert requeue["reason"].startswith(RAY_DIED) and end["exit_code"] is None
    kinds = [e["event"] for e in events]
    resumed = events[kinds.index("resumed")]["data"]
    assert resumed["iteration"] == end["resume_iteration"]  # no checkpoint lost
    after = [e["data"]["iteration"] for e in events[kinds.index("resumed"):]
             if e["event"] == "progress"]
    assert after and min(after) > resumed["iteration"]  # it went on from there
    status = alice.get(f"/v1/jobs/{job['id']}").json()
    assert (status["state"], status["attempts"], status["iteration"]) == (
        "succeeded", 2, KILLABLE["iterations"])


def test_no_attempts_left_fails_with_the_reason(ray_srv):
    jobs, alice = ray_srv.ctx.jobs, _client(ray_srv, ray_srv.alice)
    config = jobs.worker.config
    jobs.worker.config = dataclasses.replace(config, max_attempts=1)
    try:
        job = alice.post("/v1/jobs", json={"dataset": "take", "config": LONG}).json()
    finally:
        jobs.worker.config = config
    checkpointed = _first_checkpoint(jobs, job["id"])
    os.kill(_pid(jobs, job["id"]), signal.SIGKILL)
    events = _sse(alice, job["id"])
    assert _states(events) == ["queued", "running", "failed"]
    failed = alice.get(f"/v1/jobs/{job['id']}").json()
    assert "no attempts left" in failed["error"]
    (end,) = failed["attempt_log"]
    assert end["outcome"] == "failed" and end["resume_iteration"] >= checkpointed
    checkpoint = jobs.worker.job_dir(job["id"]) / "out" / "checkpoints" / end["resume_from"]
    assert checkpoint.is_file() and RAY_DIED in failed["error"]  # kept for a resume


def test_jobs_share_the_cluster_and_cancel_ends_the_actor(ray_srv):
    jobs, alice = ray_srv.ctx.jobs, _client(ray_srv, ray_srv.alice)
    ids = [alice.post("/v1/jobs", json={"dataset": "take", "config": LONG}).json()["id"]
           for _ in range(CLUSTER_CPUS + 1)]
    first, last = ids[:CLUSTER_CPUS], ids[-1]
    try:
        wait_for(lambda: all(jobs.store.get(j).iteration > 0 for j in first), 120,
                 what="two jobs training at once")
        # both placed, every CPU of the cluster held: the third waits in the queue
        assert jobs.store.get(last).state == "queued"
        pid = _pid(jobs, first[0])
        assert _alive(pid)
        assert alice.post(f"/v1/jobs/{first[0]}/cancel").status_code == 202
        events = _sse(alice, first[0])
        assert _states(events) == ["queued", "running", "cancelled"]
        wait_for(lambda: not _alive(pid), 30, what=f"the actor's process {pid} to end")
        wait_for(lambda: jobs.store.get(last).state == "running", 120,
                 what="the queued job to start in the room freed")
    finally:
        for job_id in ids:
            if not jobs.store.get(job_id).done:
                jobs.cancel(job_id)
        wait_for(lambda: all(jobs.store.get(j).done for j in ids), 60, what="the cancels")


def test_a_job_the_cluster_can_never_hold_fails_with_the_reason(ray_srv):
    jobs, alice = ray_srv.ctx.jobs, _client(ray_srv, ray_srv.alice)
    jobs.worker.num_gpus = 1.0  # as ray_job_num_gpus = 1; the test cluster has no GPU
    try:
        job = alice.post("/v1/jobs", json={"dataset": "take", "config": FAST}).json()
        failed = wait_for(lambda: (j := jobs.store.get(job["id"])).done and j, 60,
                          what="the job to fail")
    finally:
        jobs.worker.num_gpus = None
    assert failed.state == "failed" and failed.attempts == 1
    assert "asks for CPU 1, GPU 1; the whole Ray cluster has CPU 2, GPU 0" in failed.error


def test_a_jobs_request_comes_from_the_settings_or_its_device(tmp_path):
    from server.jobs.ray_backend import RayWorker, Request
    from server.jobs.store import NewJob, SQLiteJobStore

    store = SQLiteJobStore(tmp_path / "jobs.db")
    worker = RayWorker(store, tmp_path, lambda job, package: "", connect=lambda: None)
    job = store.create(NewJob(owner="alice", dataset="upload", dataset_path=str(tmp_path),
                              config={"device": "cuda:0"}, total=10))
    assert worker.request(job) == Request(num_cpus=1, num_gpus=1)
    assert worker.request(dataclasses.replace(job, config={"device": "auto"})) == Request(1, 0)
    worker.num_cpus, worker.num_gpus = 4, 0.5
    assert worker.request(job) == Request(num_cpus=4, num_gpus=0.5)
    store.close()


def test_the_ray_backends_need_a_cluster_address(tmp_path):
    from server.config import Settings

    for backend in ("job_backend", "render_backend"):
        with pytest.raises(ValueError, match="needs cluster_address"):
            Settings(data_dir=tmp_path, **{backend: "ray"})
    assert Settings(data_dir=tmp_path).cluster_storage_dir == tmp_path


def test_a_restarted_server_resumes_the_job_from_its_checkpoint(ray_head, tmp_path,
                                                                 capture_dir):
    data_dir = tmp_path / "data"
    with _serve(data_dir, "ray", ray_head) as first:
        _tune(first, capture_dir)
        token = first.issue("alice", ("train",))
        job = _client(first, token).post(
            "/v1/jobs", json={"dataset": "take", "config": KILLABLE}).json()
        checkpointed = _first_checkpoint(first.ctx.jobs, job["id"])
        pid = _pid(first.ctx.jobs, job["id"])
    wait_for(lambda: not _alive(pid), 30, what="the first server's actor to end")
    with _serve(data_dir, "ray", ray_head) as second:
        _tune(second, capture_dir)
        events = _sse(_client(second, token), job["id"])
        assert _states(events) == ["queued", "running", "queued", "running", "succeeded"]
        requeue = [e["data"] for e in events if e["event"] == "state"][2]
        assert requeue["reason"] == "the server stopped"
        resumed = next(e["data"] for e in events if e["event"] == "resumed")
        assert resumed["iteration"] >= checkpointed


def test_serve_cluster_joins_the_head_and_a_crashed_gateways_job_resumes(ray_head, tmp_path,
                                                                      capture_dir):
    """``telesplat serve --cluster ADDRESS`` in a process of its own (token auth as Ray 2.60
    sets it up by default) runs a job on the cluster; killed with SIGKILL mid-job, its actor
    ends with it, and the next server resumes the job from its checkpoint."""
    data_dir = tmp_path / "data"
    shutil.copytree(capture_dir, data_dir / "datasets" / "take")
    env = {**ray_head.env, "TELESPLAT_WARMUP": "false", "TELESPLAT_STARTUP_ROOM": "false",
           "TELESPLAT_DEFAULT_WIDTH": "64", "TELESPLAT_DEFAULT_HEIGHT": "64",
           # the render actors take little of the test cluster: the job needs one CPU
           "TELESPLAT_RENDER_ACTORS": "1", "TELESPLAT_RENDER_ACTOR_NUM_CPUS": "0.5",
           "TELESPLAT_JOB_THREADS": "1"}
    cmd = [sys.executable, "-m", "server", "--cluster", ray_head.address, "--port", "0",
           "--data-dir", str(data_dir), "--demo-avatar", "synthetic"]
    proc = subprocess.Popen(cmd, env=env, cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    try:
        banner = wait_for(lambda: next((line for line in lines if "serving at" in line),
                                       None) or (proc.poll() is not None and "exited"),
                          180, what="the server's banner")
        assert banner != "exited", "".join(lines)
        url, _, token = banner.split("serving at ", 1)[1].strip().partition("/#token=")
        with httpx.Client(base_url=url, timeout=30,
                          headers={"Authorization": f"Bearer {token}"}) as client:
            job = client.post("/v1/jobs", json={"dataset": "take", "config": LONG}).json()
            checkpoints = data_dir / "jobs" / job["id"] / "out" / "checkpoints"
            wait_for(lambda: any(checkpoints.glob("iter_*.pt")), 180,
                     what="the job's first checkpoint")
            log = client.get(f"/v1/jobs/{job['id']}/logs").text
        assert "on Ray" in log and "Ray worker process" in log
        actor_pid = int(log.split("Ray worker process ", 1)[1].split()[0])
        proc.kill()  # a crash: no clean stop, no checkpoint on the way out
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(30)
        reader.join(10)
    wait_for(lambda: not _alive(actor_pid), 60, what="the dead gateway's actor to end")
    with _serve(data_dir, "ray", ray_head) as second:
        jobs = second.ctx.jobs
        resumed = wait_for(lambda: next((e.data for e in jobs.store.events(job["id"])
                                         if e.type == "resumed"), None), 180,
                           what="the job to resume on the next server")
        requeue = [e.data for e in jobs.store.events(job["id"])
                   if e.type == "state" and e.data["state"] == "queued"][-1]
        assert requeue["reason"] == "the server restarted"
        assert resumed["iteration"] == requeue["attempt_end"]["resume_iteration"] >= 10
        jobs.cancel(job["id"])
        wait_for(lambda: jobs.store.get(job["id"]).state == "cancelled", 60, what="the cancel")
