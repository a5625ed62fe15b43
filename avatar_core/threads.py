"""Thread pools that wait passively, and thread counts chosen from the machine.

torch (ATen's OpenMP pool, libgomp here) and numba (its ``omp`` threading layer) keep their
worker threads spinning for a while after each parallel region by default. On a machine whose
cores are busy with other processes, those spinning threads fight the other processes (and each
other) for the cores: bench/train.py and bench/render.py ``--hog`` measure it (docs/benchmarks.md,
"Passive thread pools"). :func:`passive_waiting` asks for passive waiting instead. OpenMP reads
these variables once, when its library loads (``import torch`` / numba's first parallel call),
so they are set at the earliest point of every process we start: the ``avatar_core`` and
``server`` packages' ``__init__`` (which run before the entry points import torch), and the
environment of the training processes the job worker starts. A value already in the
environment is kept (``OMP_WAIT_POLICY=ACTIVE`` brings spinning back).

This module imports nothing heavy: it runs before torch and numba are loaded.
"""

from __future__ import annotations

import importlib.util
import math
import os
from collections.abc import MutableMapping
from dataclasses import dataclass
from pathlib import Path

__all__ = ["THREADS_VAR", "RenderThreads", "available_cpus", "cpu_quota", "machine_threads",
           "passive_waiting", "render_threads", "usable_cores"]

THREADS_VAR = "TELESPLAT_THREADS"  # overrides the machine's core count for our thread pools
PASSIVE = {
    "OMP_WAIT_POLICY": "PASSIVE",  # libgomp / any OpenMP: sleep at once, no spin-wait
    "KMP_BLOCKTIME": "0",          # Intel OpenMP (libiomp5, if an MKL build brings it)
}


def _numba_has_omp() -> bool:
    """Whether numba's OpenMP threading layer is installed (found without importing numba)."""
    try:
        spec = importlib.util.find_spec("numba")
    except (ImportError, ValueError):
        return False
    if spec is None or spec.origin is None:
        return False
    return any((Path(spec.origin).parent / "np" / "ufunc").glob("omppool*"))


def passive_waiting(environ: MutableMapping[str, str] | None = None) -> MutableMapping[str, str]:
    """Set passive waiting in ``environ`` (default ``os.environ``) where not set already:
    ``OMP_WAIT_POLICY=PASSIVE``, ``KMP_BLOCKTIME=0`` and, when numba's ``omp`` layer is
    installed, ``NUMBA_THREADING_LAYER=omp`` (its default order tries ``tbb`` first, whose
    workers spin; ``omp`` follows OMP_WAIT_POLICY). Returns ``environ``."""
    env = os.environ if environ is None else environ
    for name, value in PASSIVE.items():
        env.setdefault(name, value)
    if "NUMBA_THREADING_LAYER" not in env and _numba_has_omp():
        env["NUMBA_THREADING_LAYER"] = "omp"
    return env


def available_cpus() -> int:
    """The cores this process may run on (its affinity mask, e.g. a container's cpuset),
    else the machine's count."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def machine_threads(cap: int | None = None) -> int:
    """Threads for one pool: ``$TELESPLAT_THREADS`` when set (a setting overrides the
    machine), else the available cores, at most ``cap``."""
    raw = os.environ.get(THREADS_VAR, "").strip()
    if raw:
        try:
            value = int(raw)
        except ValueError:
            raise ValueError(f"{THREADS_VAR} must be a whole number, not {raw!r}") from None
        if value < 1:
            raise ValueError(f"{THREADS_VAR} must be >= 1")
        return value
    n = available_cpus()
    return n if cap is None else max(1, min(cap, n))


CGROUP = Path("/sys/fs/cgroup")


def cpu_quota(root: Path = CGROUP) -> float | None:
    """The CPUs' worth of time a cgroup quota grants this process (a container's
    ``--cpus``), None without one: cgroup v2 ``cpu.max``, else v1 ``cpu.cfs_quota_us`` /
    ``cpu.cfs_period_us``."""
    try:
        quota, period = (root / "cpu.max").read_text().split()[:2]
        return None if quota == "max" else int(quota) / int(period)
    except (OSError, ValueError):
        pass
    for folder in (root / "cpu", root / "cpu,cpuacct", root):
        try:
            quota_us = int((folder / "cpu.cfs_quota_us").read_text())
            period_us = int((folder / "cpu.cfs_period_us").read_text())
        except (OSError, ValueError):
            continue
        return None if quota_us <= 0 or period_us <= 0 else quota_us / period_us
    return None


def usable_cores(root: Path = CGROUP) -> int:
    """Cores this process can keep busy: its affinity mask, less where a cgroup quota grants
    less time (rounded up: a 1.5-CPU quota still runs two threads in part)."""
    cores = available_cpus()
    quota = cpu_quota(root)
    return cores if quota is None else max(1, min(cores, math.ceil(quota)))


@dataclass(frozen=True)
class RenderThreads:
    """The render pool's shape: ``workers`` frames at once, each spread over ``per_frame``
    torch / numba threads, and over up to ``spread`` numba threads while fewer frames than
    that run at once (``spread // running``); ``why`` says how it was chosen (logged)."""

    workers: int
    per_frame: int
    why: str
    spread: int = 0  # 0: per_frame always

    def __str__(self) -> str:
        spread = f", a lone frame on {self.spread}" if self.spread > self.per_frame else ""
        return (f"{self.workers} render thread(s) x {self.per_frame} thread(s) per frame"
                f"{spread} ({self.why})")


def render_threads(cores: int, workers: int | None = None,
                   per_frame: int | None = None) -> RenderThreads:
    """Render workers x threads per frame for ``cores`` cores, never more threads than cores
    unless both counts are given. Either count given: the other fills the cores. Neither:
    one worker per core and one thread per frame while the workers are all busy (distinct
    views, rooms: each core on its own frame, no fork/join between cores within a frame),
    a lone frame's numba kernels spread over the idle cores (``spread``: one session keeps
    its frame rate). docs/benchmarks.md, "Thread counts", measures the choices."""
    if cores < 1:
        raise ValueError(f"cores must be >= 1, got {cores}")
    for name, value in (("render_threads", workers), ("torch_threads", per_frame)):
        if value is not None and value < 1:
            raise ValueError(f"{name} must be >= 1, got {value}")
    if workers is not None and per_frame is not None:
        over = workers * per_frame > cores
        return RenderThreads(workers, per_frame, "both set" + (
            f": {workers * per_frame} threads on {cores} cores oversubscribe" if over else ""))
    if workers is not None:
        return RenderThreads(workers, max(1, cores // workers),
                             f"render_threads set, torch_threads fills {cores} cores")
    if per_frame is not None:
        return RenderThreads(max(1, cores // per_frame), per_frame,
                             f"torch_threads set, render_threads fills {cores} cores")
    return RenderThreads(cores, 1, f"auto: one render thread per core of {cores}", cores)
