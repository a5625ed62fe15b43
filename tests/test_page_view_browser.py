"""The page's view controls in a real headless Chromium (1280x720) against a real server: the
default view frames the whole upper body at rest from the welcome's framing, the wheel zooms
toward the face without ever cutting the head, shift- and right-drag pan, the button and a
double-click reset; the picture fits the window at every size; fullscreen, a PNG snapshot, a
WebM recording (stopped by hand or by its length limit) and the background colour, over the
WebSocket here and over WebRTC in the second half."""

from __future__ import annotations

import json
import os
import time

import numpy as np
import pytest
import torch

from avatar_core.render.camera import orbit
from avatar_core.render.camera_path import NECK_JOINT, framing_target
from protocol import Orbit, View
from server.stream.drive import DriveState
from server.stream.scene import view_camera
from tests.server_fixtures import server_fixture  # noqa: F401 (the `server` fixture)
from tests.test_client_browser import CANVAS_PROBE, thumb_diff, wait_for
from tests.test_client_units import chromium_missing, make_chromium, node, run_node
from tests.test_webrtc_browser import NO_BROWSER_TEST, WEB, make_webrtc_chromium, wait_playing

browser_test = pytest.mark.skipif(chromium_missing() is not None,
                                  reason=chromium_missing() or "")

SIZES = (256, 384, 512, 768)
EBML = "1a45dfa3"  # the first four bytes of every WebM (Matroska) file
PNG = "89504e470d0a1a0a"


@pytest.fixture(scope="module")
def page(server):  # noqa: F811
    driver = make_chromium(1280, 720)
    try:
        driver.get(f"{server.url}/?transport=ws#token={server.token}")
        wait_for(driver, "window.telesplat?.session?.welcome && window.telesplat.framesShown > 0",
                 90, "the first frame")
        yield driver
    finally:
        driver.quit()


def orbit_of(page) -> dict:
    return page.execute_script("return window.telesplat.orbit.current()")


def rest_mesh(server) -> tuple[np.ndarray, np.ndarray]:
    """(vertices [V, 3], joints [J, 3]) of the demo avatar as a new session poses it."""
    animator = server.ctx.registry.open("demo").animator
    params = DriveState().smplx_params(animator.body_model, {})
    params["betas"] = animator.betas
    with torch.no_grad():
        out = animator.body_model(params)
    return out.vertices[0].numpy(), out.joints[0].numpy()


def pixels(server, orbit: dict, points: np.ndarray, size: int = 512) -> np.ndarray:
    """Where ``points`` land in a ``size`` px frame of the page's orbit (the server's camera)."""
    chest = framing_target(server.ctx.registry.open("demo").animator.body_model.joint_template)
    camera = view_camera(View(orbit=Orbit(**orbit)), size, size, chest)
    cam = points @ camera.R.T + camera.t
    uv = cam @ camera.K.T
    return uv[:, :2] / uv[:, 2:]


def inside(uv: np.ndarray, size: int = 512) -> bool:
    return bool(((uv >= 0) & (uv <= size)).all())


def head_points(server) -> np.ndarray:
    vertices, joints = rest_mesh(server)
    return vertices[vertices[:, 1] > joints[NECK_JOINT, 1]]


def wheel(page, delta_y: float, times: int = 1) -> None:
    page.execute_script("""
        for (let i = 0; i < arguments[1]; i++) document.getElementById('view').dispatchEvent(
          new WheelEvent('wheel', {deltaY: arguments[0], bubbles: true, cancelable: true}));""",
                        delta_y, times)


def settled_probe(page, previous: dict | None = None, changed: bool = True) -> dict:
    """The canvas once it shows the newest view: changed from ``previous`` (or, ``changed``
    False, no longer changed), else once no new frame came for 0.5 s (bounded waits)."""
    deadline = time.monotonic() + 30
    shown, quiet_since = -1, time.monotonic()
    while True:
        probe = page.execute_script(CANVAS_PROBE)
        if probe["shown"] != shown:
            shown, quiet_since = probe["shown"], time.monotonic()
        if previous is not None and (thumb_diff(previous, probe) > 2 if changed
                                     else thumb_diff(previous, probe) < 1):
            return probe
        if previous is None and time.monotonic() - quiet_since > 0.5:
            return probe
        if time.monotonic() > deadline:
            return probe
        time.sleep(0.05)


