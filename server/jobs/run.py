"""The training process of one job: ``python -m server.jobs.run --db DB --job-dir DIR JOB_ID``.

Started by the worker with its thread limits in the environment (``OMP_NUM_THREADS``,
``NUMBA_NUM_THREADS``, ... must be set before torch and numba load). It trains fresh, or
resumes from the last checkpoint in ``DIR/out`` when there is one, and writes every trainer
event into the store. Cancel is checked at each progress event; SIGTERM (the server stopping)
makes it checkpoint at the next one and exit. Its stdout/stderr are the job's log file.

Exit codes: 0 trained (the package is ``DIR/out/avatar``), 1 failed (the reason is in the
store), 3 cancelled, 4 interrupted with a checkpoint saved.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..stream.scheduler import limit_threads
from .store import JobStore, SQLiteJobStore

EXIT_OK, EXIT_FAILED, EXIT_CANCELLED, EXIT_INTERRUPTED = 0, 1, 3, 4
OUT_DIR = "out"

log = logging.getLogger("server.jobs.run")


class _Cancelled(Exception):
    pass


class _Interrupted(Exception):
    pass


def _limit_threads(threads: int) -> None:
    import torch

    limit_threads(threads)  # torch and numba, as the render workers
    try:
        torch.set_num_interop_threads(1)
    except RuntimeError:  # already set (only possible once per process)
        pass


def _public(event: dict[str, Any]) -> dict[str, Any]:
    """The event as clients see it: no server paths."""
    out = dict(event)
    path = out.pop("path", None)
    if path is not None and out.get("type") == "checkpoint":
        out["checkpoint"] = Path(path).name
    return out


def _watch_parent(pid: int, every_s: float = 0.25) -> None:
    """Exit when the server that started this process has died (we are re-parented): the
    next server resumes the job from its checkpoint, and two processes must never train
    one job. Checkpoints are written to a temporary name and renamed, so exiting mid-write
    leaves the last complete one."""

    def watch() -> None:
        while True:
            if os.getppid() != pid:
                os._exit(EXIT_INTERRUPTED)
            time.sleep(every_s)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def train(store: JobStore, job_id: str, job_dir: Path, body_models: str | None, *,
          interrupted: Callable[[], bool] | None = None) -> int:
    """Train (or resume) the job; its exit code. ``interrupted``: polled at each progress
    event instead of a SIGTERM handler (a thread that is not the main one, e.g. a Ray
    actor's, cannot install one)."""
    from avatar_core.train.checkpoint import latest_checkpoint
    from avatar_core.train.config import config_from_dict
    from avatar_core.train.trainer import Trainer

    job = store.get(job_id)
    out = job_dir / OUT_DIR
    stop = {"interrupt": False, "training": False}

    def on_term(signum: int, frame: Any) -> None:
        if not stop["training"]:  # still setting up: nothing to checkpoint
            os._exit(EXIT_INTERRUPTED)
        stop["interrupt"] = True

    if interrupted is None:
        signal.signal(signal.SIGTERM, on_term)

    def progress(event: dict[str, Any]) -> None:
        store.report(job_id, _public(event))
        if event.get("type") == "done":
            return
        if store.get(job_id).cancel_requested:
            raise _Cancelled
        if stop["interrupt"] or (interrupted is not None and interrupted()):
            raise _Interrupted

    if job.kind == "enroll":  # nothing to checkpoint: SIGTERM exits, a retry starts over
        return _enroll(store, job, job_dir, body_models, interrupted)
    if latest_checkpoint(out) is not None:
        trainer = Trainer.resume(out, job.dataset_path, body_model=body_models,
                                 progress=progress)
        log.info("resumed job %s at iteration %d", job_id, trainer.iteration)
        store.report(job_id, {"type": "resumed", "iteration": trainer.iteration,
                              "total": trainer.config.iterations})
    else:
        config = config_from_dict(job.config)
        trainer = Trainer(job.dataset_path, config, out, body_model=body_models,
                          progress=progress)
        log.info("training job %s: %d iterations", job_id, config.iterations)
    stop["training"] = True  # from here SIGTERM means: checkpoint at the next event
    try:
        package = trainer.train()
    except _Cancelled:
        log.info("job %s cancelled at iteration %d", job_id, trainer.iteration)
        return EXIT_CANCELLED
    except _Interrupted:
        path = trainer.save_checkpoint()
        log.info("job %s interrupted at iteration %d; checkpoint %s", job_id,
                 trainer.iteration, path.name)
        return EXIT_INTERRUPTED
    if package is None:  # pragma: no cover - train() without stop_at always finishes
        store.set_error(job_id, "training stopped before its last iteration")
        return EXIT_FAILED
    log.info("job %s trained: %s", job_id, package)
    return EXIT_OK


def _enroll(store: JobStore, job: Any, job_dir: Path, body_models: str | None,
            interrupted: Callable[[], bool] | None) -> int:
    """An enrollment job (server/jobs/enrollment.py): its exit code."""
    from .enrollment import run_enrollment

    def check() -> None:
        if store.get(job.id).cancel_requested:
            raise _Cancelled
        if interrupted is not None and interrupted():
            raise _Interrupted

    log.info("enrolling job %s", job.id)
    try:
        done = run_enrollment(job, job_dir, job_dir / OUT_DIR,
                              report=lambda event: store.report(job.id, event), check=check,
                              set_error=lambda error: store.set_error(job.id, error[:2000]),
                              body_models=body_models)
    except _Cancelled:
        log.info("job %s cancelled", job.id)
        return EXIT_CANCELLED
    except _Interrupted:
        log.info("job %s interrupted; it starts over when it runs again", job.id)
        return EXIT_INTERRUPTED
    return EXIT_OK if done else EXIT_FAILED


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m server.jobs.run")
    parser.add_argument("job_id")
    parser.add_argument("--db", type=Path, required=True)
    parser.add_argument("--job-dir", type=Path, required=True)
    parser.add_argument("--body-models", default=None,
                        help="the server setting body_models (resolve_body_models' setting)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--nice", type=int, default=0)
    parser.add_argument("--parent-pid", type=int, default=None,
                        help="exit when this process (the server) is gone")
    args = parser.parse_args(argv)
    if args.nice:
        os.nice(args.nice)
    if args.parent_pid is not None:
        _watch_parent(args.parent_pid)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    _limit_threads(args.threads)
    store = SQLiteJobStore(args.db)
    try:
        return train(store, args.job_id, args.job_dir, args.body_models)
    except Exception as exc:  # the reason goes to the store; the traceback to the log
        log.exception("job %s failed", args.job_id)
        reason = f"{type(exc).__name__}: {exc}".strip()
        try:
            store.set_error(args.job_id, reason[:2000])
            store.report(args.job_id, {"type": "error", "message": reason[:2000]})
        except Exception:  # the store itself may be what failed
            log.exception("could not record the failure")
        return EXIT_FAILED
    finally:
        store.close()


if __name__ == "__main__":
    os.umask(0o077)  # job files hold users' data
    sys.exit(main())
