"""JobService: the store and the worker together, plus submitting (used by the routes).

Started and stopped with the app (its lifespan). Submissions are validated here, not in the
worker: the dataset is loaded (and so validated) and the config resolved before a job row
exists, so a bad submission creates nothing. Per-owner quotas (:class:`JobQuota`) are checked
before an upload is unpacked and again, atomically, when the row is inserted.
"""

from __future__ import annotations

import re
import shutil
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, BinaryIO

from avatar_core.body.model_paths import (
    SYNTHETIC_SOURCE,
    BodyModelsMissing,
    models_for_source,
    synthetic_seed_of,
)
from avatar_core.bounded_npz import NpzLimits
from avatar_core.dataset import DatasetError, load_dataset
from avatar_core.enroll.errors import EnrollmentRefused
from avatar_core.enroll.video import VideoLimits, decode_plan, probe_video
from avatar_core.train.checkpoint import latest_checkpoint
from avatar_core.train.config import TrainConfig, config_from_dict, config_to_dict, preset

from ..quotas import storage_left
from .archive import ArchiveError, UploadLimits, extract_archive
from .enrollment import (
    PROGRESS_STEPS,
    VIDEO_FILE,
    ConfigRefused,
    EnrollCaps,
    decode_side,
    enroll_caps,
    enroll_config,
    job_config,
    refusal_status,
    video_limits,
    video_suffix,
)
from .run import OUT_DIR
from .store import (
    RESUMABLE,
    InvalidTransition,
    Job,
    JobStore,
    NewJob,
    QuotaExceeded,
    SQLiteJobStore,
    check_quota,
    new_job_id,
)
from .worker import UPLOADED_DATASET, Register, Worker, WorkerConfig

__all__ = ["DATASETS_DIR", "JOBS_DIR", "JobQuota", "JobService", "SubmitError",
           "resolve_config"]

JOBS_DIR, DATASETS_DIR, DB_FILE = "jobs", "datasets", "jobs.db"
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")
MAX_AVATAR_NAME = 128
# Without an explicit checkpoint_interval a job checkpoints at least every tenth of its run.
CHECKPOINT_FRACTION = 10


class SubmitError(ValueError):
    """A submission that is refused; ``status`` is the HTTP status to answer, ``detail`` what
    the answer carries (the message, or an enrollment refusal's reason and what to do)."""

    def __init__(self, message: str, status: int = 400, detail: Any = None) -> None:
        super().__init__(message)
        self.status = status
        self.detail = message if detail is None else detail


@dataclass(frozen=True)
class JobQuota:
    """Per-owner caps on jobs (None: no cap); admins are exempt."""

    max_active: int | None = 4    # queued + running jobs of one owner
    max_stored: int | None = 200  # jobs of one owner kept in the store, finished ones included

    def __post_init__(self) -> None:
        if any(v is not None and v < 1 for v in (self.max_active, self.max_stored)):
            raise ValueError("job quotas must be >= 1 (or None: no cap)")


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


def _validated(root: Path, body_models: str | None, npz_limits: NpzLimits) -> None:
    try:
        # shallow validation: files present, headers, parameters (read within npz_limits)
        dataset = load_dataset(root, npz_limits=npz_limits)
    except DatasetError as exc:
        lines = [str(p) for p in exc.problems[:20]]
        more = len(exc.problems) - len(lines)
        detail = "; ".join(lines) + (f"; and {more} more" if more > 0 else "")
        raise SubmitError(f"the dataset is not valid: {detail}") from exc
    except (OSError, ValueError, KeyError) as exc:
        raise SubmitError(f"the dataset cannot be read: {exc}") from exc
    source = str(dataset.meta.get("body_model", {}).get("source", ""))
    if synthetic_seed_of(source, SYNTHETIC_SOURCE) is None:  # (a synthetic one is generated)
        # the trainer would fail without the model files (posing.resolve_body): say so now
        try:
            models_for_source(source, body_models)
        except BodyModelsMissing as exc:  # (the public message names no server folder)
            raise SubmitError(f"this server cannot train on the dataset: {exc.public}") \
                from None


