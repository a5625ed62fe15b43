"""The trained demo avatar, built in the background while the server already runs.

With ``demo_avatar = "trained"`` and no trained demo in the demo cache yet, the server starts
at once with the synthetic avatar standing in as ``demo`` (server/registry.py) and
:class:`DemoBuild` builds the trained one behind it:

1. **capture**: the synthetic studio films the demo's dataset into the demo cache, in a
   process of its own (``python -m avatar_core.demo capture``, niced like a training job, its
   thread pools passive), whose JSON progress lines are read here; a dataset already filmed
   (by ``telesplat demo-avatar`` or an earlier start) is kept;
2. **train**: a job of the server's own job service (owner ``public``, dataset label
   ``demo:trained``; quotas do not apply), so it runs like any training job (its own process,
   niced, thread-limited, checkpointed, resumed after a restart, its progress events at
   ``/v1/jobs/{id}/events`` for admins); when it succeeds the job service's register step
   hands the package to :meth:`AvatarRegistry.register_trained_demo`, which installs it in
   the demo cache and registers it as ``demo`` in place of the stand-in.

``GET /v1/demo`` (no auth, like /v1/health) reports :meth:`DemoBuild.status`; the page shows
it as a banner. When the job succeeds, :attr:`DemoBuild.on_replaced` (server/app.py) reloads
the trained demo into every live room and plain session showing the stand-in
(server/rooms/reload.py: connections kept, an ``avatar`` message, then frames of the trained
one), and only then is the state ``ready``.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import threading
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from avatar_core.threads import passive_waiting

from ..auth import PUBLIC_OWNER

if TYPE_CHECKING:
    from ..registry import AvatarRecord, AvatarRegistry
    from .service import JobService
    from .store import Job

log = logging.getLogger("telesplat.demo_build")

DEMO_DATASET = "demo:trained"  # the job's dataset label (users' jobs: upload, dataset:NAME)
DEMO_JOB_NAME = "Demo avatar (trained)"
CAPTURE_SHARE = 0.2  # of the overall progress: the capture (the training the rest)
POLL_S = 0.5
CAPTURE_LOG = "capture-log.txt"
_ACTIVE = ("queued", "running")
_REPO_ROOT = Path(__file__).resolve().parents[2]


class DemoBuild:
    """One background build of the trained demo (a thread); :meth:`status` at any time."""

    def __init__(self, settings: Any, registry: AvatarRegistry) -> None:
        self.settings = settings
        self.registry = registry
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._process: subprocess.Popen[str] | None = None
        # called (on this build's thread) once the trained demo is registered: the server
        # reloads it into the live rooms and sessions showing the stand-in
        self.on_replaced: Callable[[AvatarRecord | None], None] | None = None
        self._stand_in: AvatarRecord | None = None  # the record the trained one replaces
        self._status: dict[str, Any] = {"state": "off", "stage": None, "progress": 0.0,
                                        "stage_progress": 0.0, "job_id": None, "error": None}

    # -- status ----------------------------------------------------------------------------

    def status(self) -> dict[str, Any]:
        """state: off (no build configured), ready, building or failed; stage: capture or
        train while building; progress: the whole build's, in [0, 1]."""
        with self._lock:
            out = dict(self._status)
        try:
            out["trained"] = bool(self.registry.get("demo").metadata.get("trained"))
        except KeyError:
            out["trained"] = False
        return out

    def _set(self, **changes: Any) -> None:
        with self._lock:
            self._status.update(changes)
            stage, part = self._status["stage"], float(self._status["stage_progress"])
            if self._status["state"] == "ready":
                self._status["progress"] = 1.0
            elif stage == "capture":
                self._status["progress"] = CAPTURE_SHARE * part
            elif stage == "train":
                self._status["progress"] = CAPTURE_SHARE + (1 - CAPTURE_SHARE) * part

    # -- life cycle ------------------------------------------------------------------------

    def start(self, jobs: JobService | None) -> None:
        """Start building when the demo is the stand-in (``demo_avatar = "trained"`` with no
        trained demo cached); else the status is ready (trained) or off."""
        try:
            record = self.registry.get("demo")
        except KeyError:
            return
        if self.settings.demo_avatar != "trained":
            return
        if record.metadata.get("trained"):
            self._set(state="ready")
            return
        if jobs is None:
            self._set(state="failed", error="no job service to train it")
            return
        self._stand_in = record
        self._set(state="building", stage="capture", stage_progress=0.0)
        self._thread = threading.Thread(target=self._run, args=(jobs,), daemon=True,
                                        name="telesplat-demo-build")
        self._thread.start()

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def stop(self) -> None:
        """Stop following (the job itself is checkpointed and re-queued by the job service's
        own stop; the next start resumes it); a capture in progress is ended."""
        self._stop.set()
        process = self._process
        if process is not None and process.poll() is None:
            process.terminate()
            try:
                process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
        if self._thread is not None:
            self._thread.join(timeout=15)
            self._thread = None

    # -- the build -------------------------------------------------------------------------

    def _run(self, jobs: JobService) -> None:
        from avatar_core.studio_entry import demo_build_plan

        try:
            plan = demo_build_plan(self.settings.demo_cache_dir, self.settings.demo_build_recipe)
            job = _find_job(jobs)
            if job is None:
                if not (plan.dataset / "dataset.json").is_file():
                    self._capture(plan.capture_command, plan.root)
                    if self._stop.is_set():
                        return
                self._set(stage="train", stage_progress=0.0)
                job = jobs.submit_prepared(PUBLIC_OWNER, DEMO_DATASET, plan.dataset,
                                           plan.config, DEMO_JOB_NAME)
                log.info("trained demo avatar: training job %s queued", job.id)
            self._follow(jobs, job.id)
        except Exception as exc:  # the stand-in stays; the page says why
            log.exception("building the trained demo avatar failed")
            self._set(state="failed", error=f"{type(exc).__name__}: {exc}"[:500])

    def _capture(self, command: list[str], root: Path) -> None:
        root.mkdir(parents=True, exist_ok=True)
        command, env = capture_process(self.settings, command)
        log.info("trained demo avatar: filming its dataset in %s", root)
        with open(root / CAPTURE_LOG, "ab") as logf:
            self._process = process = subprocess.Popen(  # process group: as a training job's
                command, stdout=subprocess.PIPE, stderr=logf, stdin=subprocess.DEVNULL,
                env=env, text=True, bufsize=1, process_group=0)
            assert process.stdout is not None
            for line in process.stdout:  # ends when the process does (or is terminated)
                try:
                    event = json.loads(line)
                except ValueError:
                    continue
                if event.get("stage") == "capture" and event.get("total"):
                    self._set(stage_progress=min(1.0, event["done"] / event["total"]))
            rc = process.wait()
        self._process = None
        if rc != 0 and not self._stop.is_set():
            raise RuntimeError(f"filming the demo's dataset failed (exit {rc}; see "
                               f"{CAPTURE_LOG} in the demo cache)")

    def _follow(self, jobs: JobService, job_id: str) -> None:
        """Mirror the job's progress until it ends (or the server stops)."""
        self._set(stage="train", job_id=job_id)
        while not self._stop.is_set():
            job = jobs.store.get(job_id)
            self._set(stage_progress=job.progress)
            if job.state == "succeeded":
                if self.on_replaced is not None:  # live rooms first: "ready" means shown
                    self.on_replaced(self._stand_in)
                self._set(state="ready", stage=None, stage_progress=1.0)
                log.info("trained demo avatar ready (job %s)", job_id)
                return
            if job.state in ("failed", "cancelled"):
                self._set(state="failed", error=job.error or job.state)
                return
            self._stop.wait(POLL_S)


