"""Enrollment jobs over REST against a real uvicorn: ``POST /v1/jobs`` with a ``video`` part.
Authenticated before the body is read, bounded while it streams, probed before a job exists
(a refused video is 413 / 422 with its reason and what to do, and nothing is kept), then a job
of kind ``enroll`` with progress events; a video the job itself refuses fails it with the
reason and is deleted."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import httpx
import numpy as np
import pytest

from server.jobs.enrollment import PROGRESS_STEPS, EnrollCaps, enroll_config
from server.jobs.service import SubmitError

from .enroll_videos import write_audio_only, write_garbage, write_video
from .server_fixtures import run_server
from .test_jobs_support import wait_for
from .track_models import needs_models

TIMEOUT_S = 120.0
ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def srv(tmp_path_factory):
    with run_server(tmp_path_factory.mktemp("enroll-jobs"), job_threads=1, job_nice=0,
                    enroll_max_video_bytes=400_000, enroll_max_duration_s=30.0,
                    enroll_min_duration_s=1.0, max_upload_bytes=1_000_000) as server:
        yield server


@pytest.fixture(scope="module")
def videos(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("videos")
    clip = write_video(d / "me.webm", seconds=4, width=320, height=240)
    damaged = bytearray(write_video(d / "ok.mp4", seconds=4, width=320, height=240)
                        .read_bytes())
    at = int(len(damaged) * 0.3)  # pictures damaged, container intact: the probe passes
    damaged[at:at + 200] = np.random.default_rng(1).integers(0, 256, 200, np.uint8).tobytes()
    (d / "damaged.mp4").write_bytes(bytes(damaged))
    return {"clip": clip, "damaged": d / "damaged.mp4", "garbage": write_garbage(d / "x.mp4"),
            "audio": write_audio_only(d / "voice.ogg"),
            "short": write_video(d / "short.webm", seconds=0.5),
            "long": write_video(d / "long.webm", seconds=40, fps=5, width=64, height=64),
            "huge": write_garbage(d / "huge.webm", size=500_000)}


def post_video(srv, path: Path, token: str | None = None, config=None, name=None,
               content_type: str = "video/webm") -> httpx.Response:
    data = {k: v for k, v in (("config", None if config is None else json.dumps(config)),
                              ("name", name)) if v is not None}
    with path.open("rb") as fh:
        return httpx.post(f"{srv.url}/v1/jobs", headers=srv.headers(token), data=data,
                          files={"video": (path.name, fh, content_type)}, timeout=60)


def stored(srv) -> tuple[set[str], set[str]]:
    """The jobs folder's entries and the upload scratch's files: what a refusal must not
    change."""
    jobs = srv.ctx.jobs
    tmp = jobs.data_dir / "tmp"
    return ({p.name for p in jobs.jobs_dir.iterdir()},
            {p.name for p in tmp.iterdir()} if tmp.is_dir() else set())


def events(srv, job_id: str) -> list[dict]:
    return [{"type": e.type, **e.data} for e in srv.ctx.jobs.store.events(job_id)]


def test_authentication_and_scope_come_before_the_body(srv, videos):
    before = stored(srv)
    r = httpx.post(f"{srv.url}/v1/jobs", files={"video": ("a.webm", b"x" * 10_000)})
    assert r.status_code == 401
    viewer = srv.issue("viewer", ("stream",))
    assert post_video(srv, videos["clip"], token=viewer).status_code == 403
    # A body past the limit, announced or not, is cut off at the limit: 413.
    r = post_video(srv, videos["huge"])
    assert r.status_code == 413 and "video is larger than 400000 bytes" in r.text
    assert stored(srv) == before


@pytest.mark.parametrize("case, status, reason", [
    ("garbage", 422, "corrupt_video"), ("audio", 422, "no_video_stream"),
    ("short", 422, "too_short"), ("long", 413, "too_long")])
def test_refused_videos_say_why_and_leave_nothing(srv, videos, case, status, reason):
    before = stored(srv)
    r = post_video(srv, videos[case])
    assert r.status_code == status, r.text
    detail = r.json()["detail"]
    assert detail["reason"] == reason and detail["what_to_do"] and detail["message"]
    assert stored(srv) == before
    assert not [j for j in srv.ctx.jobs.store.list() if j.kind == "enroll" and j.state == "queued"]


def test_bad_enrollment_configs_are_422_naming_the_key(srv, videos):
    for config, words in (({"iteratons": 5}, "iteratons"), ({"iterations": 10**9}, "iterations"),
                          ({"masks": "yes"}, "masks"), ("quick", "enroll"),
                          ({"preset": "default"}, "enroll")):
        r = post_video(srv, videos["clip"], config=config)
        assert r.status_code == 422 and words in r.text, (config, r.text)
    caps = EnrollCaps(max_iterations=100)
    assert enroll_config({"iterations": 100, "fine_tune": False}, caps).fine_tune is False
    with pytest.raises(Exception, match="resolution"):
        enroll_config({"resolution": 4096, "iterations": 10}, caps)


def test_a_video_the_job_refuses_fails_it_with_the_reason_and_is_deleted(srv, videos):
    r = post_video(srv, videos["damaged"], config={"iterations": 10}, name="me",
                   content_type="video/mp4")
    assert r.status_code == 201, r.text
    job = r.json()
    assert (job["kind"], job["dataset"], job["total"], job["name"]) == \
        ("enroll", "video", PROGRESS_STEPS, "me")
    assert job["config"]["preset"] == "enroll" and job["config"]["iterations"] == 10
    folder = srv.ctx.jobs.worker.job_dir(job["id"])
    assert [p.name for p in (folder / "dataset").iterdir()] == ["video.mp4"]
    done = wait_for(lambda: (j := srv.ctx.jobs.store.get(job["id"])).done and j, TIMEOUT_S,
                    what="the job to end")
    assert done.state == "failed" and "Record it again" in done.error, done
    seen = events(srv, job["id"])
    assert any(e["type"] == "progress" and e.get("stage") == "decode" for e in seen), seen
    refusal = [e for e in seen if e["type"] == "error"]
    assert refusal and refusal[0]["reason"] == "corrupt_video", seen
    assert not (folder / "dataset").exists()  # nothing of a refused video is kept
    # The SSE stream ends with the same answer for a page or `jobs watch`.
    text = httpx.get(f"{srv.url}/v1/jobs/{job['id']}/events", headers=srv.headers(),
                     timeout=30).text
    assert "event: end" in text and "Record it again" in text


def test_an_accepted_video_becomes_a_running_job_with_progress(srv, videos):
    r = post_video(srv, videos["clip"], config={"iterations": 10, "resolution": 64})
    assert r.status_code == 201, r.text
    job_id = r.json()["id"]
    assert r.headers["location"] == f"/v1/jobs/{job_id}"
    wait_for(lambda: any(e["type"] == "progress" for e in events(srv, job_id)), TIMEOUT_S,
             what="the first progress event")
    first = next(e for e in events(srv, job_id) if e["type"] == "progress")
    assert first["total"] == PROGRESS_STEPS and 0 <= first["progress"] <= 1
    listed = httpx.get(f"{srv.url}/v1/jobs", headers=srv.headers()).json()["jobs"]
    assert any(j["id"] == job_id and j["kind"] == "enroll" for j in listed)
    end = wait_for(lambda: (j := srv.ctx.jobs.store.get(job_id)).done and j, TIMEOUT_S,
                   what="the job to end")
    # A test pattern holds no person: the pipeline refuses it before training (or, on a
    # branch without the pipeline, the job fails on its import).
    assert end.state == "failed", end
    assert httpx.post(f"{srv.url}/v1/jobs/{job_id}/resume", headers=srv.headers()
                      ).status_code in (202, 409)


def test_the_service_refuses_before_it_stores(tmp_path, videos):
    from server.jobs.service import JobService

    service = JobService(tmp_path, lambda job, package: "unused")
    copy = tmp_path / "upload.webm"
    copy.write_bytes(videos["garbage"].read_bytes())
    with pytest.raises(SubmitError) as info:
        service.submit_video("alice", copy)
    assert info.value.status == 422 and info.value.detail["reason"] == "corrupt_video"
    assert not copy.exists() and service.store.list() == []


def _client(*args: str, timeout: float = 240.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "client.cli", *args], capture_output=True,
                          text=True, timeout=timeout, cwd=ROOT, env=dict(os.environ),
                          check=False)


def test_the_client_submits_a_video_and_watches_its_progress(srv, videos, tmp_path):
    config = tmp_path / "tiny.json"
    config.write_text(json.dumps({"iterations": 10, "resolution": 64}))
    common = ("--server", srv.url, "--token", srv.token)
    done = _client("jobs", "submit", "--video", str(videos["damaged"]), "--config",
                   str(config), "--name", "cli-me", "--watch", *common)
    lines = done.stdout.strip().splitlines()
    assert lines[0].startswith("submitted job "), done.stdout + done.stderr
    job_id = lines[0].split()[-1]
    assert "too few for a usable avatar" not in done.stderr  # no training-job warning
    assert "decode" in done.stderr.replace("\r", "\n")  # the bar names the stage
    # The job refuses the damaged pictures: the summary says what to do, exit status 1.
    assert done.returncode == 1 and lines[1].startswith(f"enrollment job {job_id} failed")
    assert "Record it again" in done.stdout
    job = srv.ctx.jobs.store.get(job_id)
    assert (job.kind, job.name) == ("enroll", "cli-me")

    refused = _client("jobs", "submit", "--video", str(videos["audio"]), *common)
    assert refused.returncode == 1 and "HTTP 422" in refused.stderr
    assert "not a sound recording" in refused.stderr and "(no_video_stream)" in refused.stderr


TINY_ENROLL = {"iterations": 6, "resolution": 64, "min_frames": 8, "fit_iterations": 20,
               "preflight_frames": 4}


@pytest.fixture(scope="module")
def studio_take(tmp_path_factory) -> Path:
    """The studio's one-camera take (the synthetic actor turning and gesturing, 2 s at
    320 x 240), filmed once for the module: the jobs only read it."""
    from avatar_core.synth.enroll_video import EnrollVideoSpec, film_enroll_video

    return film_enroll_video(tmp_path_factory.mktemp("studio") / "take.mp4",
                             EnrollVideoSpec(seconds=2.0, fps=10.0, width=320, height=240))


@needs_models
def test_a_studio_take_becomes_an_avatar_the_server_lists(srv, studio_take, tmp_path):
    """The studio take, submitted and watched with the client, enrolled end to end by the
    job."""
    take = studio_take
    config = tmp_path / "tiny.json"
    config.write_text(json.dumps(TINY_ENROLL))
    done = _client("jobs", "submit", "--video", str(take), "--config", str(config), "--name",
                   "studio-me", "--watch", "--server", srv.url, "--token", srv.token,
                   timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    bar = done.stderr.replace("\r", "\n")
    assert "100%" in bar and "train" in bar, bar
    lines = done.stdout.strip().splitlines()
    job_id = lines[0].split()[-1]
    assert lines[1].startswith(f"enrollment job {job_id} succeeded")
    avatar_id = srv.ctx.jobs.store.get(job_id).avatar_id
    assert lines[2] == f"avatar {avatar_id}"
    listed = httpx.get(f"{srv.url}/v1/avatars", headers=srv.headers()).json()
    listed = listed["avatars"] if isinstance(listed, dict) else listed
    assert any(a["id"] == avatar_id and a["name"] == "studio-me" for a in listed), listed
    stages = [e.get("stage") for e in events(srv, job_id) if e["type"] == "progress"]
    assert [s for s in ("decode", "track", "fit", "train") if s in stages] == \
        ["decode", "track", "fit", "train"], stages
    steps = [e["iteration"] for e in events(srv, job_id) if e["type"] == "progress"]
    assert steps == sorted(steps) and steps[-1] == PROGRESS_STEPS  # one bar, never back
    folder = srv.ctx.jobs.worker.job_dir(job_id)
    assert not (folder / "out" / "dataset").exists()
    # the worker deletes the upload just after it records the end (not before): wait for it
    wait_for(lambda: not (folder / "dataset").exists(), TIMEOUT_S, what="the video deleted")


def test_a_body_of_skipped_parts_is_bounded_too(srv, videos):
    """Parts the server does not keep (an unknown name) still count against the body's
    limit (the largest file part's, 1 MB here, plus the text fields' and some slack): a 4 MB
    one is cut off at 413, nothing kept."""
    before = stored(srv)

    def body():
        yield b"--b\r\nContent-Disposition: form-data; name=\"junk\"\r\n\r\n"
        for _ in range(80):
            yield b"x" * 50_000
        yield b"\r\n--b--\r\n"

    r = httpx.post(f"{srv.url}/v1/jobs", content=body(), timeout=60,
                   headers={**srv.headers(), "Content-Type": "multipart/form-data; boundary=b"})
    assert r.status_code == 413 and "request body" in r.text
    assert stored(srv) == before


@needs_models
def test_cancelling_an_enrollment_stops_it_at_its_next_progress_call(srv, studio_take):
    r = post_video(srv, studio_take, config={**TINY_ENROLL, "iterations": 30_000},
                   content_type="video/mp4")
    assert r.status_code == 201, r.text
    job_id = r.json()["id"]
    # cancelled while it tracks the video (a training job's cancel: tests/test_jobs_worker.py)
    wait_for(lambda: any(e.get("stage") == "track" for e in events(srv, job_id)), 300,
             what="tracking to start")
    assert httpx.post(f"{srv.url}/v1/jobs/{job_id}/cancel", headers=srv.headers()
                      ).status_code == 202
    job = wait_for(lambda: (j := srv.ctx.jobs.store.get(job_id)).done and j, TIMEOUT_S,
                   what="the cancel")
    assert job.state == "cancelled"
    folder = srv.ctx.jobs.worker.job_dir(job_id)
    # the process saw the cancel itself (not killed after the grace period) ...
    assert f"job {job_id} cancelled" in (folder / "log.txt").read_text()
    # ... and the video is gone (deleted just after the end is recorded: waited for)
    wait_for(lambda: not (folder / "dataset").exists(), TIMEOUT_S, what="the video deleted")
