"""The page's "Make my avatar" panel (client/web/enroll.js) in a real headless Chromium with a
fake camera against a real uvicorn: it records a WebM with MediaRecorder while the guidance
steps go by, shows the recorded length, uploads it as an enrollment job, shows the job's
progress events and its end; a recording the server refuses shows why and what to do.
The pure helpers (guidance timing, lengths, the SSE parser) run under node."""

from __future__ import annotations

import json
import os
from urllib.parse import quote

import cv2
import pytest

from avatar_core.enroll.video import probe_video, read_video
from tests.browser_fixtures import browser_fixture  # noqa: F401 (`browser`)
from tests.server_fixtures import run_server
from tests.test_client_browser import wait_for
from tests.test_client_units import chromium_missing, make_chromium, node, run_node
from tests.track_models import needs_models

pytestmark = pytest.mark.skipif(chromium_missing() is not None,
                                reason=chromium_missing() or "")
WEB = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "client", "web"))
WAIT_S = 90.0  # each browser wait (bounded)
RECORD_S = 5   # the shortest recording the page offers (?enroll_s=)
TINY = {"iterations": 6, "resolution": 64, "min_frames": 8, "fit_iterations": 20,
        "preflight_frames": 4}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    # 4 frames a second kept: a 5 s recording is ~20 frames to track (the test's time)
    with run_server(tmp_path_factory.mktemp("enroll-page"), job_threads=1, job_nice=0,
                    enroll_max_decode_fps=4.0) as srv:
        yield srv


def write_y4m(path, frames_rgb, fps: int = 10) -> str:
    """A raw YUV 4:2:0 video (Chromium's fake camera plays it in a loop)."""
    height, width = frames_rgb[0].shape[:2]
    with open(path, "wb") as out:
        out.write(f"YUV4MPEG2 W{width} H{height} F{fps}:1 Ip A1:1 C420jpeg\n".encode())
        for rgb in frames_rgb:
            out.write(b"FRAME\n" + cv2.cvtColor(rgb, cv2.COLOR_RGB2YUV_I420).tobytes())
    return str(path)


@pytest.fixture(scope="module")
def studio_camera(tmp_path_factory) -> str:
    """The studio's one-camera take (the synthetic actor turning and gesturing) as the fake
    camera's video."""
    from avatar_core.synth.enroll_video import EnrollVideoSpec, film_enroll_video

    d = tmp_path_factory.mktemp("studio-camera")
    take = film_enroll_video(d / "take.mp4", EnrollVideoSpec(seconds=4.0, fps=10.0,
                                                             width=320, height=240))
    return write_y4m(d / "take.y4m", read_video(take).frames)


def open_page(driver, server, **query) -> None:
    qs = "&".join(f"{k}={quote(str(v))}" for k, v in {"transport": "ws", **query}.items())
    driver.get(f"{server.url}/?{qs}#token={server.token}")
    wait_for(driver, "window.telesplat.framesShown > 0", WAIT_S, "a frame")


def text_of(driver, element_id: str) -> str:
    return driver.execute_script(f"return document.getElementById('{element_id}').innerText")


@pytest.mark.parametrize("camera", ["pattern", pytest.param("studio", marks=needs_models)])
def test_record_upload_and_follow_an_enrollment_job(server, camera, request):
    """The fake camera's test pattern (no person: refused by the job before training) or the
    studio take (enrolled: the new avatar appears in the page's avatar choice)."""
    driver = make_chromium(camera_file=request.getfixturevalue("studio_camera")
                           if camera == "studio" else None)
    try:
        record_upload_and_follow(server, driver, camera)
    finally:
        driver.quit()


def record_upload_and_follow(server, browser, camera: str) -> None:
    open_page(browser, server, enroll_s=RECORD_S, enroll_config=json.dumps(TINY))
    browser.find_element("id", "enroll-record").click()
    wait_for(browser, "window.telesplat.enroll.phase === 'recording'", WAIT_S, "recording")
    # The guidance moves through its steps with the time (six steps in 5 s).
    seen = set()
    for _ in range(200):  # bounded: ~10 s of 50 ms polls
        phase, step, guide = browser.execute_script(
            "const e = window.telesplat.enroll; return [e.phase, e.step, "
            "document.getElementById('enroll-guide').textContent]")
        if phase != "recording":
            break
        if step is not None:
            seen.add((step, guide.split(" (")[0]))
        browser.execute_script("return new Promise(r => setTimeout(r, 50))")
    texts = {text for _, text in seen}
    assert {"Turn slowly to your left", "Smile, then open your mouth"} <= texts, seen
    assert len({step for step, _ in seen}) >= 4, seen
    state = wait_for(browser, "window.telesplat.enroll.phase === 'recorded' && "
                              "window.telesplat.enroll", WAIT_S, "the recording")
    assert RECORD_S - 0.5 <= state["seconds"] <= RECORD_S + 0.5 and state["bytes"] > 1000
    assert text_of(browser, "enroll-length").startswith(f"0:0{RECORD_S} recorded")

    browser.find_element("id", "enroll-name").send_keys("me")
    browser.find_element("id", "enroll-upload").click()
    job_id = wait_for(browser, "window.telesplat.enroll.jobId", WAIT_S, "the job's id")
    jobs = server.ctx.jobs
    job = jobs.store.get(job_id)
    assert (job.kind, job.name, job.config["iterations"]) == ("enroll", "me", 6)
    # What the browser recorded is a WebM the server probes: its length from the packets
    # (MediaRecorder writes no duration in the header).
    if job.state in ("queued", "running"):
        video = next((jobs.worker.job_dir(job_id) / "dataset").glob("video*"), None)
        if video is not None:
            try:
                info = probe_video(video)
            except FileNotFoundError:  # the job ended and deleted it meanwhile
                info = None
            assert info is None or (info.container.startswith("matroska")
                                    and abs(info.duration_s - RECORD_S) < 1.0), info
    end = wait_for(browser, "['succeeded', 'failed', 'cancelled']"
                            ".includes(window.telesplat.enroll.phase) && window.telesplat.enroll",
                   WAIT_S * 2, "the job's end")
    progress = [e for e in end["events"] if e["event"] == "progress"]
    assert progress and progress[0]["stage"] == "decode", end["events"]
    assert any(e["event"] == "end" for e in end["events"])
    status = text_of(browser, "enroll-status")
    if camera == "studio":  # enrolled: the new avatar is in the page's avatar choice
        assert end["phase"] == "succeeded", (end["error"], status)
        assert status.startswith("done") and end["avatarId"]
        # the page fetches the list again once the job has ended
        wait_for(browser, f"[...document.getElementById('avatar').options]"
                          f".some(o => o.value === '{end['avatarId']}')", WAIT_S,
                 "the new avatar in the avatar list")
        assert {"track", "train"} <= {e.get("stage") for e in progress}
        browser.find_element("id", "enroll-show").click()  # and it streams
        wait_for(browser, f"window.telesplat.session?.welcome?.avatar?.id === "
                          f"'{end['avatarId']}' && window.telesplat.framesShown > 0",
                 WAIT_S, "the new avatar's stream")
    else:  # a test pattern, no person: refused before training, with what to do
        assert end["phase"] == "failed" and status.startswith("failed: ") and end["error"]
        assert "person" in status, status
        assert jobs.store.get(job_id).state == "failed"


