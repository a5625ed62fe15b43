"""Client pieces without a server (SSE parsing, motion files, URLs, images), and the helpers
the other client tests share: a headless Chromium driven by selenium and a node runner."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from client.images import decode_image, save_frame
from client.motion_file import load_motion
from client.rest import parse_sse
from client.stream import params_of, stream_url
from protocol import Frame, ProtocolError


def _tool(env: str, name: str) -> Path:
    """$env, else Debian's /usr/bin/<name>, else <name> on PATH."""
    default = Path("/usr/bin") / name
    found = os.environ.get(env) or (str(default) if default.exists() else shutil.which(name))
    return Path(found or default)


CHROMIUM = _tool("TELESPLAT_CHROMIUM", "chromium")
CHROMEDRIVER = _tool("TELESPLAT_CHROMEDRIVER", "chromedriver")


# -- shared helpers ----------------------------------------------------------------------


def chromium_missing() -> str | None:
    """Why the browser tests cannot run here, or None when they can."""
    for path in (CHROMIUM, CHROMEDRIVER):
        if not os.access(path, os.X_OK):
            return f"{path} not found (apt-get install chromium chromium-driver; make test does)"
    try:
        import selenium  # noqa: F401
    except ImportError:
        return "selenium is not installed (pip install -e .[dev])"
    return None