@browser_test
def test_default_view_frames_the_whole_upper_body(page, server):  # noqa: F811
    framing = page.execute_script("return window.telesplat.session.welcome.framing")
    orbit = orbit_of(page)
    assert orbit["target"] == pytest.approx(framing["target"])
    assert orbit["distance"] == pytest.approx(framing["distance"])
    vertices, joints = rest_mesh(server)
    uv = pixels(server, orbit, vertices)
    assert inside(uv), (uv.min(0), uv.max(0))  # head to the cut and both hands, every vertex
    # ... and it fills the frame: the body spans most of its height (not the old small figure)
    assert uv[:, 1].max() - uv[:, 1].min() > 0.8 * 512
    assert orbit["yaw_deg"] == 0 and orbit["pitch_deg"] == 0


@browser_test
def test_wheel_zooms_toward_the_face_and_never_cuts_the_head(page, server):  # noqa: F811
    page.find_element("id", "reset-view").click()
    framing = page.execute_script("return window.telesplat.session.welcome.framing")
    head = head_points(server)
    distances, heights = [], []
    for _ in range(14):  # 14 notches in: well past the closest zoom
        wheel(page, -100)
        orbit = orbit_of(page)
        distances.append(orbit["distance"])
        heights.append(orbit["target"][1])
        assert inside(pixels(server, orbit, head)), orbit  # the whole head, at every zoom
    assert all(b <= a for a, b in zip(distances, distances[1:], strict=False))
    assert all(b >= a for a, b in zip(heights, heights[1:], strict=False))  # up, toward the face
    assert distances[-1] == pytest.approx(framing["min_distance"])  # stops there
    assert orbit_of(page)["target"] == pytest.approx(framing["face"])  # aimed at the face
    face = pixels(server, orbit_of(page), np.asarray([framing["face"]]))[0]
    assert np.allclose(face, 256, atol=1)  # the face is the centre of the picture
    probe = settled_probe(page)
    assert probe["foreground"] > 0.3  # close up: the head fills much of the frame
    wheel(page, 100, 30)  # out again, past the default: the target stays the framing's
    assert orbit_of(page)["target"] == pytest.approx(framing["target"])
    assert orbit_of(page)["distance"] > framing["distance"]
    page.find_element("id", "reset-view").click()


@browser_test
def test_pan_by_shift_drag_and_right_drag_then_reset(page):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.keys import Keys

    page.find_element("id", "reset-view").click()
    home = orbit_of(page)
    before = settled_probe(page)
    canvas = page.find_element("id", "view")
    ActionChains(page).move_to_element(canvas).key_down(Keys.SHIFT).click_and_hold() \
        .move_by_offset(60, 0).pause(0.05).move_by_offset(60, 40).release() \
        .key_up(Keys.SHIFT).perform()
    panned = orbit_of(page)
    # dragged right and down: the avatar follows, so the target moves left (-x) and up (+y)
    assert panned["target"][0] < home["target"][0] - 0.1
    assert panned["target"][1] > home["target"][1] + 0.03
    assert panned["yaw_deg"] == home["yaw_deg"]  # a pan, not an orbit
    moved = settled_probe(page, before)
    assert thumb_diff(before, moved) > 2
    # The right button pans too (pointer events as the browser sends them).
    page.execute_script("""
        const c = document.getElementById('view');
        const at = (x, y, buttons) => ({clientX: x, clientY: y, button: 2, buttons,
                                        pointerId: 1, bubbles: true, cancelable: true});
        c.dispatchEvent(new PointerEvent('pointerdown', at(300, 300, 2)));
        c.dispatchEvent(new PointerEvent('pointermove', at(300, 360, 2)));
        c.dispatchEvent(new PointerEvent('pointerup', at(300, 360, 0)));""")
    right = orbit_of(page)
    assert right["target"][1] > panned["target"][1] + 0.03  # dragged down: target up
    assert right["target"][0] == pytest.approx(panned["target"][0])
    page.find_element("id", "reset-view").click()
    assert orbit_of(page) == home
    back = settled_probe(page, before, changed=False)
    assert thumb_diff(before, back) < 1
    # A double-click resets as well, orbit included.
    ActionChains(page).move_to_element(canvas).click_and_hold().move_by_offset(80, 0) \
        .release().perform()
    assert orbit_of(page)["yaw_deg"] != 0
    ActionChains(page).double_click(canvas).perform()
    assert orbit_of(page) == home


