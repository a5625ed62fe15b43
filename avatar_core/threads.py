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
import os
from collections.abc import MutableMapping
from pathlib import Path

__all__ = ["THREADS_VAR", "available_cpus", "machine_threads", "passive_waiting"]

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
