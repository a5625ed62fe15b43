"""avatar_core/threads.py: passive OpenMP waiting in every process we start, and thread counts
from the machine (the speed it buys is measured in docs/benchmarks.md, not here)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from avatar_core.threads import THREADS_VAR, available_cpus, machine_threads, passive_waiting


def test_passive_waiting_sets_defaults_and_keeps_what_is_set():
    env = passive_waiting({})
    assert env["OMP_WAIT_POLICY"] == "PASSIVE" and env["KMP_BLOCKTIME"] == "0"
    assert env.get("NUMBA_THREADING_LAYER") in (None, "omp")
    kept = passive_waiting({"OMP_WAIT_POLICY": "ACTIVE", "NUMBA_THREADING_LAYER": "workqueue"})
    assert kept["OMP_WAIT_POLICY"] == "ACTIVE" and kept["NUMBA_THREADING_LAYER"] == "workqueue"


def test_entry_points_set_it_before_torch_loads():
    """`import server` (python -m server, uvicorn) and `import avatar_core` (the telesplat
    script) set the policy first; torch's OpenMP then reports passive pools."""
    code = "import os, server, torch; print(os.environ['OMP_WAIT_POLICY'])"
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=env, timeout=120, check=True)
    assert out.stdout.split()[0] == "PASSIVE"


def test_training_processes_get_it_in_their_environment(tmp_path, monkeypatch):
    from server.jobs.store import SQLiteJobStore
    from server.jobs.worker import Worker, WorkerConfig

    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
    store = SQLiteJobStore(tmp_path / "jobs.db")
    try:
        env = Worker(store, tmp_path, lambda job, pkg: "x", WorkerConfig(threads=2))._env()
    finally:
        store.close()
    assert env["OMP_WAIT_POLICY"] == "PASSIVE" and env["OMP_NUM_THREADS"] == "2"


def test_machine_threads_from_the_affinity_mask_or_the_setting(monkeypatch):
    monkeypatch.delenv(THREADS_VAR, raising=False)
    assert machine_threads() == available_cpus() >= 1
    assert machine_threads(cap=1) == 1
    monkeypatch.setenv(THREADS_VAR, "3")
    assert machine_threads(cap=2) == 3  # the setting overrides the machine
    monkeypatch.setenv(THREADS_VAR, "0")
    with pytest.raises(ValueError):
        machine_threads()