@browser_test
def test_picture_fits_the_window_at_every_size(page):
    from selenium.webdriver.support.ui import Select

    for size in SIZES:
        Select(page.find_element("id", "size")).select_by_visible_text(str(size))
        wait_for(page, f"document.getElementById('view').width === {size}", 30, f"{size} px")
        rect, width, height = page.execute_script("""
            const r = document.getElementById('view').getBoundingClientRect();
            return [r.toJSON(), window.innerWidth, window.innerHeight];""")
        assert rect["top"] >= 0 and rect["left"] >= 0, rect
        assert rect["bottom"] <= height and rect["right"] <= width, (size, rect, height)
        assert rect["width"] == pytest.approx(rect["height"], abs=1)  # the aspect is kept
        bar = page.execute_script(
            "return document.getElementById('view-bar').getBoundingClientRect().toJSON()")
        assert bar["bottom"] <= height, bar  # the buttons under it stay in view too
    assert rect["height"] < 768  # at 768 it is scaled down to fit
    Select(page.find_element("id", "size")).select_by_visible_text("512")
    wait_for(page, "document.getElementById('view').width === 512", 30, "512 px")


@browser_test
def test_fullscreen_button_puts_the_stage_in_fullscreen(page):
    page.find_element("id", "fullscreen").click()
    wait_for(page, "document.fullscreenElement?.id === 'stage'", 10, "fullscreen")
    assert page.find_element("id", "fullscreen").text == "Exit fullscreen"
    rect, width, height = page.execute_script("""
        const r = document.getElementById('view').getBoundingClientRect();
        return [r.toJSON(), window.innerWidth, window.innerHeight];""")
    assert rect["bottom"] <= height and rect["right"] <= width
    page.find_element("id", "fullscreen").click()
    wait_for(page, "document.fullscreenElement === null", 10, "fullscreen to end")
    assert page.find_element("id", "fullscreen").text == "Fullscreen"


def blob_facts(page, kind: str) -> dict:
    """The newest saved capture of ``kind``: size, type, first bytes and, for an image, the
    size it decodes to."""
    return page.execute_async_script("""
        const [kind, done] = arguments;
        const saved = window.telesplat.saved.filter(s => s.kind === kind).at(-1);
        const head = new Uint8Array(await saved.blob.slice(0, 8).arrayBuffer());
        const hex = [...head].map(b => b.toString(16).padStart(2, '0')).join('');
        let decoded = null;
        if (kind === 'snapshot') {
          const bitmap = await createImageBitmap(saved.blob);
          decoded = [bitmap.width, bitmap.height];
        }
        const link = document.querySelector(`#saved a[data-kind="${kind}"]`);
        done({size: saved.blob.size, type: saved.blob.type, hex, decoded,
              width: saved.width, height: saved.height, seconds: saved.seconds,
              link: link && link.download, href: link && link.href});""", kind)


def saved_count(page, kind: str) -> int:
    return page.execute_script(
        f"return window.telesplat.saved.filter(s => s.kind === '{kind}').length")


@browser_test
def test_snapshot_saves_a_png_of_the_frame(page):
    n = saved_count(page, "snapshot")
    page.find_element("id", "snapshot").click()
    wait_for(page, f"window.telesplat.saved.filter(s => s.kind === 'snapshot').length > {n}",
             10, "the snapshot")
    facts = blob_facts(page, "snapshot")
    size = page.execute_script("return document.getElementById('view').width")
    assert facts["hex"] == PNG and facts["type"] == "image/png"
    assert facts["decoded"] == [size, size]  # the frame's own size, not the CSS size
    assert facts["link"].endswith(".png") and facts["href"].startswith("blob:")


