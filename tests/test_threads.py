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


def test_cpu_quota_from_cgroup_v2_and_v1(tmp_path):
    from avatar_core.threads import cpu_quota

    v2 = tmp_path / "v2"
    v2.mkdir()
    (v2 / "cpu.max").write_text("150000 100000\n")
    assert cpu_quota(v2) == 1.5
    (v2 / "cpu.max").write_text("max 100000\n")
    assert cpu_quota(v2) is None
    v1 = tmp_path / "v1" / "cpu"
    v1.mkdir(parents=True)
    (v1 / "cpu.cfs_quota_us").write_text("200000\n")
    (v1 / "cpu.cfs_period_us").write_text("100000\n")
    assert cpu_quota(tmp_path / "v1") == 2.0
    (v1 / "cpu.cfs_quota_us").write_text("-1\n")
    assert cpu_quota(tmp_path / "v1") is None
    assert cpu_quota(tmp_path / "nothing") is None


def test_usable_cores_take_the_quota_rounded_up(tmp_path):
    from avatar_core.threads import usable_cores

    (tmp_path / "cpu.max").write_text("50000 100000\n")  # half a CPU: still one thread
    assert usable_cores(tmp_path) == 1
    (tmp_path / "cpu.max").write_text("max 100000\n")
    assert usable_cores(tmp_path) == available_cpus()


def test_render_threads_never_oversubscribe_unless_both_are_set():
    from avatar_core.threads import render_threads

    auto = render_threads(8)
    assert (auto.workers, auto.per_frame, auto.spread) == (8, 1, 8)
    assert render_threads(2, workers=1).per_frame == 2  # one worker: a frame on both cores
    assert render_threads(8, workers=3).per_frame == 2
    assert render_threads(8, per_frame=4).workers == 2
    assert render_threads(2, workers=4).per_frame == 1  # more workers than cores: 1 each
    both = render_threads(2, workers=2, per_frame=2)
    assert (both.workers, both.per_frame) == (2, 2) and "oversubscribe" in both.why
    assert "oversubscribe" not in render_threads(4, workers=2, per_frame=2).why
    for bad in ({"cores": 0}, {"cores": 2, "workers": 0}, {"cores": 2, "per_frame": 0}):
        with pytest.raises(ValueError):
            render_threads(**bad)


def test_settings_choose_the_pool_from_the_machine_or_the_override(monkeypatch, tmp_path):
    from server.config import Settings

    monkeypatch.delenv(THREADS_VAR, raising=False)
    monkeypatch.delenv("TELESPLAT_RENDER_THREADS", raising=False)
    monkeypatch.delenv("TELESPLAT_TORCH_THREADS", raising=False)
    pool = Settings(data_dir=tmp_path).render_pool()
    assert pool.workers * pool.per_frame <= available_cpus()
    monkeypatch.setenv(THREADS_VAR, "6")
    pool = Settings(data_dir=tmp_path, torch_threads=2).render_pool()
    assert (pool.workers, pool.per_frame) == (3, 2)


def test_a_lone_frame_spreads_and_concurrent_frames_take_a_core_each():
    """spread: a job's numba threads = spread // jobs running as it starts (read on the
    job's own thread)."""
    import threading

    import numba

    from server.stream.scheduler import RenderScheduler

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba has one thread here")
    scheduler = RenderScheduler(render_threads=2, threads_per_render=1, spread=2)
    try:
        alone = scheduler.submit(numba.get_num_threads).result(timeout=60)
        release = threading.Event()

        def held() -> int:  # holds its render thread until released
            release.wait(30)
            return numba.get_num_threads()

        first = scheduler.submit(held)
        second = scheduler.submit(numba.get_num_threads)  # starts while `first` runs
        beside = second.result(timeout=60)
        release.set()
        assert (alone, beside, first.result(timeout=60)) == (2, 1, 2)
    finally:
        scheduler.shutdown()


def test_the_chosen_pool_is_logged_and_shapes_the_scheduler(caplog, tmp_path, monkeypatch):
    import logging

    from server.app import render_scheduler
    from server.config import Settings

    monkeypatch.setenv(THREADS_VAR, "2")
    with caplog.at_level(logging.INFO, logger="telesplat.server"):
        auto = render_scheduler(Settings(data_dir=tmp_path))
        over = render_scheduler(Settings(data_dir=tmp_path, render_threads=2, torch_threads=2))
    try:
        assert (auto.render_threads, auto.threads_per_render, auto.spread) == (2, 1, 2)
        assert (over.render_threads, over.threads_per_render) == (2, 2)
        levels = {r.getMessage(): r.levelno for r in caplog.records}
        assert levels["render threads: 2 render thread(s) x 1 thread(s) per frame, a lone "
                      "frame on 2 (auto: one render thread per core of 2)"] == logging.INFO
        assert any("oversubscribe" in m and lv == logging.WARNING for m, lv in levels.items())
    finally:
        auto.shutdown()
        over.shutdown()
