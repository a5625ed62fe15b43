"""Rooms in a real headless Chromium against a real server: the performer's page clicks Share,
a second browser (its own context: another webdriver) opens the watch link it shows, the
performer moves the jaw slider and the viewer's canvas changes in the projected mouth box.
The viewer's page shows no drive controls; both show who performs and how many watch."""

from __future__ import annotations

import importlib.util
import time

import numpy as np
import pytest

from tests.server_fixtures import server_fixture  # noqa: F401 (the `server` fixture)
from tests.test_client_browser import wait_for
from tests.test_client_units import chromium_missing, make_chromium

pytestmark = [
    pytest.mark.skipif(chromium_missing() is not None, reason=chromium_missing() or ""),
    pytest.mark.skipif(importlib.util.find_spec("server.routers.rooms") is None,
                       reason="the server has no rooms yet"),
]

SIZE = 512          # the page's default frame size
JAW_JOINT = 22      # SMPL-X joint index of the jaw
HEAD_JOINT = 15
MOUTH_HALF_WIDTH_M = 0.07
CHIN_BELOW_JAW_M = 0.12

# The canvas as grey levels, row-major (read back through the 2D context, as the page shows it).
CANVAS_GREY = """
const canvas = document.getElementById("view");
const {width, height} = canvas;
const data = canvas.getContext("2d").getImageData(0, 0, width, height).data;
const grey = new Array(width * height);
for (let i = 0; i < width * height; i++) grey[i] = (data[4*i] + data[4*i+1] + data[4*i+2]) / 3;
return {width, height, grey, shown: window.telesplat.framesShown};
"""


def mouth_box(server) -> tuple[int, int, int, int]:  # noqa: F811
    """(x0, y0, x1, y1) pixels of the demo avatar's mouth at the page's default orbit: from
    the head joint's height down to below the chin, a mouth's width either side of the jaw."""
    from avatar_core.render.camera_path import framing_target
    from protocol import Orbit, View
    from server.stream.scene import view_camera

    model = server.ctx.registry.open("demo").animator.body_model
    joints = model.joint_template.cpu().numpy().astype(np.float64)
    camera = view_camera(View(orbit=Orbit()), SIZE, SIZE, framing_target(model.joint_template))
    jaw, head = joints[JAW_JOINT], joints[HEAD_JOINT]
    corners = np.array([jaw + [dx, dy, 0.0] for dx in (-MOUTH_HALF_WIDTH_M, MOUTH_HALF_WIDTH_M)
                        for dy in (head[1] - jaw[1], -CHIN_BELOW_JAW_M)])
    uv, z = camera.project(corners)
    assert (z > 0).all()
    x0, y0 = np.floor(uv.min(axis=0)).astype(int)
    x1, y1 = np.ceil(uv.max(axis=0)).astype(int)
    return max(int(x0), 0), max(int(y0), 0), min(int(x1), SIZE), min(int(y1), SIZE)


def grey_image(driver) -> np.ndarray:
    shot = driver.execute_script(CANVAS_GREY)
    return np.asarray(shot["grey"], np.float64).reshape(shot["height"], shot["width"])


def visible(driver, element_id: str) -> bool:
    return driver.find_element("id", element_id).is_displayed()


@pytest.fixture()
def browsers():
    """Two separate browsers: the performer's and the viewer's (no shared storage)."""
    drivers = []
    try:
        drivers.append(make_chromium())
        drivers.append(make_chromium())
        yield drivers
    finally:
        for driver in drivers:
            driver.quit()


def test_share_link_viewer_sees_the_performers_jaw(server, browsers):  # noqa: F811
    performer, viewer = browsers
    # The admin URL `make run` prints; these are the WebSocket transport's pages (canvas).
    performer.get(f"{server.url}/?transport=ws#token={server.token}")
    wait_for(performer, "window.telesplat.framesShown > 0", 60, "the performer's first frame")
    assert visible(performer, "share")
    performer.find_element("id", "share").click()
    watch_url = wait_for(performer, "document.querySelector('#share-links [data-scope=watch] "
                                    "input')?.value", 60, "the watch link")
    assert watch_url.startswith(f"{server.url}/?room=") and "#token=tsr_" in watch_url
    watch_url = watch_url.replace("/?room=", "/?transport=ws&room=", 1)
    room = performer.execute_script("return window.telesplat.room")
    assert room["role"] == "perform" and room["seat"] == 0 and room["id"] in watch_url
    # One seat, performed by this page: no perform link is offered.
    assert not performer.find_elements("css selector", "#share-links [data-scope=perform]")
    assert "token" not in performer.current_url and f"room={room['id']}" in performer.current_url

    viewer.get(watch_url)
    wait_for(viewer, "window.telesplat.room && window.telesplat.room.role === 'watch'", 60,
             "the viewer to join")
    wait_for(viewer, f"window.telesplat.framesShown > 0 && "
                     f"document.getElementById('view').width === {SIZE}", 60,
             "the viewer's first full-size frame")
    assert "token" not in viewer.current_url
    # Viewer mode: no sliders, clips, webcam or share; orbit/zoom stay on the canvas.
    assert not visible(viewer, "drive-controls") and visible(viewer, "viewer-note")
    assert not visible(viewer, "share")
    assert not any(e.is_displayed() for e in viewer.find_elements(
        "css selector", "input[type=range], #webcam, #motions button"))
    assert visible(viewer, "view")
    # Presence reaches both pages.
    wait_for(performer, "window.telesplat.presence?.viewers >= 1", 30, "the viewer's join")
    line = wait_for(viewer, "document.getElementById('presence').textContent", 30, "presence")
    assert "performing" in line and "1 watching" in line

    x0, y0, x1, y1 = mouth_box(server)
    assert 0 <= x0 < x1 <= SIZE and 0 <= y0 < y1 <= SIZE
    before = grey_image(viewer)
    shown = viewer.execute_script("return window.telesplat.framesShown")
    performer.execute_script("""
        const input = document.querySelector('input[data-param="jaw open"]');
        input.value = input.max;
        input.dispatchEvent(new Event('input'));""")
    wait_for(viewer, f"window.telesplat.framesShown > {shown}", 60, "a frame after the drive")
    deadline = time.monotonic() + 60
    while True:  # bounded: the frame of the last drive may come a moment after the first one
        after = grey_image(viewer)
        mouth = np.abs(after - before)[y0:y1, x0:x1].mean()
        if mouth > 1.0 or time.monotonic() > deadline:
            break
        time.sleep(0.1)
    torso = np.abs(after - before)[SIZE * 3 // 4:, :].mean()
    assert mouth > 1.0 and mouth > 4 * torso, (mouth, torso, (x0, y0, x1, y1))
    assert not viewer.execute_script(
        "return window.telesplat.errors.map(e => e.code)"), "the viewer got errors"
