"""The browser page (client/web/) in a real headless Chromium against a real server: it loads,
shows frames on its canvas, orbits on a mouse drag, shows stats, drives from its sliders and
reports the server's answer to webcam frames. These are the WebSocket transport's tests
(?transport=ws); tests/test_webrtc_browser.py has the WebRTC one's."""

from __future__ import annotations

import logging
import time

import pytest

from tests.server_fixtures import server_fixture  # noqa: F401 (the `server` fixture)
from tests.test_client_units import chromium_missing, make_chromium

pytestmark = pytest.mark.skipif(chromium_missing() is not None,
                                reason=chromium_missing() or "")

# A 16x16 grey thumbnail of the canvas, its pixel spread, and how many pixels are not the
# background colour: enough to tell "blank", "shows the avatar" and "the view changed".
CANVAS_PROBE = """
const canvas = document.getElementById("view");
const ctx = canvas.getContext("2d");
const {width, height} = canvas;
const data = ctx.getImageData(0, 0, width, height).data;
const bg = [data[0], data[1], data[2]];
let sum = 0, sum2 = 0, fg = 0;
const thumb = new Array(256).fill(0), counts = new Array(256).fill(0);
for (let y = 0; y < height; y++) for (let x = 0; x < width; x++) {
  const i = 4 * (y * width + x);
  const g = (data[i] + data[i + 1] + data[i + 2]) / 3;
  sum += g; sum2 += g * g;
  const d = Math.abs(data[i] - bg[0]) + Math.abs(data[i + 1] - bg[1])
    + Math.abs(data[i + 2] - bg[2]);
  if (d > 30) fg++;
  const t = Math.floor(16 * y / height) * 16 + Math.floor(16 * x / width);
  thumb[t] += g; counts[t] += 1;
}
const n = width * height;
return {width, height, std: Math.sqrt(Math.max(0, sum2 / n - (sum / n) ** 2)),
        foreground: fg / n, thumb: thumb.map((v, i) => v / counts[i]),
        shown: window.telesplat.framesShown};
"""