def make_chromium(width: int = 1280, height: int = 900, camera_file: str | None = None):
    """Headless Chromium with Debian's chromedriver, given explicitly so that selenium-manager
    never looks anything up or downloads a driver; a fake camera for getUserMedia (its
    built-in test pattern, or ``camera_file``: a .y4m / .mjpeg video, played in a loop)."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    os.environ.setdefault("SE_OFFLINE", "true")
    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                f"--window-size={width},{height}", "--use-fake-ui-for-media-stream",
                "--use-fake-device-for-media-stream", "--mute-audio",
                "--disable-background-timer-throttling", "--no-first-run"):
        options.add_argument(arg)
    if camera_file is not None:
        options.add_argument(f"--use-file-for-fake-video-capture={camera_file}")
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(executable_path=str(CHROMEDRIVER)),
                              options=options)
    driver.set_script_timeout(30)
    driver.set_page_load_timeout(30)
    return driver


def node() -> str | None:
    return shutil.which("node")


def run_node(script: str, stdin: str = "", timeout: float = 60.0) -> str:
    """Run an ES-module script with node; its stdout."""
    done = subprocess.run([node(), "--input-type=module", "-e", script], input=stdin,
                          capture_output=True, text=True, timeout=timeout, check=False)
    if done.returncode != 0:
        raise AssertionError(f"node failed ({done.returncode}):\n{done.stderr}")
    return done.stdout


# -- SSE -----------------------------------------------------------------------------------


def test_parse_sse_events_comments_and_multiline_data():
    lines = [": keepalive", "", "id: 1", "event: state", 'data: {"state": "running"}', "",
             "event: log", "data: line one", "data: line two", "", "event: end",
             'data: {"state": "succeeded"}']
    events = list(parse_sse(iter(lines)))
    assert [e.event for e in events] == ["state", "log", "end"]
    assert events[0].data == {"state": "running"} and events[0].id == "1"
    assert events[1].data == "line one\nline two"
    assert events[2].data == '{"state": "succeeded"}'  # no blank line: kept as text


# -- motion files -----------------------------------------------------------------------


def test_motion_json_list_and_wrapped(tmp_path):
    frames = [{"jaw_pose": [0.1 * i, 0, 0], "flame": {"expr": [0.5]}} for i in range(3)]
    (tmp_path / "a.json").write_text(json.dumps(frames))
    (tmp_path / "b.json").write_text(json.dumps({"fps": 24, "frames": frames}))
    a, b = load_motion(tmp_path / "a.json"), load_motion(tmp_path / "b.json")
    assert len(a) == 3 and a.fps is None and b.fps == 24.0
    assert a.frames[2] == {"smplx": {"jaw_pose": [0.2, 0, 0]}, "flame": {"expr": [0.5]}}


def test_motion_npz_frame_axis_static_betas_and_families(tmp_path):
    path = tmp_path / "m.npz"
    np.savez(path, jaw_pose=np.zeros((5, 3)), body_pose=np.zeros((5, 21, 3)),
             betas=np.ones(10), **{"mano_left.hand_pose": np.zeros((5, 45))}, fps=np.array(15))
    motion = load_motion(path)
    assert len(motion) == 5 and motion.fps == 15.0
    assert set(motion.frames[0]["smplx"]) == {"jaw_pose", "body_pose", "betas"}
    assert "betas" not in motion.frames[1]["smplx"]  # sent once: drives are partial updates
    assert motion.frames[3]["mano_left"]["hand_pose"].shape == (45,)


def test_motion_files_reject_bad_input(tmp_path):
    np.savez(tmp_path / "bad.npz", poses=np.zeros((4, 165)))
    with pytest.raises(ValueError, match="unknown parameter 'poses'"):
        load_motion(tmp_path / "bad.npz")
    np.savez(tmp_path / "uneven.npz", jaw_pose=np.zeros((4, 3)), transl=np.zeros((5, 3)))
    with pytest.raises(ValueError, match="frame count"):
        load_motion(tmp_path / "uneven.npz")
    (tmp_path / "empty.json").write_text("[]")
    with pytest.raises(ValueError, match="non-empty list"):
        load_motion(tmp_path / "empty.json")
    with pytest.raises(ProtocolError):
        params_of({"jaw": [0, 0, 0]})


# -- URLs and images ----------------------------------------------------------------------


def test_stream_url_from_http_and_ws_bases():
    assert stream_url("http://h:1", "de mo") == "ws://h:1/v1/stream?avatar=de+mo"  # no token
    assert stream_url("https://h/base/", "a") == "wss://h/base/v1/stream?avatar=a"
    assert stream_url("ws://h:2/v1/stream", "a") == "ws://h:2/v1/stream?avatar=a"


def test_decode_and_save_frame(tmp_path):
    import cv2

    bgr = np.zeros((8, 12, 3), np.uint8)
    bgr[..., 2] = 255  # red in BGR
    ok, png = cv2.imencode(".png", bgr)
    frame = Frame(seq=1, frame=1, codec="png", width=12, height=8, data=png.tobytes())
    rgb = decode_image(frame)
    assert rgb.shape == (8, 12, 3) and (rgb[..., 0] == 255).all() and (rgb[..., 2] == 0).all()
    assert save_frame(frame, tmp_path / "f").read_bytes() == png.tobytes()
    with pytest.raises(ValueError, match="h264"):
        decode_image(frame.model_copy(update={"codec": "h264"}))


def test_client_package_imports_no_torch_no_server():
    code = ("import sys, client, client.cli; "
            "bad = [m for m in ('torch', 'server', 'cv2', 'avatar_core') if m in sys.modules]; "
            "print(bad)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=60, check=True, cwd=Path(__file__).parent.parent)
    assert done.stdout.strip() == "[]"


# -- REST client against a mock transport (request shapes the jobs API documents) ---------


def test_rest_client_jobs_requests_and_sse(tmp_path):
    import httpx

    from client.rest import RestClient

    seen = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        path = request.url.path
        if request.method == "POST" and path == "/v1/jobs":
            return httpx.Response(201, json={"id": "j1", "state": "queued"})
        if path == "/v1/jobs":
            return httpx.Response(200, json={"jobs": [{"id": "j1"}]})
        if path == "/v1/jobs/j1/events":
            text = ('id: 1\nevent: progress\ndata: {"iteration": 5, "total": 10}\n\n'
                    'event: end\ndata: {"state": "succeeded"}\n\n')
            return httpx.Response(200, text=text, headers={"content-type": "text/event-stream"})
        if path == "/v1/jobs/j1/logs":
            return httpx.Response(200, text="line 1\nline 2\n")
        if path == "/v1/jobs/j1/cancel":
            return httpx.Response(409, json={"detail": "job j1 already finished"})
        return httpx.Response(404, json={"detail": "nope"})

    archive = tmp_path / "take.zip"
    archive.write_bytes(b"PK\x05\x06" + b"\0" * 18)
    with RestClient("http://test", "tok", transport=httpx.MockTransport(handler)) as api:
        assert api.submit_job(dataset="studio", config="quick", name="A")["id"] == "j1"
        assert json.loads(seen[-1].content) == {"dataset": "studio", "config": "quick",
                                                "name": "A"}
        assert seen[-1].headers["authorization"] == "Bearer tok"
        api.submit_job(archive=archive, config={"iterations": 3})
        body = seen[-1].content
        assert seen[-1].headers["content-type"].startswith("multipart/form-data")
        assert b'name="archive"; filename="take.zip"' in body and b'{"iterations": 3}' in body
        assert api.jobs() == [{"id": "j1"}]
        events = list(api.job_events("j1", after=0))
        assert [e.event for e in events] == ["progress", "end"]
        assert events[0].data == {"iteration": 5, "total": 10} and events[0].id == "1"
        assert api.job_logs("j1", tail=2) == "line 1\nline 2\n"
        assert seen[-1].url.params["tail"] == "2"
        with pytest.raises(Exception, match="409.*already finished"):
            api.cancel_job("j1")
        with pytest.raises(ValueError, match="exactly one"):
            api.submit_job()
