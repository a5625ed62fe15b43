"""The page's status and feedback (issue 26) in a real headless Chromium against a real
server: named expression sliders, the stats overlay (under the picture, a remembered toggle,
"idle"), the status line in a room and after Share, display names in presence, the token
field after a 401, the webcam's "no person found" / "tracking" from Chromium's fake camera
playing a generated video, and the WebRTC overlay's drive -> frame latency."""

from __future__ import annotations

import asyncio
import json
import os

import cv2
import numpy as np
import pytest

from avatar_core.synth.humanoid.build import EXPRESSION_NAMES
from tests.browser_fixtures import browser_fixture  # noqa: F401 (`browser`)
from tests.server_fixtures import is_type, recv_until, server_fixture  # noqa: F401 (`server`)
from tests.test_client_browser import wait_for
from tests.test_client_units import chromium_missing, make_chromium, node, run_node
from tests.test_server_rooms import create_room, invite, join
from tests.test_webrtc_browser import NO_BROWSER_TEST, make_webrtc_chromium
from tests.track_models import needs_models

pytestmark = pytest.mark.skipif(chromium_missing() is not None,
                                reason=chromium_missing() or "")
WEB = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "client", "web"))
WAIT_S = 60.0  # each browser wait (bounded)


def text_of(driver, element_id: str) -> str:
    return driver.execute_script(f"return document.getElementById('{element_id}').innerText")


def set_slider(driver, param: str, value: float) -> int:
    """Move the slider `param` as a user would; the session's seq after it."""
    return driver.execute_script(f"""
        const input = document.querySelector('input[data-param="{param}"]');
        input.value = {value};
        input.dispatchEvent(new Event('input'));
        return window.telesplat.session.seq;""")


def open_page(driver, server, query: str = "transport=ws") -> None:  # noqa: F811
    driver.get(f"{server.url}/?{query}#token={server.token}")
    wait_for(driver, "window.telesplat.framesShown > 0", WAIT_S, "a frame")


# -- 1. named expression sliders -----------------------------------------------------------


def test_expression_sliders_carry_the_avatars_names(server, browser):  # noqa: F811
    open_page(browser, server)
    labels = wait_for(browser, "[...document.querySelectorAll('#sliders .slider span')]"
                               ".map(s => s.textContent)", WAIT_S, "the sliders")
    named = [label for label in labels if label in EXPRESSION_NAMES]
    assert named == list(EXPRESSION_NAMES), labels
    assert not any(label.startswith("expression ") for label in labels), labels
    # A named slider drives its own coefficient: its frame comes back with the drive's seq.
    seq = set_slider(browser, EXPRESSION_NAMES[0], 1.2)
    wait_for(browser, f"window.telesplat.stats.latencies.length > 0 && "
                      f"window.telesplat.session.seq === {seq}", WAIT_S, "the drive's frame")


def test_sliders_fall_back_to_numbers_without_names():
    """An official body model names no expressions: ten sliders "expression 0" … "9" (node,
    with a stand-in container: the page's Controls class as it is)."""
    if node() is None:
        pytest.skip("node is not installed")
    script = f"""
    const made = [];
    const el = (tag) => {{ const e = {{ tag, children: [], dataset: {{}},
      append(...c) {{ this.children.push(...c); }}, addEventListener() {{}} }};
      made.push(e); return e; }};
    globalThis.document = {{ createElement: el }};
    const {{ Controls }} = await import("{WEB}/controls.js");
    const container = {{ children: [], replaceChildren() {{ this.children = []; }},
                         append(c) {{ this.children.push(c); }} }};
    const c = new Controls(container, () => {{}});
    const labels = () => container.children.map((row) => row.children[0].textContent);
    c.build([]);
    const unnamed = labels();
    c.build(["smile", "frown", "blink"]);
    console.log(JSON.stringify({{ unnamed, named: labels(), size: c.expression.length }}));
    """
    out = json.loads(run_node(script))
    assert [x for x in out["unnamed"] if x.startswith("expression")] == \
        [f"expression {i}" for i in range(10)]
    assert [x for x in out["named"] if x in ("smile", "frown", "blink")] == \
        ["smile", "frown", "blink"] and out["size"] == 3
    assert not any(x.startswith("expression") for x in out["named"])