def wait_for(driver, script: str, timeout: float, what: str):
    """Poll a JS expression until it is truthy (bounded); returns its value."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = driver.execute_script(f"return ({script});")
        if value:
            return value
        time.sleep(0.05)
    logs = "\n".join(str(e) for e in driver.get_log("browser"))
    raise TimeoutError(f"timed out after {timeout} s waiting for {what}; console:\n{logs}")


def thumb_diff(a: dict, b: dict) -> float:
    return sum(abs(x - y) for x, y in zip(a["thumb"], b["thumb"], strict=True)) / 256


@pytest.fixture(scope="module")
def server_log():
    """What uvicorn logs at INFO (request lines, WebSocket URLs) while the page runs."""
    lines: list[str] = []

    class Collect(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            lines.append(record.getMessage())

    handler = Collect()
    loggers = [logging.getLogger(name) for name in ("uvicorn.access", "uvicorn.error")]
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.setLevel(logging.INFO)
        logger.addHandler(handler)
    try:
        yield lines
    finally:
        for logger, level in zip(loggers, levels, strict=True):
            logger.removeHandler(handler)
            logger.setLevel(level)


@pytest.fixture(scope="module")
def page(server, server_log):  # noqa: F811
    driver = make_chromium()
    try:
        # As `telesplat serve` prints it, with the WebSocket transport forced.
        driver.get(f"{server.url}/?transport=ws#token={server.token}")
        yield driver
    finally:
        driver.quit()


def test_page_loads_and_shows_frames(page):
    assert page.title == "Telesplat"
    wait_for(page, "window.telesplat && window.telesplat.framesShown > 0", 60, "a frame")
    # The first frames may be the server's default size, until the page's request lands.
    wait_for(page, "document.getElementById('view').width === 512", 30, "a 512 px frame")
    avatars = page.execute_script(
        "return [...document.querySelectorAll('#avatar option')].map(o => o.value)")
    assert "demo" in avatars
    probe = page.execute_script(CANVAS_PROBE)
    assert (probe["width"], probe["height"]) == (512, 512)  # the page asks for 512 px
    assert probe["std"] > 5 and 0.02 < probe["foreground"] < 0.95, probe  # not blank


def test_stats_overlay_is_visible(page):
    wait_for(page, "window.telesplat.framesShown > 0", 60, "a frame")
    stats = page.find_element("id", "stats")
    assert stats.is_displayed()
    text = wait_for(page, "document.getElementById('stats').innerText.includes('ping:') && "
                          "!/ping: –/.test(document.getElementById('stats').innerText) && "
                          "document.getElementById('stats').innerText", 20, "the ping")
    for label in ("fps:", "latency p50:", "kB/s", "frames:"):
        assert label in text
    assert "transport: websocket" in text


def test_mouse_drag_orbits_and_changes_the_image(page):
    from selenium.webdriver.common.action_chains import ActionChains

    wait_for(page, "window.telesplat.framesShown > 0", 60, "a frame")
    before = page.execute_script(CANVAS_PROBE)
    yaw0 = page.execute_script("return window.telesplat.orbit.orbit.yaw_deg")
    canvas = page.find_element("id", "view")
    chain = ActionChains(page).move_to_element(canvas).click_and_hold()
    for _ in range(6):
        chain = chain.move_by_offset(25, 4).pause(0.05)
    chain.release().perform()
    yaw = page.execute_script("return window.telesplat.orbit.orbit.yaw_deg")
    assert abs(yaw - yaw0) > 30  # 150 px at 0.4 deg/px
    shown = before["shown"]
    wait_for(page, f"window.telesplat.framesShown > {shown}", 30, "a frame after the drag")
    deadline = time.monotonic() + 30
    while True:  # the frame for the last view may need a moment
        after = page.execute_script(CANVAS_PROBE)
        if thumb_diff(before, after) > 2 or time.monotonic() > deadline:
            break
        time.sleep(0.1)
    assert thumb_diff(before, after) > 2, "the image did not change after orbiting"
    assert after["std"] > 5


def test_slider_drives_and_latency_is_measured(page):
    wait_for(page, "window.telesplat.framesShown > 0", 60, "a frame")
    seq = page.execute_script("""
        const input = document.querySelector('input[data-param="jaw open"]');
        input.value = 0.4;
        input.dispatchEvent(new Event('input'));
        return window.telesplat.session.seq;""")
    assert seq >= 1
    wait_for(page, "window.telesplat.stats.latencies.length > 0", 30, "a drive's frame")
    text = wait_for(page, "!/latency p50: –/.test(document.getElementById('stats').innerText)"
                          " && document.getElementById('stats').innerText", 10, "latency")
    assert " ms" in text.split("latency p50:")[1].splitlines()[0]


def test_webcam_toggle_shows_the_servers_answer(page):
    from tests.track_models import models_available

    wait_for(page, "window.telesplat.framesShown > 0", 60, "a frame")
    started = page.execute_script("return performance.now() / 1000")
    page.find_element("id", "webcam").click()  # Chromium's fake camera stands in
    if models_available():  # the server tracks the images: frames keep coming, no error
        before = page.execute_script("return window.telesplat.framesShown")
        wait_for(page, f"window.telesplat.framesShown > {before} + 2", 60,
                 "frames driven by webcam images")
        errors = page.execute_script(
            "return window.telesplat.errors.filter(e => e.answers?.type === 'image')"
            ".map(e => e.code)")
        assert errors == [], errors
        # Each image carries its capture time (the camera's, on the page's clock): the frames
        # tracked from it carry it back, as a drive's do (the voice syncs to them).
        captured = wait_for(page, f"window.telesplat.frameCapture > {started} && "
                                  "window.telesplat.frameCapture", 30,
                            "a frame carrying its image's capture time")
        assert captured < page.execute_script("return performance.now() / 1000")
        # Chromium's built-in test pattern holds no person: the server's `tracked` says so
        # (tests/test_page_status_browser.py plays a person too).
        status = wait_for(page, "window.telesplat.tracked && document.getElementById("
                                "'webcam-status').textContent", 60, "a tracked answer")
        assert status.startswith("no person found"), status
    else:
        status = wait_for(page, "/unsupported/.test(document.getElementById('webcam-status')"
                                ".textContent) && document.getElementById('webcam-status')"
                                ".textContent", 30, "the server's answer to webcam frames")
        assert "unsupported" in status
    page.find_element("id", "webcam").click()
    assert page.find_element("id", "webcam-status").text == "off"


def test_motion_clips_panel(page):
    text = wait_for(page, "!document.getElementById('motions').textContent.startsWith('loading')"
                          " && document.getElementById('motions').textContent", 30, "motions")
    buttons = page.find_elements("css selector", "#motions button[data-motion]")
    if not buttons:
        assert "does not offer motion clips" in text
        pytest.skip("the server has no GET /v1/motions yet: the panel says so")
    seq = page.execute_script("return window.telesplat.session.seq")
    buttons[0].click()
    wait_for(page, f"window.telesplat.session.seq > {seq + 5}", 30, "the clip to drive")


def test_the_token_stays_out_of_urls_and_logs(page, server, server_log):  # noqa: F811
    wait_for(page, "window.telesplat.framesShown > 0", 60, "a frame")
    assert server.token not in page.current_url and "token" not in page.current_url
    assert "token" not in page.execute_script("return window.telesplat.session.url")
    sockets = [line for line in server_log if '"WebSocket /v1/stream' in line]
    assert sockets and all("token" not in line for line in sockets), sockets
    assert not any(server.token in line for line in server_log)


def test_an_old_link_with_a_query_token_still_works(page, server, server_log):  # noqa: F811
    page.get(f"{server.url}/?token={server.token}&avatar=demo&transport=ws")
    wait_for(page, "window.telesplat.framesShown > 0", 60, "a frame")
    assert "token" not in page.current_url and "avatar=demo" in page.current_url
    # Nor does it travel on in the Referer of the page's own requests (scripts, API calls).
    assert page.execute_script(
        "return document.querySelector('meta[name=referrer]').content") == "no-referrer"
    # The first request carried it; the log shows it redacted, and no WebSocket URL has it.
    assert any("GET /?token=[redacted]&avatar=demo" in line for line in server_log), server_log
    sockets = [line for line in server_log if '"WebSocket /v1/stream' in line]
    assert all("token" not in line for line in sockets), sockets
    assert not any(server.token in line for line in server_log)
