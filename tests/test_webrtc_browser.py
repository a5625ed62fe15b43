"""The page over WebRTC in a real headless Chromium against a real server (uvicorn on
127.0.0.1): it WHEPs into a private room, plays the avatar's video track in its <video>, shows
the getStats() figures, drives the mouth over the data channel, and DELETEs its WHEP resource
and its room when it goes away; an invitation link WHEPs with the invitation's token;
?transport=ws still gives the canvas. The overlay's getStats() arithmetic runs in node."""

from __future__ import annotations

import importlib.util
import json
import os
import time

import httpx
import numpy as np
import pytest

from tests.server_fixtures import run_server, server_fixture  # noqa: F401 (`server`)
from tests.test_client_browser import server_log, wait_for  # noqa: F401 (a fixture)
from tests.test_client_units import CHROMEDRIVER, CHROMIUM, chromium_missing, node, run_node
from tests.test_rooms_browser import SIZE, mouth_box

WEB = os.path.join(os.path.dirname(__file__), "..", "client", "web")
NO_BROWSER_TEST = chromium_missing() or (
    "the server has no WebRTC endpoints (server/routers/webrtc.py) yet"
    if importlib.util.find_spec("server.routers.webrtc") is None else None)
browser_test = pytest.mark.skipif(NO_BROWSER_TEST is not None, reason=NO_BROWSER_TEST or "")

# The <video>'s current frame as grey levels, read back through a canvas (drawImage +
# getImageData), with what the page counted.
VIDEO_GREY = """
const video = document.getElementById("video");
const width = video.videoWidth, height = video.videoHeight;
if (!width || !height) return null;
const canvas = document.createElement("canvas");
canvas.width = width; canvas.height = height;
const ctx = canvas.getContext("2d", {willReadFrequently: true});
ctx.drawImage(video, 0, 0);
const data = ctx.getImageData(0, 0, width, height).data;
const grey = new Array(width * height);
for (let i = 0; i < width * height; i++) grey[i] = (data[4*i] + data[4*i+1] + data[4*i+2]) / 3;
return {width, height, grey, shown: window.telesplat.framesShown};
"""


