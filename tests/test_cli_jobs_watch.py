"""Job progress end to end: one event schema (protocol.jobs) from the trainer through the
store and the SSE stream to ``telesplat-client jobs submit --watch``, run as a subprocess
against a real server: the bar reaches 100 % and the output is a short summary, not JSON."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from avatar_core.train.config import PRESETS, preset
from protocol.jobs import (
    MIN_USABLE_ITERATIONS,
    PRESET_NAMES,
    JobProgress,
    progress_event,
    progress_of,
    small_job_warning,
)

from . import test_jobs_support as support
from .server_fixtures import run_server
from .test_jobs_support import FAST

capture_dir = support.capture_dir  # the shared session fixture
ROOT = Path(__file__).resolve().parent.parent


def test_the_schema_sets_progress_and_readers_use_it():
    event = progress_event({"type": "progress", "iteration": 5, "total": 20, "loss": 0.5,
                            "its_per_s": 3.0})
    assert event["progress"] == 0.25 and event["its_per_s"] == 3.0  # extra fields kept
    assert progress_of("progress", event) == 0.25
    assert progress_of("done", {"iteration": 20, "total": 20}) == 1.0
    assert progress_of("state", {"state": "running"}) is None
    assert progress_of("end", {"state": "succeeded"}) == 1.0
    assert progress_event({"type": "state", "state": "queued"}) == {"type": "state",
                                                                     "state": "queued"}
    with pytest.raises(ValueError, match="schema"):
        progress_event({"type": "progress", "iteration": -1, "total": 20})
    assert JobProgress.model_validate({"type": "checkpoint", "iteration": 30,
                                       "total": 20}).progress == 1.0


def test_presets_and_the_usable_threshold_agree_with_the_trainer():
    assert set(PRESET_NAMES) == set(PRESETS)
    assert MIN_USABLE_ITERATIONS == preset("demo").iterations
    assert small_job_warning(preset("test").iterations)
    for name in ("demo", "quick", "default"):
        assert small_job_warning(preset(name).iterations) is None


@pytest.fixture(scope="module")
def srv(tmp_path_factory, capture_dir):
    with run_server(tmp_path_factory.mktemp("jobs-cli")) as server:
        jobs = server.app.state.ctx.jobs
        jobs.worker.config = dataclasses.replace(jobs.worker.config, nice=0, poll_s=0.05)
        shutil.copytree(capture_dir, jobs.datasets_dir / "take")
        yield server


def _client(*args: str, timeout: float = 240.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "client.cli", *args], capture_output=True,
                          text=True, timeout=timeout, cwd=ROOT, env=dict(os.environ),
                          check=False)


def test_submit_watch_reaches_100_percent_and_prints_a_summary(srv, tmp_path):
    config = tmp_path / "fast.json"
    config.write_text(json.dumps(FAST))
    done = _client("jobs", "submit", "--server", srv.url, "--token", srv.token, "--dataset",
                   "take", "--config", str(config), "--name", "cli", "--watch")
    assert done.returncode == 0, done.stderr
    bar = done.stderr.replace("\r", "\n")
    assert "100%" in bar, bar
    assert "too few for a usable avatar" in done.stderr  # 20 iterations: warned
    lines = done.stdout.strip().splitlines()
    assert lines[0].startswith("submitted job ")
    job_id = lines[0].split()[-1]
    assert len(lines) <= 4 and "{" not in done.stdout, done.stdout
    assert lines[1].startswith(f"job {job_id} succeeded") and "20/20 iterations" in lines[1]
    status = srv.app.state.ctx.jobs.store.get(job_id)
    assert lines[2] == f"avatar {status.avatar_id}"
    # every trainer event as stored carries the schema's progress
    events = [e.data for e in srv.app.state.ctx.jobs.store.events(job_id)]
    trainer = [e for e in events if e["type"] in ("progress", "checkpoint", "done")]
    assert trainer and all(e["progress"] == e["iteration"] / e["total"] for e in trainer)

    # `jobs watch` of the ended job: the same summary; --json: the whole status
    again = _client("jobs", "watch", job_id, "--server", srv.url, "--token", srv.token,
                    "--quiet")
    assert again.returncode == 0 and again.stdout.strip().splitlines()[0] == lines[1]
    whole = _client("jobs", "watch", job_id, "--server", srv.url, "--token", srv.token,
                    "--quiet", "--json")
    assert json.loads(whole.stdout)["avatar_id"] == status.avatar_id

    table = _client("jobs", "list", "--server", srv.url, "--token", srv.token)
    row = next(line for line in table.stdout.splitlines() if line.startswith(job_id))
    assert re.search(r"succeeded\s+100%\s+\d{4}-\d\d-\d\d \d\d:\d\d:\d\d$", row), row