# -- 2. the stats overlay --------------------------------------------------------------------


def test_stats_sit_under_the_picture_and_the_toggle_is_remembered(server, browser):  # noqa: F811
    open_page(browser, server)
    wait_for(browser, "document.getElementById('view').width === 512", WAIT_S, "512 px")
    picture, stats = browser.execute_script(
        "return ['view', 'stats'].map(id => document.getElementById(id)"
        ".getBoundingClientRect().toJSON())")
    assert stats["height"] > 0 and stats["top"] >= picture["bottom"] - 0.5, (picture, stats)
    # As wide as the picture, which stays where it was (the stats do not widen the stage).
    assert abs(stats["left"] - picture["left"]) < 1 and abs(stats["width"] - picture["width"]) < 1
    stage = browser.execute_script(
        "return document.getElementById('stage').getBoundingClientRect().toJSON()")
    assert abs(stage["width"] - picture["width"]) < 1, (stage, picture)
    toggle = browser.find_element("id", "stats-toggle")
    assert toggle.is_selected()
    toggle.click()
    assert not browser.find_element("id", "stats").is_displayed()
    browser.refresh()  # remembered (localStorage), the token taken from memory is gone:
    assert not browser.find_element("id", "stats-toggle").is_selected()
    assert not browser.find_element("id", "stats").is_displayed()
    browser.find_element("id", "stats-toggle").click()
    assert browser.execute_script("return localStorage.getItem('telesplat.stats')") == "shown"


def test_idle_reads_idle_never_fps_zero(server, browser):  # noqa: F811
    open_page(browser, server)
    text = wait_for(browser, "/fps: idle/.test(document.getElementById('stats').innerText) && "
                             "document.getElementById('stats').innerText", WAIT_S, "idle")
    assert "fps: 0.0" not in text
    # Driving again brings the rate back.
    set_slider(browser, "jaw open", 0.3)
    wait_for(browser, "/fps: \\d+\\.\\d/.test(document.getElementById('stats').innerText)",
             WAIT_S, "a rate after a drive")


# -- 4 and 5. the status line, display names in presence ---------------------------------------


def test_share_says_room_once_and_presence_shows_names(server, browser):  # noqa: F811
    open_page(browser, server, "transport=ws&name=Ann")
    assert "session" in text_of(browser, "status")
    browser.find_element("id", "share").click()
    wait_for(browser, "document.querySelector('#share-links [data-scope=watch]')", WAIT_S,
             "the share links")
    status = text_of(browser, "status")
    assert "room" in status and "session" not in status and "room room" not in status, status
    assert "performing seat 0" in status
    room_id = browser.execute_script("return window.telesplat.room.id")
    watch = invite(server, room_id, "watch")

    async def watch_a_while():
        async with join(server, room_id, watch["token"]) as viewer:  # no name: "viewer 1"
            presence = await recv_until(viewer, is_type("presence"))
            assert presence.seats[0].performer == "Ann"
            await asyncio.to_thread(wait_for, browser, "/viewer 1 joined \\(watching\\)/"
                                    ".test(document.getElementById('messages').innerText)",
                                    WAIT_S, "the join note")
            return text_of(browser, "presence")
    line = asyncio.run(watch_a_while())
    assert "seat 0 (demo): Ann performing" in line and "1 watching" in line, line
    assert "whep-" not in line and "telesplat-web" not in line


def test_a_named_room_reads_room_name_not_room_room(server, browser):  # noqa: F811
    unnamed = create_room(server)  # its name is "room <id>": never "room room <id>"
    browser.get(f"{server.url}/?transport=ws&room={unnamed['id']}#token={server.token}")
    wait_for(browser, "window.telesplat.room", WAIT_S, "the room's welcome")
    status = text_of(browser, "status")
    assert f"{unnamed['name']} (performing seat 0)" in status and "room room" not in status


