"""The worker: runs queued jobs, each in a training process of its own (``server.jobs.run``).

A thread in the server process claims queued jobs (``max_concurrent`` at a time), starts
``python -m server.jobs.run`` for each with its thread limits and priority, watches for
cancels (the process checks at every progress event and is killed after a grace period) and,
when a process ends, finishes its job: on success the avatar package is registered through
``register`` (the registry, with the job's owner) before the job is marked succeeded, so its
avatar id is servable at once.

Faults: a process that dies abnormally (a signal such as the out-of-memory killer's SIGKILL,
or an exit code the training process never uses) ends an attempt, recorded in the job's
``attempt_log`` with the reason; while the job's attempts last it is re-queued to resume from
its latest checkpoint (from the start when there is none), then it fails with the reason. A
process that reports its own error (exit code 1) fails at once: running it again would fail
the same way; ``resume`` after a fix.

Restarts: :meth:`Worker.recover` (run by :meth:`start`) re-queues jobs left ``running`` by a
server that died, to resume from their last checkpoint, and fails those with none. A clean
:meth:`stop` asks each process to checkpoint (SIGTERM), kills it after a grace period, and
re-queues its job. A training process whose server dies exits on its own (it watches its
parent), so two processes never train one job.
"""

from __future__ import annotations

import logging
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX
    fcntl = None  # type: ignore[assignment]

from avatar_core.threads import passive_waiting
from avatar_core.train.checkpoint import CHECKPOINT_DIR, latest_checkpoint

from .run import EXIT_CANCELLED, EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK, OUT_DIR
from .store import InvalidTransition, Job, JobNotFound, JobStore

__all__ = ["LOG_FILE", "UPLOADED_DATASET", "Register", "Worker", "WorkerConfig"]

log = logging.getLogger(__name__)

LOG_FILE = "log.txt"
LOCK_FILE = "worker.lock"
UPLOADED_DATASET = "dataset"  # an uploaded dataset, unpacked: jobs/<id>/dataset
Register = Callable[[Job, Path], str]  # (job, package dir) -> avatar id
_THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                "NUMBA_NUM_THREADS", "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS")
_REPO_ROOT = Path(__file__).resolve().parents[2]


@dataclass(frozen=True)
class WorkerConfig:
    max_concurrent: int = 1      # training processes at once
    threads: int = 1             # torch / numba / BLAS threads per training process
    nice: int = 10               # CPU priority increment of a training process
    body_models: str | None = None  # the server setting body_models (None: resolved by
    #                                  the training process: $TELESPLAT_BODY_MODELS, else the
    #                                  synthetic family for a synthetic dataset)
    max_attempts: int = 3        # runs of one job (restarts and retries after a crash
    #                              included) before it is failed; a resume grants as many more
    poll_s: float = 0.2          # how often processes and cancels are checked
    cancel_grace_s: float = 5.0  # after a cancel, kill the process if still running (at
    #                              once while it has not trained an iteration yet)
    stop_grace_s: float = 10.0   # at stop, time for processes to checkpoint

    def __post_init__(self) -> None:
        if self.max_concurrent < 1 or self.threads < 1 or self.max_attempts < 1:
            raise ValueError("max_concurrent, threads and max_attempts must be >= 1")


@dataclass
class _Run:
    job_id: str
    process: subprocess.Popen[bytes]
    log: IO[bytes]
    cancel_seen: float | None = None
    killed_for_cancel: bool = False
    started: float = field(default_factory=time.monotonic)


