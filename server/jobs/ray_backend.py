"""Training jobs on a Ray cluster (``job_backend = "ray"``).

The local :class:`~server.jobs.worker.Worker` does everything around a job's run: claiming,
cancels, retries from the latest checkpoint, restarts, registering the package. Here only the
run itself moves: instead of a ``python -m server.jobs.run`` process, each attempt is a Ray
actor (:class:`JobActor`, one worker process of its own, asking ``num_cpus`` / ``num_gpus``)
that trains with the same :func:`server.jobs.run.train`. The job store stays on the server,
the source of truth: the actor buffers the trainer's events and the server drains them into
the store (so progress, logs and SSE events are those of the local backend). Datasets,
checkpoints, the log and the finished package are files under ``cluster_storage``, a path
every node mounts at the same place.

:class:`RayRun` gives the actor the face of a ``subprocess.Popen`` (poll, wait, kill, SIGTERM
as "checkpoint and stop"), so the worker's loop runs Ray attempts unchanged. A job starts when
the cluster has room for its request (``ray.available_resources``), up to
``max_concurrent``; the others stay queued in the store. The actors are not detached: a server
that dies takes its actors with it, and the next server resumes their jobs from their last
checkpoints (:meth:`Worker.recover`), killing a straggler of the old server first (actors are
named after their job).
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from .run import EXIT_FAILED, _limit_threads, train
from .store import Job, JobStore
from .worker import LOG_FILE, Register, Worker, WorkerConfig, _Run

__all__ = ["JobActor", "RayRun", "RayWorker", "Request"]

log = logging.getLogger(__name__)

ACTOR_PREFIX = "telesplat-job-"
ACTOR_CONCURRENCY = 4     # run() plus the server's events()/where()/interrupt() calls
DRAIN_TIMEOUT_S = 30.0    # the last events of an attempt that returned
EVICT_TIMEOUT_S = 30.0    # a straggler actor of a dead server, until its name is free
DIED_EXIT = -signal.SIGKILL  # what poll() returns when the actor's process died
ROOM_WARN_S = 30.0        # at most one "cluster unreachable" warning per this many seconds
_EPS = 1e-6


@dataclass(frozen=True)
class Request:
    """What one job asks the cluster for."""

    num_cpus: float
    num_gpus: float


# -- the actor (runs on a cluster node) -------------------------------------------------------

class _BufferStore:
    """The store as :func:`train` sees it inside the actor: the job as submitted, cancel
    from the server, events into a buffer the server drains."""

    def __init__(self, actor: JobActor) -> None:
        self.actor = actor
        self.error: str | None = None

    def get(self, job_id: str) -> Job:
        return replace(self.actor.job, cancel_requested=self.actor.cancel_requested)

    def report(self, job_id: str, event: dict[str, Any]) -> int:
        return self.actor.add_event(event)

    def set_error(self, job_id: str, error: str) -> None:
        self.error = error


class JobActor:
    """One attempt of one job, in a Ray worker process of its own. The server calls
    ``run`` once, then ``events`` repeatedly (threaded actor: they overlap)."""

    def __init__(self, job: Job, job_dir: str, body_models: str | None, threads: int,
                 nice: int) -> None:
        if nice:
            os.nice(nice)
        _limit_threads(threads)
        self.job = job
        self.job_dir = Path(job_dir)
        self.body_models = body_models
        self.cancel_requested = False
        self._interrupt = False
        self._events: list[tuple[int, dict[str, Any]]] = []
        self._seq = 0
        self._lock = threading.Lock()
        # The job's log is a file on the shared storage, as the local backend's.
        handler = logging.FileHandler(self.job_dir / LOG_FILE)
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: "
                                               "%(message)s"))
        for name in ("server.jobs", "avatar_core"):
            logger = logging.getLogger(name)
            logger.addHandler(handler)
            logger.setLevel(logging.INFO)
        log.info("job %s: Ray worker process %d on node %s", job.id, os.getpid(),
                 _node_ip())

    def where(self) -> dict[str, Any]:
        return {"pid": os.getpid(), "node": _node_ip()}

    def add_event(self, event: dict[str, Any]) -> int:
        with self._lock:
            self._seq += 1
            self._events.append((self._seq, event))
            return self._seq

    def events(self, acked: int) -> list[tuple[int, dict[str, Any]]]:
        """The events after ``acked``; those up to it are dropped (the server has them)."""
        with self._lock:
            self._events = [(seq, e) for seq, e in self._events if seq > acked]
            return list(self._events)

    def cancel(self) -> None:
        self.cancel_requested = True  # the trainer sees it at its next progress event

    def interrupt(self) -> None:
        self._interrupt = True  # checkpoint at the next progress event, then return

    def run(self) -> dict[str, Any]:
        store = _BufferStore(self)
        try:
            rc = train(store, self.job.id, self.job_dir, self.body_models,  # type: ignore[arg-type]
                       interrupted=lambda: self._interrupt)
        except Exception as exc:  # the reason to the store, the traceback to the log
            log.exception("job %s failed", self.job.id)
            reason = f"{type(exc).__name__}: {exc}".strip()[:2000]
            self.add_event({"type": "error", "message": reason})
            return {"rc": EXIT_FAILED, "error": reason}
        return {"rc": rc, "error": store.error}


def _node_ip() -> str:
    import ray

    return ray.util.get_node_ip_address()


# -- the server's side --------------------------------------------------------------------------

class RayRun:
    """A running :class:`JobActor` with the face of ``subprocess.Popen``; ``poll`` also
    drains its events into the store."""

    def __init__(self, actor: Any, job_id: str, store: JobStore, request: Request) -> None:
        import ray

        self._ray = ray
        self.actor = actor
        self.job_id = job_id
        self.store = store
        self.request = request
        self.returncode: int | None = None
        self.died: str | None = None  # why the actor's process is gone, when it died
        self._run_ref = actor.run.remote()
        self._where_ref = actor.where.remote()
        self._where: dict[str, Any] | None = None
        self._events_ref: Any = None
        self._acked = 0

    @property
    def started(self) -> bool:
        """Whether the actor runs (placed on a node, its process up)."""
        if self._where is None and self._ray.wait([self._where_ref], timeout=0)[0]:
            try:
                self._where = self._ray.get(self._where_ref)
            except self._ray.exceptions.RayError:
                self._where = {"pid": None, "node": None}
        return self._where is not None

    @property
    def pid(self) -> int | None:
        """The actor's process id (on its node) once it runs."""
        return self._where["pid"] if self.started and self._where else None

    def poll(self) -> int | None:
        if self.returncode is not None:
            return self.returncode
        self._drain(timeout=0)
        if not self._ray.wait([self._run_ref], timeout=0)[0]:
            return None
        try:
            result = self._ray.get(self._run_ref)
        except self._ray.exceptions.RayError as exc:  # the process died (or was killed)
            self.died = _died_reason(exc)
            self.returncode = DIED_EXIT
            return self.returncode
        for _ in range(3):  # the actor lives until killed: collect what it reported last
            if not self._drain(timeout=DRAIN_TIMEOUT_S):
                break
        if result.get("error"):
            self.store.set_error(self.job_id, result["error"])
        self.kill()  # done: free its process and resources
        self.returncode = int(result["rc"])
        return self.returncode

    def _drain(self, timeout: float) -> int:
        """Move the actor's new events into the store; how many."""
        if self._events_ref is None:
            self._events_ref = self.actor.events.remote(self._acked)
        if not self._ray.wait([self._events_ref], timeout=timeout)[0]:
            return 0
        ref, self._events_ref = self._events_ref, None
        try:
            batch = self._ray.get(ref)
        except self._ray.exceptions.RayError:
            return 0  # the actor is gone: its run's result says how
        moved = 0
        for seq, event in batch:
            if seq > self._acked:
                self.store.report(self.job_id, event)
                self._acked = seq
                moved += 1
        return moved

    def request_cancel(self) -> None:
        self.actor.cancel.remote()

    def send_signal(self, sig: int) -> None:
        if sig == signal.SIGTERM:  # as the local process: checkpoint, then stop
            self.actor.interrupt.remote()
        else:
            self.kill()

    def kill(self) -> None:
        self._ray.kill(self.actor, no_restart=True)

    def wait(self, timeout: float | None = None) -> int:
        deadline = None if timeout is None else time.monotonic() + timeout
        while (rc := self.poll()) is None:
            if deadline is not None and time.monotonic() > deadline:
                raise subprocess.TimeoutExpired(f"Ray job actor {self.job_id}", timeout or 0)
            time.sleep(0.05)
        return rc