@browser_test
def test_record_saves_a_webm_and_stops_at_its_length_limit(page, server):  # noqa: F811
    n = saved_count(page, "recording")
    page.find_element("id", "record").click()
    assert page.find_element("id", "record").text == "Stop recording"
    wheel(page, -100, 2)  # something changes while it records
    # its first chunk comes a second in: past the 1 s the length check below needs
    wait_for(page, "window.telesplat.capture.recordedChunks >= 1", 15, "a second recorded")
    page.find_element("id", "record").click()
    wait_for(page, f"window.telesplat.saved.filter(s => s.kind === 'recording').length > {n}",
             15, "the recording")
    facts = blob_facts(page, "recording")
    assert facts["size"] > 0 and facts["hex"].startswith(EBML), facts
    assert facts["link"].endswith(".webm") and 1.0 < facts["seconds"] < 10
    assert page.find_element("id", "record").text == "Record"
    page.find_element("id", "reset-view").click()
    # ?record_s=1: the recording stops by itself after a second.
    page.get(f"{server.url}/?transport=ws&record_s=1#token={server.token}")
    wait_for(page, "window.telesplat?.framesShown > 0", 60, "a frame")
    page.find_element("id", "record").click()
    wait_for(page, "window.telesplat.saved.some(s => s.kind === 'recording')", 15,
             "the recording to stop by itself")
    facts = blob_facts(page, "recording")
    assert facts["hex"].startswith(EBML) and 0.9 < facts["seconds"] < 3, facts
    # A bad limit is said, and the default used.
    page.get(f"{server.url}/?transport=ws&record_s=9999#token={server.token}")
    text = wait_for(page, "document.getElementById('messages').textContent.includes('record_s')"
                          " && document.getElementById('messages').textContent", 20,
                    "the record_s message")
    assert "1 to 300 seconds" in text
    assert page.execute_script("return window.telesplat.capture.maxSeconds") == 30


def corner_rgb(page) -> list[int]:
    return page.execute_script("""
        const c = document.getElementById('view');
        return [...c.getContext('2d').getImageData(1, 1, 1, 1).data.slice(0, 3)];""")


def pick_background(page, hex_colour: str) -> None:
    page.execute_script("""
        const input = document.getElementById('background');
        input.value = arguments[0];
        input.dispatchEvent(new Event('input', {bubbles: true}));""", hex_colour)


@browser_test
def test_background_colour_changes_the_frames_corners(page, server):  # noqa: F811
    page.get(f"{server.url}/?transport=ws#token={server.token}")
    wait_for(page, "window.telesplat?.framesShown > 0", 60, "a frame")
    assert page.execute_script("return document.getElementById('background').value") == "#ffffff"
    wait_for(page, "(() => { const d = document.getElementById('view').getContext('2d')"
                   ".getImageData(1, 1, 1, 1).data; return d[0] > 240 && d[2] > 240; })()",
             30, "the server's white background")
    pick_background(page, "#d01010")
    wait_for(page, "(() => { const d = document.getElementById('view').getContext('2d')"
                   ".getImageData(1, 1, 1, 1).data; return d[0] > 180 && d[1] < 50; })()",
             30, "a red background")
    r, g, b = corner_rgb(page)
    assert abs(r - 0xd0) < 12 and g < 30 and b < 30, (r, g, b)
    # A new size keeps the chosen colour (the page sends it with every request).
    from selenium.webdriver.support.ui import Select

    Select(page.find_element("id", "size")).select_by_visible_text("256")
    wait_for(page, "document.getElementById('view').width === 256", 30, "256 px")
    r, g, b = corner_rgb(page)
    assert r > 180 and g < 50, (r, g, b)


# -- over WebRTC: the <video> instead of the canvas -------------------------------------------

webrtc_test = pytest.mark.skipif(NO_BROWSER_TEST is not None, reason=NO_BROWSER_TEST or "")