class Worker:
    def __init__(self, store: JobStore, jobs_dir: str | Path, register: Register,
                 config: WorkerConfig | None = None) -> None:
        self.store = store
        self.jobs_dir = Path(jobs_dir)
        self.register = register
        self.config = config or WorkerConfig()
        self.db_path = getattr(store, "path", None)  # the training process opens it too
        self._runs: dict[str, _Run] = {}
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock_file: IO[bytes] | None = None

    def job_dir(self, job_id: str) -> Path:
        return self.jobs_dir / job_id

    def running(self) -> list[str]:
        with self._lock:
            return list(self._runs)

    def process_id(self, job_id: str) -> int | None:
        """The pid of the job's training process while this worker runs it."""
        with self._lock:
            run = self._runs.get(job_id)
        return None if run is None else run.process.pid

    def budget(self, job: Job) -> int:
        """The runs the job may have in all."""
        return job.max_attempts or self.config.max_attempts

    def cleanup(self, job_id: str) -> None:
        """Free the disk of a job that succeeded or was cancelled: its checkpoints and its
        uploaded dataset (a failed job keeps both, to be looked at). The log and the
        exported package stay."""
        folder = self.job_dir(job_id)
        for sub in (folder / OUT_DIR / CHECKPOINT_DIR, folder / UPLOADED_DATASET):
            shutil.rmtree(sub, ignore_errors=True)

    # -- life cycle ------------------------------------------------------------------------

    def start(self) -> None:
        if self._thread is not None:
            return
        if not self._take_lock():
            log.warning("another server runs the jobs in %s: this one only accepts "
                        "submissions", self.jobs_dir)
            return
        self.recover()
        self._stopping.clear()
        self._thread = threading.Thread(target=self._loop, name="telesplat-jobs", daemon=True)
        self._thread.start()

    def wake(self) -> None:
        """Look at the queue now (a job was just submitted or cancelled)."""
        self._wake.set()

    def stop(self, grace_s: float | None = None) -> None:
        """Stop taking jobs; ask running processes to checkpoint, kill them after
        ``grace_s`` (default ``config.stop_grace_s``) and re-queue their jobs."""
        self._stopping.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=30)
            self._thread = None
        grace = self.config.stop_grace_s if grace_s is None else grace_s
        with self._lock:
            runs = list(self._runs.values())
        for run in runs:
            if run.process.poll() is None:
                run.process.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + grace
        for run in runs:
            try:
                run.process.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                run.process.kill()
                run.process.wait()
            self._finish(run, run.process.returncode)
        self._release_lock()

    def _take_lock(self) -> bool:
        """One worker per jobs folder (two would resume each other's jobs): an exclusive
        flock, released by the kernel when the server dies."""
        if fcntl is None:  # not POSIX: no lock
            return True
        self.jobs_dir.mkdir(parents=True, exist_ok=True)
        lock = open(self.jobs_dir / LOCK_FILE, "a+b")  # noqa: SIM115 - held until stop()
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            lock.close()
            return False
        self._lock_file = lock
        return True

    def _release_lock(self) -> None:
        if self._lock_file is not None:
            self._lock_file.close()  # closing releases the flock
            self._lock_file = None

    def recover(self) -> None:
        """Jobs left ``running`` by a server that died: that attempt ended; re-queued to
        resume from their last checkpoint (from the start without one) while attempts
        remain, failed with the reason otherwise."""
        with self._lock:
            mine = set(self._runs)
        for job in self.store.list(state="running", limit=1_000_000):
            if job.id in mine:
                continue
            try:
                if job.cancel_requested:
                    self.cleanup(job.id)  # before the state: whoever sees it sees the disk freed
                    self.store.transition(job.id, "cancelled", error="cancelled")
                else:
                    self._retry_or_fail(job, "the server restarted")
            except (InvalidTransition, JobNotFound):  # changed meanwhile: leave it
                continue

    # -- the loop --------------------------------------------------------------------------

    def _loop(self) -> None:
        while not self._stopping.is_set():
            try:
                self._tick()
            except Exception:  # one bad tick must not end the worker
                log.exception("job worker tick failed")
            self._wake.wait(self.config.poll_s)
            self._wake.clear()

    def _tick(self) -> None:
        with self._lock:
            runs = list(self._runs.values())
        for run in runs:
            rc = run.process.poll()
            if rc is not None:
                self._finish(run, rc)
            else:
                self._check_cancel(run)
        while (not self._stopping.is_set() and len(self.running()) < self.config.max_concurrent
               and self._has_room()):
            job = self.store.claim_next()
            if job is None:
                break
            self._launch(job)

    def _has_room(self) -> bool:
        """Whether the next queued job may start now (besides max_concurrent); a cluster
        backend asks its cluster."""
        return True

    def _ended(self, run: _Run, rc: int) -> tuple[str, int | None]:
        """Why an attempt ended abnormally, in words, and the exit status to record."""
        return exit_reason(rc), rc

    def _check_cancel(self, run: _Run) -> None:
        try:
            job = self.store.get(run.job_id)
        except JobNotFound:
            return
        if not job.cancel_requested:
            return
        now = time.monotonic()
        if run.cancel_seen is None:
            run.cancel_seen = now  # the process sees it at its next progress event
        if run.killed_for_cancel:
            return
        if job.iteration == 0 or now - run.cancel_seen > self.config.cancel_grace_s:
            # not training yet (nothing to lose) or not honoured in time
            log.info("job %s: cancelled, killing its process", run.job_id)
            run.killed_for_cancel = True
            run.process.kill()

    def _command(self, job: Job) -> list[str]:
        cmd = [sys.executable, "-m", "server.jobs.run", job.id, "--db", str(self.db_path),
               "--job-dir", str(self.job_dir(job.id)), "--threads", str(self.config.threads),
               "--nice", str(self.config.nice), "--parent-pid", str(os.getpid())]
        if self.config.body_models is not None:
            cmd += ["--body-models", str(self.config.body_models)]
        return cmd

    def _env(self) -> dict[str, str]:
        env = dict(os.environ)
        env.update({name: str(self.config.threads) for name in _THREAD_VARS})
        passive_waiting(env)  # read when torch loads: set before the process starts
        env["PYTHONUNBUFFERED"] = "1"
        path = env.get("PYTHONPATH")
        env["PYTHONPATH"] = str(_REPO_ROOT) + (os.pathsep + path if path else "")
        return env

    def _launch(self, job: Job) -> None:
        folder = self.job_dir(job.id)
        folder.mkdir(parents=True, exist_ok=True)
        logf = open(folder / LOG_FILE, "ab")  # noqa: SIM115 - owned by the _Run
        logf.write(f"--- attempt {job.attempts} at {time.strftime('%Y-%m-%d %H:%M:%S')} "
                   f"---\n".encode())
        logf.flush()
        try:
            # own process group: a Ctrl-C at the server's terminal reaches the server only,
            # which then stops the process cleanly (SIGTERM, checkpoint). The server's
            # session, not one of its own: with Linux's autogroup scheduling a session is
            # one group of CPU share and nice counts only within it, so job_nice makes the
            # training yield to this server's live sessions while the group as a whole keeps
            # its fair share against other programs (docs/benchmarks.md, "First run").
            process = subprocess.Popen(self._command(job), stdout=logf,
                                       stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                       env=self._env(), cwd=folder, process_group=0)
        except OSError as exc:
            logf.close()
            self.store.transition(job.id, "failed",
                                  error=f"could not start the training process: {exc}")
            return
        log.info("job %s: training process %d started (attempt %d)", job.id, process.pid,
                 job.attempts)
        with self._lock:
            self._runs[job.id] = _Run(job.id, process, logf)

    def _finish(self, run: _Run, rc: int) -> None:
        with self._lock:
            if self._runs.pop(run.job_id, None) is None:
                return  # finished already
        run.log.close()
        try:
            job = self.store.get(run.job_id)
        except JobNotFound:
            return
        try:
            self._settle(job, rc, run)
        except InvalidTransition as exc:
            log.warning("job %s: %s", job.id, exc)

    def _settle(self, job: Job, rc: int, run: _Run) -> None:
        """The job's state after its process ended with ``rc``."""
        if rc == EXIT_OK:
            package = self.job_dir(job.id) / OUT_DIR / "avatar"
            try:
                avatar_id = self.register(job, package)
            except Exception as exc:
                log.exception("job %s: registering the avatar failed", job.id)
                self.store.transition(job.id, "failed",
                                      error=f"registering the avatar failed: {exc}")
                return
            self.store.transition(job.id, "succeeded", avatar_id=avatar_id)
            self.cleanup(job.id)
        elif rc == EXIT_CANCELLED or job.cancel_requested or run.killed_for_cancel:
            self.cleanup(job.id)  # before the state: whoever sees it sees the disk freed
            self.store.transition(job.id, "cancelled", error="cancelled")
        elif self._stopping.is_set():
            # a planned stop is no fault of the job: re-queued whatever its attempts, the
            # next start resumes it from its checkpoint
            self._retry_or_fail(job, "the server stopped", rc, always=True)
        elif rc == EXIT_FAILED:  # the trainer's own error (in job.error): it would repeat
            error = job.error or "the training process failed; see the log"
            self.store.transition(job.id, "failed", error=error, attempt_end={
                "attempt": job.attempts, "exit_code": rc, "reason": error[:500]})
        else:  # SIGTERM from someone else (it checkpointed), a kill, a crash: try again
            self._retry_or_fail(job, *self._ended(run, rc))

    def _retry_or_fail(self, job: Job, reason: str, rc: int | None = None, *,
                       always: bool = False) -> None:
        """The attempt ended (``reason``; ``rc``: the exit status when known): back to the
        queue to resume from the latest checkpoint while the job has attempts left (or
        ``always``), failed with the reason otherwise."""
        ckpt = latest_checkpoint(self.job_dir(job.id) / OUT_DIR)
        resume_iteration = 0 if ckpt is None else checkpoint_iteration(ckpt)
        record = {"attempt": job.attempts, "exit_code": rc, "reason": reason,
                  "resume_from": None if ckpt is None else ckpt.name,
                  "resume_iteration": resume_iteration}
        budget = self.budget(job)
        log.warning("job %s: attempt %d of %d ended: %s", job.id, job.attempts, budget, reason)
        if always or job.attempts < budget:
            record["outcome"] = "requeued"
            self.store.transition(job.id, "queued", attempt_end=record,
                                  iteration=resume_iteration, note={
                                      "reason": reason, "resume_from": record["resume_from"]})
            return
        record["outcome"] = "failed"
        where = "" if ckpt is None else f" (a resume goes on from {ckpt.name})"
        self.store.transition(job.id, "failed", attempt_end=record, error=(
            f"attempt {job.attempts} of {budget}: {reason}; no attempts left{where}"))


def exit_reason(rc: int) -> str:
    """How a training process ended, in words (``rc`` as Popen reports it)."""
    if rc == EXIT_INTERRUPTED:
        return "interrupted (SIGTERM); it checkpointed"
    if rc < 0:
        try:
            name = signal.Signals(-rc).name
        except ValueError:
            name = f"signal {-rc}"
        if -rc == signal.SIGKILL:
            return f"killed by {name} (likely out of memory)"
        return f"killed by {name}"
    return f"exited with unexpected code {rc}"


def checkpoint_iteration(path: Path) -> int:
    """The iteration in a checkpoint's name (``iter_000120.pt``: 120)."""
    digits = path.stem.rpartition("_")[2]
    return int(digits) if digits.isdigit() else 0