class JobService:
    """Jobs under ``data_dir``: ``jobs/jobs.db``, ``jobs/<id>/``, named datasets in
    ``datasets/<name>/``. ``register(job, package_dir) -> avatar id``."""

    def __init__(self, data_dir: str | Path, register: Register, *,
                 worker: WorkerConfig | None = None, limits: UploadLimits | None = None,
                 store: JobStore | None = None, quota: JobQuota | None = None,
                 worker_type: Callable[..., Worker] = Worker,
                 video: VideoLimits | None = None, enroll: EnrollCaps | None = None) -> None:
        self.data_dir = Path(data_dir)
        self.jobs_dir = self.data_dir / JOBS_DIR
        self.datasets_dir = self.data_dir / DATASETS_DIR
        self.jobs_dir.mkdir(parents=True, exist_ok=True)
        self.limits = limits or UploadLimits()
        self.video_limits = video or VideoLimits()
        self.enroll_caps = enroll or EnrollCaps()
        # owner -> bytes they may still store (None: no storage quota); set by from_settings
        self.storage_left: Callable[[str], int] | None = None
        self.quota = quota or JobQuota()
        self.store = store or SQLiteJobStore(self.jobs_dir / DB_FILE)
        self.worker = worker_type(self.store, self.jobs_dir, register, worker)

    @classmethod
    def from_settings(cls, settings: Any, registry: Any) -> JobService:
        """From the server's Settings and AvatarRegistry. Optional settings (defaults when
        absent): job_max_concurrent, job_threads, job_nice, job_max_attempts, body_models,
        max_dataset_unpacked_bytes, max_dataset_files, job_max_active_per_user,
        job_max_stored_per_user."""

        def register(job: Job, package: Path) -> str:
            from .demo_build import register_job_package  # the demo's job: replaces 'demo'

            demo_id = register_job_package(settings, registry, job, package)
            if demo_id is not None:
                return demo_id
            record = registry.add_package(package, job.owner, job.name,
                                          source=f"job:{job.id}", metadata={"job_id": job.id})
            return record.id

        defaults, limits = WorkerConfig(), UploadLimits()
        body = getattr(settings, "body_models", None)
        worker = WorkerConfig(
            max_concurrent=getattr(settings, "job_max_concurrent", defaults.max_concurrent),
            threads=getattr(settings, "job_threads", defaults.threads),
            nice=getattr(settings, "job_nice", defaults.nice),
            max_attempts=getattr(settings, "job_max_attempts", defaults.max_attempts),
            body_models=None if body is None else str(body))
        upload = UploadLimits(
            max_upload_bytes=getattr(settings, "max_upload_bytes", limits.max_upload_bytes),
            max_unpacked_bytes=getattr(settings, "max_dataset_unpacked_bytes",
                                       limits.max_unpacked_bytes),
            max_files=getattr(settings, "max_dataset_files", limits.max_files),
            max_member_bytes=getattr(settings, "max_dataset_member_bytes",
                                     limits.max_member_bytes),
            max_json_bytes=getattr(settings, "max_dataset_json_bytes", limits.max_json_bytes),
            max_ratio=getattr(settings, "max_unpack_ratio", limits.max_ratio),
            max_npz_array_bytes=getattr(settings, "max_npz_array_bytes",
                                        limits.max_npz_array_bytes),
            max_npz_bytes=getattr(settings, "max_npz_bytes", limits.max_npz_bytes))
        quota = JobQuota(
            max_active=getattr(settings, "job_max_active_per_user", JobQuota.max_active),
            max_stored=getattr(settings, "job_max_stored_per_user", JobQuota.max_stored))
        if getattr(settings, "job_backend", "local") == "ray":
            return cls._on_ray(settings, register, worker, upload, quota, registry)
        service = cls(settings.data_dir, register, worker=worker, limits=upload, quota=quota,
                      video=video_limits(settings), enroll=enroll_caps(settings))
        if hasattr(settings, "max_stored_bytes_per_user"):  # the avatars' and jobs' bytes
            service.storage_left = lambda owner: storage_left(owner, settings, registry, service)
        return service

    @classmethod
    def _on_ray(cls, settings: Any, register: Register, worker: WorkerConfig,
                upload: UploadLimits, quota: JobQuota, registry: Any) -> JobService:
        """job_backend "ray": each attempt a Ray actor (server/jobs/ray_backend.py). Job
        folders and named datasets live under cluster_storage, which every node reaches; the
        store stays in data_dir (only this server opens it)."""
        from functools import partial

        from .. import cluster
        from .ray_backend import RayWorker

        worker_type = partial(RayWorker, connect=lambda: cluster.connect(settings),
                              num_cpus=settings.ray_job_num_cpus,
                              num_gpus=settings.ray_job_num_gpus)
        worker = replace(worker, max_concurrent=settings.ray_job_max_concurrent)
        store = SQLiteJobStore(Path(settings.data_dir) / JOBS_DIR / DB_FILE)
        service = cls(settings.cluster_storage_dir, register, worker=worker, limits=upload,
                      store=store, quota=quota, worker_type=worker_type,
                      video=video_limits(settings), enroll=enroll_caps(settings))
        service.storage_left = lambda owner: storage_left(owner, settings, registry, service)
        return service

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

    def check_quota(self, owner: str, exempt: bool = False) -> None:
        """SubmitError (429) when ``owner`` may not add a job now (``exempt``: admins)."""
        if exempt:
            return
        try:
            check_quota(self.store.count(owner), owner, self.quota.max_active,
                        self.quota.max_stored)
        except QuotaExceeded as exc:
            raise SubmitError(str(exc), 429) from exc

    def upload_limits(self, owner: str, exempt: bool = False) -> UploadLimits:
        """The archive limits for ``owner``: ``limits`` with their storage left as quota."""
        if exempt or self.storage_left is None:
            return self.limits
        return replace(self.limits, quota_bytes=self.storage_left(owner))

    def submit_named(self, owner: str, dataset: str, config: Any = None,
                     name: str | None = None, *, exempt: bool = False) -> Job:
        self.check_quota(owner, exempt)
        path = self.dataset_path(dataset)
        resolved = resolve_config(config)
        name = _check_avatar_name(name)
        _validated(path, self.worker.config.body_models, self.limits.npz_limits())
        return self._create(owner, f"dataset:{dataset}", path, resolved, name,
                            exempt=exempt)

    def submit_archive(self, owner: str, archive: str | Path | BinaryIO, config: Any = None,
                       name: str | None = None, *, exempt: bool = False) -> Job:
        """Check, unpack and validate an uploaded zip, then queue a job training on it.
        Nothing stays behind when it is refused."""
        self.check_quota(owner, exempt)  # before the work of unpacking
        resolved = resolve_config(config)
        name = _check_avatar_name(name)
        job_id = new_job_id()
        scratch = Path(tempfile.mkdtemp(prefix=".upload-", dir=self.jobs_dir))
        try:
            try:
                root = extract_archive(archive, scratch / "unpacked",
                                       self.upload_limits(owner, exempt))
            except ArchiveError as exc:
                raise SubmitError(str(exc), exc.status) from exc
            _validated(root, self.worker.config.body_models, self.limits.npz_limits())
            folder = self.worker.job_dir(job_id)
            folder.mkdir()
            target = folder / UPLOADED_DATASET
            root.rename(target)
            try:
                return self._create(owner, "upload", target, resolved, name, job_id,
                                    exempt=exempt)
            except BaseException:
                shutil.rmtree(folder, ignore_errors=True)
                raise
        finally:
            shutil.rmtree(scratch, ignore_errors=True)

    def submit_video(self, owner: str, video: Path, config: Any = None,
                     name: str | None = None, *, filename: str | None = None,
                     exempt: bool = False) -> Job:
        """Probe an uploaded enrollment video (``video``: a file this call takes over) and
        queue a job enrolling it. Refused (SubmitError, nothing kept) for a bad config (422),
        past the owner's storage (413), or a video outside ``video_limits`` (413 / 422 with
        the reason and what to do)."""
        video = Path(video)
        try:
            self.check_quota(owner, exempt)
            try:
                resolved = enroll_config(config, self.enroll_caps)
            except ConfigRefused as exc:
                raise SubmitError(f"bad enrollment config: {exc}", 422) from None
            name = _check_avatar_name(name)
            size = video.stat().st_size
            left = None if exempt or self.storage_left is None else self.storage_left(owner)
            if left is not None and size > left:
                raise SubmitError(f"the video is {size} bytes, more than the {max(0, left)} "
                                  "bytes left of your storage quota", 413)
            try:  # what decoding it would hold too, before any of it
                decode_plan(probe_video(video, self.video_limits), self.video_limits,
                            decode_side(resolved))
            except EnrollmentRefused as refused:
                raise SubmitError(str(refused), refusal_status(refused),
                                  refused.to_dict()) from None
            job_id = new_job_id()
            folder = self.worker.job_dir(job_id)
            (folder / UPLOADED_DATASET).mkdir(parents=True)
            shutil.move(video, folder / UPLOADED_DATASET / (VIDEO_FILE + video_suffix(filename)))
            try:
                return self._insert(NewJob(
                    owner=owner, dataset="video", dataset_path=str(
                        (folder / UPLOADED_DATASET).resolve()),
                    config=job_config(resolved, self.video_limits), total=PROGRESS_STEPS,
                    name=name, id=job_id, max_attempts=self.worker.config.max_attempts,
                    kind="enroll"), exempt)
            except BaseException:
                shutil.rmtree(folder, ignore_errors=True)
                raise
        finally:
            video.unlink(missing_ok=True)

    def submit_prepared(self, owner: str, label: str, path: Path, config: Any,
                        name: str | None = None) -> Job:
        """A job the server itself queues (the trained demo avatar: server/jobs/demo_build.py) on a
        dataset it made: no quota, the dataset's own checks left to the trainer. ``label``
        is the job's ``dataset`` (never ``upload`` or ``dataset:...``, which users' jobs
        carry)."""
        if label == "upload" or label.startswith("dataset:"):
            raise ValueError(f"label {label!r} is reserved for users' jobs")
        return self._create(owner, label, Path(path), resolve_config(config), name,
                            exempt=True)

    def _create(self, owner: str, dataset: str, path: Path, config: TrainConfig,
                name: str | None, job_id: str | None = None, *, exempt: bool = False) -> Job:
        return self._insert(NewJob(
            owner=owner, dataset=dataset, dataset_path=str(path.resolve()),
            config=config_to_dict(config), total=config.iterations, name=name, id=job_id,
            max_attempts=self.worker.config.max_attempts), exempt)

    def _insert(self, new: NewJob, exempt: bool) -> Job:
        caps = {} if exempt else {"max_active": self.quota.max_active,
                                  "max_stored": self.quota.max_stored}
        try:
            job = self.store.create(new, **caps)
        except QuotaExceeded as exc:  # another submission got in since check_quota
            raise SubmitError(str(exc), 429) from exc
        self.worker.wake()
        return job

    def resume(self, job_id: str, *, exempt: bool = False) -> Job:
        """A failed job queued again, to go on from its latest checkpoint (from the start
        without one) with a fresh budget of ``max_attempts`` runs. InvalidTransition when it
        is not failed; SubmitError when its dataset is gone (409) or its owner is at the
        active-jobs quota (429)."""
        job = self.store.get(job_id)
        if job.state not in RESUMABLE:
            raise InvalidTransition(f"job {job_id} is {job.state}; only a failed job can be "
                                    "resumed")
        if not Path(job.dataset_path).is_dir():
            raise SubmitError(f"job {job_id}'s dataset is no longer on the server", 409)
        if not exempt:
            try:  # it is stored already: only the active cap applies
                check_quota(self.store.count(job.owner), job.owner, self.quota.max_active, None)
            except QuotaExceeded as exc:
                raise SubmitError(str(exc), 429) from exc
        ckpt = latest_checkpoint(self.worker.job_dir(job_id) / OUT_DIR)
        resumed = self.store.resume(
            job_id, job.attempts + self.worker.config.max_attempts,
            note={"reason": "resumed on request",
                  "resume_from": None if ckpt is None else ckpt.name})
        self.worker.wake()
        return resumed

    def delete(self, job_id: str) -> None:
        """Forget a finished job and free its folder (its avatar stays registered);
        InvalidTransition while it is queued or running."""
        self.store.delete(job_id)
        shutil.rmtree(self.worker.job_dir(job_id), ignore_errors=True)

    def cancel(self, job_id: str) -> Job:
        """InvalidTransition when the job has finished already."""
        job = self.store.request_cancel(job_id)
        if job.state == "cancelled":  # it was queued: no process will clean up after it
            self.worker.cleanup(job_id)
        self.worker.wake()
        return job

