"""JobService: the store and the worker together, plus submitting (used by the routes).

Started and stopped with the app (its lifespan). Submissions are validated here, not in the
worker: the dataset is loaded (and so validated) and the config resolved before a job row
exists, so a bad submission creates nothing.
"""

from __future__ import annotations

import re
import shutil
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Any, BinaryIO

from avatar_core.dataset import DatasetError, load_dataset
from avatar_core.train.config import TrainConfig, config_from_dict, config_to_dict, preset
from avatar_core.train.posing import SYNTHETIC_PREFIX

from .archive import ArchiveError, UploadLimits, extract_archive
from .store import Job, JobStore, NewJob, SQLiteJobStore, new_job_id
from .worker import UPLOADED_DATASET, Register, Worker, WorkerConfig

__all__ = ["DATASETS_DIR", "JOBS_DIR", "JobService", "SubmitError", "resolve_config"]

JOBS_DIR, DATASETS_DIR, DB_FILE = "jobs", "datasets", "jobs.db"
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")
MAX_AVATAR_NAME = 128
# Without an explicit checkpoint_interval a job checkpoints at least every tenth of its run.
CHECKPOINT_FRACTION = 10


class SubmitError(ValueError):
    """A submission that is refused; ``status`` is the HTTP status to answer."""

    def __init__(self, message: str, status: int = 400) -> None:
        super().__init__(message)
        self.status = status