VIDEO_CORNER = """
const video = document.getElementById('video');
if (!video.videoWidth) return null;
const c = document.createElement('canvas');
c.width = video.videoWidth; c.height = video.videoHeight;
const ctx = c.getContext('2d');
ctx.drawImage(video, 0, 0);
// the bottom-right corner: the top-left strip carries the frame's stamp (rtcstats.js)
return [...ctx.getImageData(c.width - 3, c.height - 3, 1, 1).data.slice(0, 3)];
"""


@pytest.fixture(scope="module")
def rtc_page(server):  # noqa: F811
    driver = make_webrtc_chromium()
    try:
        driver.get(f"{server.url}/?transport=webrtc&record_s=2#token={server.token}")
        yield driver
    finally:
        driver.quit()


@webrtc_test
def test_webrtc_snapshot_recording_and_background(rtc_page):
    from tests.test_rooms_browser import SIZE

    wait_playing(rtc_page)
    rtc_page.find_element("id", "snapshot").click()
    wait_for(rtc_page, "window.telesplat.saved.some(s => s.kind === 'snapshot')", 10, "snapshot")
    facts = blob_facts(rtc_page, "snapshot")
    assert facts["hex"] == PNG and facts["decoded"] == [SIZE, SIZE]
    rtc_page.find_element("id", "record").click()  # stops by itself after 2 s (record_s=2)
    wait_for(rtc_page, "window.telesplat.saved.some(s => s.kind === 'recording')", 15,
             "the recording")
    facts = blob_facts(rtc_page, "recording")
    assert facts["size"] > 0 and facts["hex"].startswith(EBML), facts
    pick_background(rtc_page, "#1030c0")
    deadline = time.monotonic() + 30
    while True:  # the request goes over the data channel; the track shows it a little later
        corner = rtc_page.execute_script(VIDEO_CORNER)
        if (corner and corner[2] > 150 and corner[0] < 60) or time.monotonic() > deadline:
            break
        time.sleep(0.1)
    assert corner and corner[2] > 150 and corner[0] < 60 and corner[1] < 90, corner



# -- the pure parts in node: the same camera axes as the server's orbit, zoom, parsing ---------

@pytest.mark.skipif(node() is None, reason="node is not installed")
def test_view_math_agrees_with_the_servers_orbit_camera():
    web = os.path.abspath(WEB)
    angles = [(0, 0), (30, 10), (-120, -45), (179, 80)]
    script = f"""
    import {{ screenAxes, zoomTarget }} from "{web}/view.js";
    import {{ hexToRgb, recordSeconds }} from "{web}/capture.js";
    const framing = {{target: [0, 0.4, 0.1], face: [0, 0.66, 0], distance: 1.9,
                      min_distance: 0.7, fov_y_deg: 30}};
    const errors = [];
    const seconds = ["", "?record_s=5", "?record_s=0", "?record_s=301", "?record_s=x",
                     "?record_s="].map((q) => recordSeconds(q, (e) => errors.push(e)));
    console.log(JSON.stringify({{
      axes: {json.dumps(angles)}.map(([y, p]) => screenAxes(y, p)),
      zoom: [5, 1.9, 1.3, 0.7, 0.3].map((d) => zoomTarget(framing, d)),
      seconds, errors, red: hexToRgb("#ff8000"),
    }}));"""
    out = json.loads(run_node(script))
    for (yaw, pitch), axes in zip(angles, out["axes"], strict=True):
        camera = orbit(np.zeros(3), yaw, pitch, 2.0, width=64, height=64)
        assert np.allclose(axes["right"], camera.R[0], atol=1e-9)  # image x, world
        assert np.allclose(axes["up"], -camera.R[1], atol=1e-9)    # image -y, world
    far, default, middle, closest, past = (np.asarray(z) for z in out["zoom"])
    assert np.allclose(far, [0, 0.4, 0.1]) and np.allclose(default, [0, 0.4, 0.1])
    assert np.allclose(middle, [0, 0.53, 0.05]) and np.allclose(closest, [0, 0.66, 0])
    assert np.allclose(past, closest)
    assert out["seconds"] == [30, 5, 30, 30, 30, 30] and len(out["errors"]) == 4
    assert "1 to 300 seconds" in out["errors"][0]
    assert out["red"] == pytest.approx([1, 128 / 255, 0])