def make_webrtc_chromium():
    """make_chromium's headless Chromium, plus what WebRTC on one machine needs: real host
    candidates instead of mDNS `.local` names (the server's aiortc peer must reach them) and
    a video that starts without a user gesture."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    os.environ.setdefault("SE_OFFLINE", "true")
    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                "--window-size=1280,900", "--mute-audio", "--no-first-run",
                "--disable-background-timer-throttling",
                "--autoplay-policy=no-user-gesture-required",
                "--disable-features=WebRtcHideLocalIpsWithMdns"):
        options.add_argument(arg)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(executable_path=str(CHROMEDRIVER)),
                              options=options)
    driver.set_script_timeout(30)
    driver.set_page_load_timeout(30)
    return driver


def video_grey(driver) -> np.ndarray:
    shot = wait_for(driver, f"(() => {{ {VIDEO_GREY} }})()", 30, "a video frame")
    return np.asarray(shot["grey"], np.float64).reshape(shot["height"], shot["width"])


def wait_playing(driver, size: int = SIZE) -> None:
    wait_for(driver, "window.telesplat?.transport === 'webrtc' && window.telesplat.room", 60,
             "the WebRTC session's welcome")
    wait_for(driver, f"window.telesplat.framesShown > 2 && document.getElementById('video')"
                     f".videoWidth === {size}", 90, f"{size} px frames in the <video>")


@pytest.fixture(scope="module")
def page(server, server_log):  # noqa: F811
    driver = make_webrtc_chromium()
    try:
        driver.get(f"{server.url}/#token={server.token}")  # as `telesplat serve` prints it
        yield driver
    finally:
        driver.quit()


@browser_test
def test_page_plays_the_webrtc_stream_in_its_video(page):
    wait_playing(page)
    assert not page.find_element("id", "view").is_displayed()  # the canvas gives way
    assert page.find_element("id", "video").is_displayed()
    grey = video_grey(page)
    assert grey.shape == (SIZE, SIZE)
    background = grey[0, -1]  # a corner: the backdrop, not the avatar
    foreground = (np.abs(grey - background) > 10).mean()
    assert grey.std() > 5 and 0.02 < foreground < 0.95, (grey.std(), foreground)  # not blank
    room = page.execute_script("return window.telesplat.room")
    assert room["role"] == "perform" and room["seat"] == 0
    assert page.execute_script("return window.telesplat.privateRoom") == room["id"]


@browser_test
def test_overlay_shows_webrtc_and_get_stats(page):
    wait_playing(page)
    text = wait_for(page, "(() => { const t = document.getElementById('stats').innerText;"
                          " return !/bit rate: –/.test(t) && !/decoded: –/.test(t) && t; })()",
                    30, "getStats() figures in the overlay")
    assert "transport: webrtc" in text
    for label in ("fps:", "bit rate:", "decoded:", "dropped:", "jitter:", "rtt:", "frame:"):
        assert label in text, text
    rtc = page.execute_script("return window.telesplat.stats.rtc")
    assert rtc["framesDecoded"] > 0 and rtc["bitrateKbps"] > 0, rtc
    assert rtc["size"] == f"{SIZE}x{SIZE}"


@browser_test
def test_jaw_slider_moves_the_mouth_over_the_data_channel(page, server):  # noqa: F811
    wait_playing(page)
    wait_for(page, "document.querySelector('input[data-param=\"jaw open\"]')", 30, "the sliders")
    x0, y0, x1, y1 = mouth_box(server)
    before = video_grey(page)
    seq = page.execute_script("""
        const input = document.querySelector('input[data-param="jaw open"]');
        input.value = input.max;
        input.dispatchEvent(new Event('input'));
        return window.telesplat.session.seq;""")
    assert seq >= 1
    deadline = time.monotonic() + 60
    while True:  # bounded: the drive's frame comes a few video frames later
        after = video_grey(page)
        diff = np.abs(after - before)
        mouth, torso = diff[y0:y1, x0:x1].mean(), diff[SIZE * 3 // 4:, :].mean()
        if (mouth > 1.0 and mouth > 4 * torso) or time.monotonic() > deadline:
            break
        time.sleep(0.1)
    assert mouth > 1.0 and mouth > 4 * torso, (mouth, torso, (x0, y0, x1, y1))
    assert not page.execute_script("return window.telesplat.errors.map(e => e.code)")


@browser_test
def test_size_menu_resizes_the_video_track(page):
    wait_playing(page)
    page.execute_script("""
        const size = document.getElementById('size');
        size.value = '384';
        size.dispatchEvent(new Event('change'));""")  # a `request` over the data channel
    wait_for(page, "document.getElementById('video').videoWidth === 384", 60, "384 px frames")
    page.execute_script("""
        const size = document.getElementById('size');
        size.value = '512';
        size.dispatchEvent(new Event('change'));""")
    wait_playing(page)


@browser_test
def test_share_turns_the_private_room_into_a_shared_one(page):
    wait_playing(page)
    room = page.execute_script("return window.telesplat.room.id")
    frames = page.execute_script("return window.telesplat.framesShown")
    resource = page.execute_script("return window.telesplat.session.resource")
    page.find_element("id", "share").click()
    watch_url = wait_for(page, "document.querySelector('#share-links [data-scope=watch] "
                               "input')?.value", 60, "the watch link")
    assert f"room={room}" in watch_url and "#token=tsr_" in watch_url
    assert page.execute_script("return window.telesplat.privateRoom") is None  # kept on leave
    assert f"room={room}" in page.current_url and "token" not in page.current_url
    assert page.find_element("id", "room-bar").is_displayed()
    # The same peer goes on: no reconnect for sharing.
    assert page.execute_script("return window.telesplat.session.resource") == resource
    wait_for(page, f"window.telesplat.framesShown > {frames}", 30, "frames after sharing")


@browser_test
def test_transport_ws_still_gives_the_canvas(server):  # noqa: F811
    driver = make_webrtc_chromium()
    try:
        driver.get(f"{server.url}/?transport=ws#token={server.token}")
        wait_for(driver, "window.telesplat?.framesShown > 0", 60, "a canvas frame")
        assert driver.execute_script("return window.telesplat.transport") == "ws"
        assert driver.find_element("id", "view").is_displayed()
        assert not driver.find_element("id", "video").is_displayed()
        text = wait_for(driver, "document.getElementById('stats').innerText", 10, "stats")
        assert "transport: websocket" in text
    finally:
        driver.quit()


@browser_test
def test_invitation_link_watches_over_webrtc(server):  # noqa: F811
    headers = server.headers()
    with httpx.Client(base_url=server.url, headers=headers, timeout=30) as http:
        room = http.post("/v1/rooms", json={"seats": [{"avatar": "demo"}]}).json()
        watch = http.post(f"/v1/rooms/{room['id']}/invitations", json={"scope": "watch"}).json()
    driver = make_webrtc_chromium()
    try:
        driver.get(f"{server.url}{watch['link']}")
        wait_playing(driver)
        joined = driver.execute_script("return window.telesplat.room")
        assert joined["id"] == room["id"] and joined["role"] == "watch"
        assert driver.execute_script("return window.telesplat.privateRoom") is None
        assert not driver.find_element("id", "drive-controls").is_displayed()
        assert video_grey(driver).std() > 5
    finally:
        driver.quit()


@browser_test
def test_leaving_the_page_deletes_the_whep_resource_and_its_room(server, server_log):  # noqa: F811
    driver = make_webrtc_chromium()
    try:
        driver.get(f"{server.url}/#token={server.token}")
        wait_playing(driver)
        room = driver.execute_script("return window.telesplat.privateRoom")
        resource = driver.execute_script("return window.telesplat.session.resource")
        assert room and resource.startswith(f"/v1/rooms/{room}/whep/")
        driver.get("about:blank")  # pagehide: DELETE the WHEP resource and the private room
        with httpx.Client(base_url=server.url, headers=server.headers(), timeout=30) as http:
            deadline = time.monotonic() + 30
            while http.get(f"/v1/rooms/{room}").status_code != 404:
                assert time.monotonic() < deadline, "the page's private room outlived it"
                time.sleep(0.1)
        deadline = time.monotonic() + 30
        while not any(f"DELETE {resource}" in line for line in server_log):
            assert time.monotonic() < deadline, f"no DELETE {resource} in {server_log[-20:]}"
            time.sleep(0.1)
    finally:
        driver.quit()


@browser_test
def test_a_refused_whep_falls_back_to_the_websocket(tmp_path):
    """With one WebRTC peer allowed, a second page's WHEP gets 503: it says so, gives its
    private room back and streams over the WebSocket instead."""
    def room_ids() -> set[str]:
        with httpx.Client(base_url=srv.url, headers=srv.headers(), timeout=30) as http:
            body = http.get("/v1/rooms").json()
        return {room["id"] for room in (body["rooms"] if isinstance(body, dict) else body)}

    with run_server(tmp_path, webrtc_max_peers=1) as srv:
        driver = make_webrtc_chromium()
        try:
            driver.get(f"{srv.url}/#token={srv.token}")
            wait_playing(driver)  # this tab holds the one peer
            rooms = room_ids()
            driver.switch_to.new_window("tab")
            driver.get(f"{srv.url}/#token={srv.token}")
            wait_for(driver, "window.telesplat?.transport === 'ws' && "
                             "window.telesplat.framesShown > 0", 90, "WebSocket frames")
            assert "503" in driver.find_element("id", "messages").text
            assert driver.find_element("id", "view").is_displayed()
            assert not driver.find_element("id", "video").is_displayed()
            assert driver.execute_script("return window.telesplat.privateRoom") is None
            deadline = time.monotonic() + 30
            while room_ids() != rooms:  # the second tab's private room is given back
                assert time.monotonic() < deadline, (room_ids(), rooms)
                time.sleep(0.1)
        finally:
            driver.quit()


# -- the overlay's getStats() arithmetic (node, no browser) ----------------------------------


def stats_report(t_ms: float, bytes_received: int, decoded: int) -> list[list]:
    """A getStats() report as [id, entry] pairs (node builds the Map)."""
    return [
        ["IT01V", {"type": "inbound-rtp", "kind": "video", "timestamp": t_ms,
                   "bytesReceived": bytes_received, "framesDecoded": decoded,
                   "framesDropped": 2, "jitter": 0.004, "codecId": "CIT01_96",
                   "frameWidth": 512, "frameHeight": 512}],
        ["CIT01_96", {"type": "codec", "mimeType": "video/VP8"}],
        ["T01", {"type": "transport", "selectedCandidatePairId": "CP1"}],
        ["CP1", {"type": "candidate-pair", "currentRoundTripTime": 0.003}],
        ["CP2", {"type": "candidate-pair", "currentRoundTripTime": 0.5}],
    ]


@pytest.mark.skipif(node() is None, reason="node is not installed")
def test_rtc_stats_rates_from_two_samples():
    script = f"""
    import {{ rtcSample, rtcSummary }} from "{os.path.abspath(WEB)}/rtcstats.js";
    const a = rtcSample(new Map({json.dumps(stats_report(1000, 10_000, 30))}));
    const b = rtcSample(new Map({json.dumps(stats_report(3000, 260_000, 90))}));
    const none = rtcSample(new Map([["x", {{type: "candidate-pair"}}]]));
    console.log(JSON.stringify({{first: rtcSummary(null, a), second: rtcSummary(a, b), none}}));
    """
    out = json.loads(run_node(script))
    first, second = out["first"], out["second"]
    assert first["bitrateKbps"] is None and first["fps"] is None  # one sample: no rates yet
    assert second["bitrateKbps"] == pytest.approx(8 * 250_000 / 2 / 1000)  # 1000 kbit/s
    assert second["fps"] == pytest.approx(30)
    assert second["codec"] == "VP8" and second["size"] == "512x512"
    assert second["rttMs"] == pytest.approx(3) and second["jitterMs"] == pytest.approx(4)
    assert second["framesDropped"] == 2
    assert out["none"] is None  # no video yet