def resolve_config(value: Any) -> TrainConfig:
    """A preset name, a TrainConfig dict (optionally with "preset") or None ("default");
    SubmitError (422) naming the bad key otherwise. Without an explicit
    ``checkpoint_interval`` the interval is capped at a tenth of the run."""
    try:
        if value is None:
            config = preset("default")
        elif isinstance(value, str):
            config = preset(value)
        elif isinstance(value, dict):
            config = config_from_dict(value)
        else:
            raise SubmitError("config must be a preset name or an object", 422)
    except ValueError as exc:  # ConfigError names the key
        if isinstance(exc, SubmitError):
            raise
        raise SubmitError(f"bad training config: {exc}", 422) from exc
    explicit = isinstance(value, dict) and "checkpoint_interval" in value
    if not explicit:
        cap = max(1, config.iterations // CHECKPOINT_FRACTION)
        config = replace(config, checkpoint_interval=min(config.checkpoint_interval, cap))
    return config


def _check_avatar_name(name: str | None) -> str | None:
    if name is None or name == "":
        return None
    if len(name) > MAX_AVATAR_NAME or not name.isprintable():
        raise SubmitError(f"name must be at most {MAX_AVATAR_NAME} printable characters")
    return name


def _validated(root: Path, body_model_dir: str | None) -> None:
    try:
        dataset = load_dataset(root)  # shallow validation: files present, headers, parameters
    except DatasetError as exc:
        lines = [str(p) for p in exc.problems[:20]]
        more = len(exc.problems) - len(lines)
        detail = "; ".join(lines) + (f"; and {more} more" if more > 0 else "")
        raise SubmitError(f"the dataset is not valid: {detail}") from exc
    except (OSError, ValueError, KeyError) as exc:
        raise SubmitError(f"the dataset cannot be read: {exc}") from exc
    source = str(dataset.meta.get("body_model", {}).get("source", ""))
    if body_model_dir is None and not source.startswith(SYNTHETIC_PREFIX):
        # the trainer would fail on it (posing.resolve_body): say so now
        raise SubmitError(f"the dataset's parameters come from body model {source!r}, and "
                          "this server has no body-model folder (setting body_model_dir)")


class JobService:
    """Jobs under ``data_dir``: ``jobs/jobs.db``, ``jobs/<id>/``, named datasets in
    ``datasets/<name>/``. ``register(job, package_dir) -> avatar id``."""

    def __init__(self, data_dir: str | Path, register: Register, *,
                 worker: WorkerConfig | None = None, limits: UploadLimits | None = None,
                 store: JobStore | None = None) -> None:
        self.data_dir = Path(data_dir)
        self.jobs_dir = self.data_dir / JOBS_DIR
        self.datasets_dir = self.data_dir / DATASETS_DIR
        self.jobs_dir.mkdir(parents=True, exist_ok=True)
        self.limits = limits or UploadLimits()
        self.store = store or SQLiteJobStore(self.jobs_dir / DB_FILE)
        self.worker = Worker(self.store, self.jobs_dir, register, worker)

    @classmethod
    def from_settings(cls, settings: Any, registry: Any) -> JobService:
        """From the server's Settings and AvatarRegistry. Optional settings (defaults when
        absent): job_max_concurrent, job_threads, job_nice, body_model_dir,
        max_dataset_unpacked_bytes, max_dataset_files."""

        def register(job: Job, package: Path) -> str:
            record = registry.add_package(package, job.owner, job.name,
                                          source=f"job:{job.id}", metadata={"job_id": job.id})
            return record.id

        defaults, limits = WorkerConfig(), UploadLimits()
        body = getattr(settings, "body_model_dir", None)
        worker = WorkerConfig(
            max_concurrent=getattr(settings, "job_max_concurrent", defaults.max_concurrent),
            threads=getattr(settings, "job_threads", defaults.threads),
            nice=getattr(settings, "job_nice", defaults.nice),
            body_model_dir=None if body is None else str(body))
        upload = UploadLimits(
            max_upload_bytes=getattr(settings, "max_upload_bytes", limits.max_upload_bytes),
            max_unpacked_bytes=getattr(settings, "max_dataset_unpacked_bytes",
                                       limits.max_unpacked_bytes),
            max_files=getattr(settings, "max_dataset_files", limits.max_files))
        return cls(settings.data_dir, register, worker=worker, limits=upload)

    def start(self) -> None:
        for leftover in self.jobs_dir.glob(".upload-*"):  # a crash mid-upload
            shutil.rmtree(leftover, ignore_errors=True)
        self.worker.start()

    def stop(self, grace_s: float | None = None) -> None:
        self.worker.stop(grace_s)
        self.store.close()

    # -- submitting ------------------------------------------------------------------------

    def dataset_path(self, name: str) -> Path:
        """The folder of a named dataset on the server; SubmitError if the name is bad (400)
        or unknown (404)."""
        if not isinstance(name, str) or not _NAME.match(name):
            raise SubmitError(f"dataset name {name!r} must match {_NAME.pattern}")
        path = self.datasets_dir / name
        if not (path / "dataset.json").is_file():
            raise SubmitError(f"no dataset named {name!r} on this server", 404)
        return path

    def submit_named(self, owner: str, dataset: str, config: Any = None,
                     name: str | None = None) -> Job:
        path = self.dataset_path(dataset)
        resolved = resolve_config(config)
        name = _check_avatar_name(name)
        _validated(path, self.worker.config.body_model_dir)
        return self._create(owner, f"dataset:{dataset}", path, resolved, name)

    def submit_archive(self, owner: str, archive: str | Path | BinaryIO, config: Any = None,
                       name: str | None = None) -> Job:
        """Check, unpack and validate an uploaded zip, then queue a job training on it.
        Nothing stays behind when it is refused."""
        resolved = resolve_config(config)
        name = _check_avatar_name(name)
        job_id = new_job_id()
        scratch = Path(tempfile.mkdtemp(prefix=".upload-", dir=self.jobs_dir))
        try:
            try:
                root = extract_archive(archive, scratch / "unpacked", self.limits)
            except ArchiveError as exc:
                raise SubmitError(str(exc), exc.status) from exc
            _validated(root, self.worker.config.body_model_dir)
            folder = self.worker.job_dir(job_id)
            folder.mkdir()
            target = folder / UPLOADED_DATASET
            root.rename(target)
            try:
                return self._create(owner, "upload", target, resolved, name, job_id)
            except BaseException:
                shutil.rmtree(folder, ignore_errors=True)
                raise
        finally:
            shutil.rmtree(scratch, ignore_errors=True)

    def _create(self, owner: str, dataset: str, path: Path, config: TrainConfig,
                name: str | None, job_id: str | None = None) -> Job:
        job = self.store.create(NewJob(owner=owner, dataset=dataset,
                                       dataset_path=str(path.resolve()),
                                       config=config_to_dict(config),
                                       total=config.iterations, name=name, id=job_id))
        self.worker.wake()
        return job

    def cancel(self, job_id: str) -> Job:
        """InvalidTransition when the job has finished already."""
        job = self.store.request_cancel(job_id)
        if job.state == "cancelled":  # it was queued: no process will clean up after it
            self.worker.cleanup(job_id)
        self.worker.wake()
        return job