def test_a_bad_stored_name_is_refused_on_the_page(server, browser):  # noqa: F811
    room = create_room(server)
    browser.get(f"{server.url}/?transport=ws&room={room['id']}#token={server.token}")
    wait_for(browser, "window.telesplat.room", WAIT_S, "the room's welcome")
    field = browser.find_element("id", "my-name")
    field.send_keys("<b>x</b>\n")
    wait_for(browser, "/cannot use that name/.test(document.getElementById('messages')"
                      ".innerText)", WAIT_S, "the refusal")
    assert browser.execute_script("return localStorage.getItem('telesplat.name')") is None
    field.clear()
    field.send_keys("Bea\n")  # stored, and the page joins again under it
    wait_for(browser, "window.telesplat.presence?.seats[0].performer === 'Bea'", WAIT_S,
             "presence under the new name")
    assert browser.execute_script("return localStorage.getItem('telesplat.name')") == "Bea"


# -- 6. the token field after a 401 ------------------------------------------------------------


def test_a_refused_token_offers_a_field_that_recovers(server, browser):  # noqa: F811
    browser.get(f"{server.url}/?transport=ws#token=not-a-valid-token")
    wait_for(browser, "!document.getElementById('token-form').hidden", WAIT_S, "the token field")
    assert "401" in text_of(browser, "token-form") or "refused" in text_of(browser, "token-form")
    form = browser.find_element("id", "token-form")
    form.find_element("css selector", "button").click()  # empty: says so, stays
    assert "paste a token" in text_of(browser, "token-form")
    form.find_element("id", "token-input").send_keys(server.token + "\n")
    wait_for(browser, "window.telesplat.framesShown > 0", WAIT_S, "frames with the new token")
    assert browser.execute_script("return document.getElementById('token-form').hidden")
    assert "token" not in browser.current_url  # taken into memory, as a #token= link is


# -- 7. webcam: "no person found" and "tracking" from a fake camera ------------------------------


def write_y4m(path, bgr: np.ndarray, frames: int = 3) -> str:
    """A raw YUV 4:2:0 video Chromium's fake camera plays in a loop."""
    height, width = bgr.shape[:2]
    yuv = cv2.cvtColor(bgr, cv2.COLOR_BGR2YUV_I420)
    with open(path, "wb") as out:
        out.write(f"YUV4MPEG2 W{width} H{height} F10:1 Ip A1:1 C420jpeg\n".encode())
        for _ in range(frames):
            out.write(b"FRAME\n" + yuv.tobytes())
    return str(path)


def person_frame() -> np.ndarray:
    """scikit-image's astronaut (head and shoulders), centred on a grey 640 x 480 frame."""
    from skimage.data import astronaut

    frame = np.full((480, 640, 3), 128, np.uint8)
    frame[:, 80:560] = cv2.resize(astronaut()[..., ::-1], (480, 480))
    return frame


@needs_models
@pytest.mark.parametrize("scene", ["empty", "person"])
def test_webcam_says_whether_a_person_is_found(server, tmp_path, scene):  # noqa: F811
    picture = person_frame() if scene == "person" else np.full((480, 640, 3), 128, np.uint8)
    driver = make_chromium(camera_file=write_y4m(tmp_path / f"{scene}.y4m", picture))
    try:
        open_page(driver, server)
        driver.find_element("id", "webcam").click()
        status = wait_for(driver, "window.telesplat.tracked && "
                                  "document.getElementById('webcam-status').textContent",
                          WAIT_S, "the server's first tracked answer")
        if scene == "empty":
            assert status.startswith("no person found"), status
        else:
            status = wait_for(driver, "/^tracking/.test(document.getElementById("
                                      "'webcam-status').textContent) && document."
                                      "getElementById('webcam-status').textContent",
                              WAIT_S, "tracking")
            assert "face" in status, status
        driver.find_element("id", "webcam").click()
        assert text_of(driver, "webcam-status") == "off"
    finally:
        driver.quit()


# -- 3. WebRTC: drive -> frame latency from frame stamps --------------------------------------