def _fits(need: Request, resources: dict[str, float]) -> bool:
    return (need.num_cpus <= resources.get("CPU", 0) + _EPS
            and need.num_gpus <= resources.get("GPU", 0) + _EPS)


def _died_reason(exc: Exception) -> str:
    first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return f"the Ray worker process died ({type(exc).__name__}: {first[:300]})"


class RayWorker(Worker):
    """The job worker with each attempt a :class:`JobActor` on the cluster.

    ``connect``: joins the cluster (server.cluster.connect); ``num_cpus`` / ``num_gpus``:
    each job's request (None: ``config.threads`` CPUs; 1 GPU when the job's config asks
    for a cuda device, else 0)."""

    def __init__(self, store: JobStore, jobs_dir: str | Path, register: Register,
                 config: WorkerConfig | None = None, *, connect: Callable[[], None],
                 num_cpus: float | None = None, num_gpus: float | None = None) -> None:
        super().__init__(store, jobs_dir, register, config)
        self._connect = connect
        self.num_cpus = num_cpus
        self.num_gpus = num_gpus
        self._actor_class: Any = None
        self._warned = -ROOM_WARN_S

    def start(self) -> None:
        if self._thread is None:
            self._connect()
        super().start()

    def request(self, job: Job) -> Request:
        device = str(job.config.get("device", "auto"))
        gpus = self.num_gpus if self.num_gpus is not None else (
            1.0 if device.startswith("cuda") else 0.0)
        cpus = self.num_cpus if self.num_cpus is not None else float(self.config.threads)
        return Request(num_cpus=cpus, num_gpus=gpus)

    def _has_room(self) -> bool:
        try:
            return self._room_for_next()
        except Exception as exc:  # the cluster unreachable: jobs wait queued; log it rarely
            now = time.monotonic()
            if now - self._warned > ROOM_WARN_S:
                self._warned = now
                log.warning("cannot ask the Ray cluster for room (jobs stay queued): %s", exc)
            return False

    def _room_for_next(self) -> bool:
        import ray

        queued = self.store.list(state="queued", limit=1_000_000)  # bounded by the quotas
        if not queued:
            return False
        need = self.request(queued[-1])  # the oldest: the one claim_next takes
        total = ray.cluster_resources()
        if not _fits(need, total):
            return True  # never fits: _launch fails it with the reason
        with self._lock:
            runs = [r.process for r in self._runs.values() if isinstance(r.process, RayRun)]
        # What this worker's own actors hold is known exactly; the cluster's view of what is
        # free (other users: render actors) lags an actor's start a little.
        mine = {key: sum(getattr(r.request, f"num_{key.lower()}s") for r in runs)
                for key in ("CPU", "GPU")}
        free = dict(ray.available_resources())
        for run in runs:
            if not run.started:
                free["CPU"] = free.get("CPU", 0) - run.request.num_cpus
                free["GPU"] = free.get("GPU", 0) - run.request.num_gpus
        room = {key: min(free.get(key, 0), total.get(key, 0) - mine[key])
                for key in ("CPU", "GPU")}
        return _fits(need, room)

    def _ended(self, run: _Run, rc: int) -> tuple[str, int | None]:
        died = getattr(run.process, "died", None)
        return (died, None) if died else super()._ended(run, rc)

    def _check_cancel(self, run: _Run) -> None:
        if run.cancel_seen is None and isinstance(run.process, RayRun):
            try:
                if self.store.get(run.job_id).cancel_requested:
                    run.process.request_cancel()  # the actor's trainer stops at its next event
            except Exception:  # the base check below still kills it after the grace
                log.exception("job %s: forwarding the cancel failed", run.job_id)
        super()._check_cancel(run)

    def _launch(self, job: Job) -> None:
        import ray

        folder = self.job_dir(job.id)
        folder.mkdir(parents=True, exist_ok=True)
        need = self.request(job)
        total = ray.cluster_resources()
        if not _fits(need, total):
            self.store.transition(job.id, "failed", error=(
                f"the job asks for CPU {need.num_cpus:g}, GPU {need.num_gpus:g}; the whole "
                f"Ray cluster has CPU {total.get('CPU', 0):g}, GPU {total.get('GPU', 0):g} "
                "(settings ray_job_num_cpus, ray_job_num_gpus)"))
            return
        logf = open(folder / LOG_FILE, "ab")  # noqa: SIM115 - owned by the _Run
        logf.write(f"--- attempt {job.attempts} at {time.strftime('%Y-%m-%d %H:%M:%S')} "
                   f"on Ray ---\n".encode())
        logf.flush()
        try:
            name = ACTOR_PREFIX + job.id
            self._evict(name)
            actor = self._actor().options(
                name=name, num_cpus=need.num_cpus, num_gpus=need.num_gpus, max_restarts=0,
                max_concurrency=ACTOR_CONCURRENCY).remote(
                    job, str(folder), self.config.body_models, self.config.threads,
                    self.config.nice)
            process = RayRun(actor, job.id, self.store, need)
        except Exception as exc:  # the cluster refused: the job cannot run
            logf.close()
            log.exception("job %s: starting its Ray actor failed", job.id)
            self.store.transition(job.id, "failed",
                                  error=f"could not start the job on the Ray cluster: {exc}")
            return
        log.info("job %s: Ray actor %s started (attempt %d, %g CPUs, %g GPUs)", job.id, name,
                 job.attempts, need.num_cpus, need.num_gpus)
        with self._lock:
            self._runs[job.id] = _Run(job.id, process, logf)  # type: ignore[arg-type]

    def _actor(self) -> Any:
        if self._actor_class is None:
            import ray

            self._actor_class = ray.remote(JobActor)
        return self._actor_class

    @staticmethod
    def _evict(name: str) -> None:
        """Kill an actor of this job left by a server that died (its driver's actors are
        being cleaned up, but may still train): two runs must never write one job."""
        import ray

        try:
            stale = ray.get_actor(name)
        except ValueError:
            return
        log.warning("killing %s, left running by an earlier server", name)
        ray.kill(stale, no_restart=True)
        deadline = time.monotonic() + EVICT_TIMEOUT_S
        while time.monotonic() < deadline:
            try:
                ray.get_actor(name)
            except ValueError:
                return
            time.sleep(0.1)
        raise RuntimeError(f"{name} of an earlier server did not stop in {EVICT_TIMEOUT_S} s")