def test_a_recording_the_server_refuses_shows_what_to_do(server, browser):
    open_page(browser, server, enroll_s=RECORD_S)
    browser.find_element("id", "enroll-record").click()
    wait_for(browser, "window.telesplat.enroll.phase === 'recording' && "
                      "window.telesplat.enroll.seconds > 0.5", WAIT_S, "recording")
    browser.find_element("id", "enroll-stop").click()
    state = wait_for(browser, "window.telesplat.enroll.phase === 'recorded' && "
                              "window.telesplat.enroll", WAIT_S, "the short recording")
    assert state["seconds"] < 3.0  # under the server's enroll_min_duration_s
    before = {p.name for p in server.ctx.jobs.jobs_dir.iterdir()}
    browser.find_element("id", "enroll-upload").click()
    state = wait_for(browser, "window.telesplat.enroll.phase === 'refused' && "
                              "window.telesplat.enroll", WAIT_S, "the refusal")
    status = text_of(browser, "enroll-status")
    assert "less than the 3 s needed" in status and "Record 20 to 60 s" in status, status
    assert {p.name for p in server.ctx.jobs.jobs_dir.iterdir()} == before
    # The recording is kept: another upload (or a new recording) is possible.
    assert browser.find_element("id", "enroll-upload").is_enabled()


def test_guidance_lengths_and_event_parsing():
    if node() is None:
        pytest.skip("node is not installed")
    script = f"""
    const m = await import("{WEB}/enroll.js");
    const steps = m.guidanceSteps(30);
    const errors = [];
    const sse = m.parseSse("id: 1\\nevent: progress\\ndata: {{\\"progress\\": 0.5, " +
                           "\\"stage\\": \\"track\\"}}\\n\\n: keepalive\\n\\nid: 2\\nevent: e");
    const more = m.parseSse(sse.rest + "nd\\ndata: {{\\"state\\": \\"failed\\"}}\\n\\n");
    console.log(JSON.stringify({{
      steps, at: [0, 3.1, 29.9, 31].map((t) => m.stepAt(steps, t)),
      lengths: [0, 7.4, 75].map(m.formatLength),
      seconds: [m.enrollSeconds("?enroll_s=12"), m.enrollSeconds("?enroll_s=2",
                                                                  (e) => errors.push(e))],
      config: [m.enrollConfig("?enroll_config=%7B%22iterations%22%3A5%7D"),
               m.enrollConfig("?enroll_config=nope", (e) => errors.push(e))],
      sse: sse.events, rest: sse.rest, more: more.events,
      texts: [m.progressText("progress", {{ progress: 0.426, stage: "train" }}),
              m.progressText("end", {{ state: "failed", error: "No person." }}),
              m.refusalText(422, {{ reason: "too_short", message: "Too short.",
                                    what_to_do: "Record more." }})],
      errors,
    }}));
    """
    out = json.loads(run_node(script))
    steps = out["steps"]
    assert steps[0]["start"] == 0 and steps[-1]["end"] == 30
    assert all(a["end"] == b["start"] for a, b in zip(steps, steps[1:], strict=False))
    words = " ".join(s["text"] for s in steps)
    assert all(w in words for w in ("left", "right", "Smile", "hands")), words
    assert out["at"] == [0, 1, 5, 5]
    assert out["lengths"] == ["0:00", "0:07", "1:15"]
    assert out["seconds"] == [12, 30] and out["config"] == [{"iterations": 5}, None]
    assert len(out["errors"]) == 2
    assert out["sse"] == [{"id": "1", "event": "progress",
                           "data": {"progress": 0.5, "stage": "track"}}]
    assert out["rest"] == "id: 2\nevent: e"
    assert out["more"] == [{"id": "2", "event": "end", "data": {"state": "failed"}}]
    assert out["texts"] == ["train: 42%", "failed: No person.", "Too short. Record more."]