@pytest.mark.skipif(NO_BROWSER_TEST is not None, reason=NO_BROWSER_TEST or "")
def test_webrtc_overlay_shows_drive_to_frame_latency(server):  # noqa: F811
    driver = make_webrtc_chromium()
    try:
        driver.get(f"{server.url}/?name=Cy#token={server.token}")
        wait_for(driver, "window.telesplat.transport === 'webrtc' && window.telesplat.room",
                 90, "the WebRTC welcome")
        for step in range(5):  # a few drives, each a frame whose stamp names it
            set_slider(driver, "jaw open", 0.1 * (step + 1))
            driver.execute_script("return new Promise(r => setTimeout(r, 300))")
        text = wait_for(driver, "(() => { const t = document.getElementById('stats').innerText;"
                                " return /latency p50: \\d+ ms/.test(t) && t; })()", 90,
                        "the latency in the WebRTC overlay")
        assert "transport: webrtc" in text and "latency p95:" in text
        latencies = driver.execute_script("return window.telesplat.stats.latencies"
                                          ".map(([, ms]) => ms)")
        assert latencies and all(0 <= ms < 30000 for ms in latencies), latencies
        # The strip that carries the stamp is clipped off the picture.
        assert driver.execute_script(
            "return document.getElementById('video').style.clipPath").startswith("inset(")
        # Share: the status line says room now, no longer session.
        driver.find_element("id", "share").click()
        wait_for(driver, "document.querySelector('#share-links [data-scope=watch]')", WAIT_S,
                 "the share links")
        status = text_of(driver, "status")
        assert "room" in status and "session" not in status and "room room" not in status
    finally:
        driver.quit()


def test_webrtc_names_reach_presence(server):  # noqa: F811
    """A WHEP participant's ?name= is what presence shows (default "performer")."""
    room = create_room(server)
    driver = make_webrtc_chromium()
    try:
        driver.get(f"{server.url}/?room={room['id']}&name=Dee#token={server.token}")
        wait_for(driver, "window.telesplat.transport === 'webrtc' && window.telesplat.room",
                 90, "the WebRTC welcome")
        watch = invite(server, room["id"], "watch")

        async def look():
            async with join(server, room["id"], watch["token"]) as viewer:
                return await recv_until(viewer, is_type("presence"))
        presence = asyncio.run(look())
        assert presence.seats[0].performer == "Dee"
    finally:
        driver.quit()


def test_stamp_reader_matches_the_servers_stamps():
    """rtcstats.js reads what protocol/stamp.py writes, also after JPEG compression."""
    if node() is None:
        pytest.skip("node is not installed")
    from protocol.stamp import cell_size, stamp

    seqs = [0, 1, 5, 4095, 123456, 0xFFFFFE]
    strips = []
    for seq in seqs:
        rgb = stamp(np.full((64, 256, 3), 90, np.uint8), seq)
        ok, jpeg = cv2.imencode(".jpg", rgb[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 60])
        back = cv2.imdecode(jpeg, cv2.IMREAD_COLOR)[..., ::-1]
        cell = cell_size(256)
        rgba = np.concatenate([back[:cell, :32 * cell], np.full((cell, 32 * cell, 1), 255,
                                                                np.uint8)], axis=2)
        strips.append(rgba.reshape(-1).tolist())
    blank = [255] * (4 * 8 * 256)
    script = f"""
    import {{ readStamp, stampCell }} from "{WEB}/rtcstats.js";
    const strips = JSON.parse(await new Promise((ok) => {{ let s = "";
      process.stdin.on("data", (d) => {{ s += d; }}); process.stdin.on("end", () => ok(s)); }}));
    console.log(JSON.stringify({{ read: strips.map((s) => readStamp(s, stampCell(256))),
      blank: readStamp({blank}, 8), cells: [stampCell(512), stampCell(63), stampCell(64)] }}));
    """
    out = json.loads(run_node(script, json.dumps(strips)))
    assert out["read"] == seqs
    assert out["blank"] is None and out["cells"] == [8, 0, 2]