def capture_process(settings: Any, command: list[str]) -> tuple[list[str], dict[str, str]]:
    """The capture's command line and environment: niced and thread-limited like a training
    job (``job_nice``, ``job_threads``), passive thread pools, this checkout's engine."""
    env = passive_waiting(dict(os.environ))
    path = env.get("PYTHONPATH")  # this checkout's engine, as the training processes get
    env["PYTHONPATH"] = str(_REPO_ROOT) + (os.pathsep + path if path else "")
    threads = str(getattr(settings, "job_threads", 1))
    for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
        env[name] = threads
    nice = int(getattr(settings, "job_nice", 10))
    if nice and shutil.which("nice"):
        command = ["nice", "-n", str(nice), *command]
    return command, env


def _find_job(jobs: JobService) -> Job | None:
    """A demo job left queued or running by an earlier start (it resumes from its
    checkpoint): followed rather than started again."""
    for state in _ACTIVE:
        for job in jobs.store.list(state=state, limit=1000):
            if job.dataset == DEMO_DATASET and job.owner == PUBLIC_OWNER:
                return job
    return None


def register_job_package(settings: Any, registry: AvatarRegistry, job: Job,
                         package: Path) -> str | None:
    """The job service's register step for the demo's job: the avatar id, or None when
    ``job`` is not the demo's (an ordinary job is registered as usual)."""
    if job.dataset != DEMO_DATASET or job.owner != PUBLIC_OWNER:
        return None
    if settings.demo_avatar != "trained":  # the setting changed since: cached, not swapped in
        from avatar_core.studio_entry import demo_build_plan, install_trained_demo

        install_trained_demo(demo_build_plan(settings.demo_cache_dir).root, package)
        return None
    return registry.register_trained_demo(package, settings.demo_cache_dir, job.id).id


__all__ = ["DEMO_DATASET", "DemoBuild", "capture_process", "register_job_package"]
