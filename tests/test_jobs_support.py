"""Shared pieces of the job tests (no tests here): a tiny capture dataset, fast training
configs, a job service on a temporary data_dir with the real avatar registry, and bounded
polling."""

from __future__ import annotations

import io
import os
import time
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from avatar_core.synth.capture import CaptureSpec, capture
from server.jobs.service import JobService
from server.jobs.worker import WorkerConfig
from server.registry import AvatarRegistry

# 32 px, 3 cameras, 2 frames: the trainer does ~10 iterations/s on one thread
FAST = {"preset": "test", "iterations": 20, "checkpoint_interval": 10, "progress_interval": 5}
LONG = {"preset": "test", "iterations": 100_000, "checkpoint_interval": 10,
        "progress_interval": 2}


@pytest.fixture(scope="session")
def capture_dir(synthetic_files, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("jobs") / "capture"
    spec = CaptureSpec(sequences=(("smile",),), num_cameras=3, resolution=32, max_frames=2,
                       supersample=1, cross_identity=None, workers=1)
    return capture(out, spec, model_dir=synthetic_files.root)


def zip_dataset(root: Path, *, top: str | None = "take") -> bytes:
    """The dataset folder as zip bytes (inside a top folder ``top``, or at the top)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for path in sorted(root.rglob("*")):
            if path.is_file():
                rel = path.relative_to(root).as_posix()
                z.write(path, f"{top}/{rel}" if top else rel)
    return buf.getvalue()


def wait_for(check: Callable[[], Any], timeout: float = 30.0, every: float = 0.05,
             what: str = "condition") -> Any:
    """Poll ``check`` until it returns something truthy; fail after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while True:
        value = check()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(every)


def make_service(data_dir: Path, synthetic_files, **worker: Any) -> JobService:
    registry = AvatarRegistry(Path(data_dir) / "avatars")

    def register(job, package):
        return registry.add_package(package, job.owner, job.name, source=f"job:{job.id}").id

    config = WorkerConfig(body_models=str(synthetic_files.root), nice=0, poll_s=0.05,
                          **worker)
    service = JobService(data_dir, register, worker=config)
    service.registry = registry  # for the tests' checks
    return service


def wait_state(service: JobService, job_id: str, states: str | tuple[str, ...],
               timeout: float = 60.0):
    states = (states,) if isinstance(states, str) else states
    return wait_for(lambda: (j := service.store.get(job_id)).state in states and j,
                    timeout, what=f"job {job_id} to be {states}")


def training_pids(job_id: str) -> list[int]:
    """Live ``server.jobs.run`` processes of a job (Linux /proc)."""
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            cmd = (entry / "cmdline").read_bytes().split(b"\0")
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        if b"server.jobs.run" in cmd and job_id.encode() in cmd and ") Z" not in stat:
            pids.append(int(entry.name))
    return [p for p in pids if p != os.getpid()]
