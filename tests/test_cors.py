"""CORS (setting ``cors_origins``): a browser WHEP player on another origin reaches the REST and
WHEP/WHIP endpoints of a real server (uvicorn on 127.0.0.1), and only from the origins set.

Over HTTP: preflights from an allowed origin get 200 with the methods, ``Authorization`` and
``Content-Type`` allowed; another origin gets no ``Access-Control-Allow-Origin``; default
settings send no CORS header at all; the WHEP POST's answer exposes ``Location``. In a real
headless Chromium: a tiny player page served by a second HTTP server (another port, so
another origin) POSTs a recvonly offer, reads ``Location``, plays a frame and DELETEs its
resource with ``cors_origins`` set to its origin, and its fetch fails without it.
"""

from __future__ import annotations

import contextlib
import functools
import http.server
import threading
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from fastapi.testclient import TestClient
from pydantic import ValidationError

from server.app import create_app
from server.config import Settings, load_settings
from tests.server_fixtures import run_server, wait_until
from tests.test_client_units import chromium_missing

pytest.importorskip("aiortc")

SIZE = 64
TIMEOUT_S = 30.0
OTHER = "http://127.0.0.1:9"  # an origin no server here allows
CORS_NAMES = ("access-control-allow-origin", "access-control-allow-methods",
              "access-control-allow-headers", "access-control-expose-headers",
              "access-control-allow-credentials", "access-control-max-age")

PLAYER = """<!doctype html>
<meta charset="utf-8"><title>another origin's WHEP player</title>
<video id="video" autoplay muted playsinline></video>
<script>
"use strict";
// A minimal WHEP player (no trickle ICE): recvonly offer, POST, answer, DELETE at the end.
window.whep = async function (serverUrl, room, token) {
  const pc = new RTCPeerConnection({iceServers: []});
  window.pc = pc;
  pc.addTransceiver("video", {direction: "recvonly"});
  pc.ontrack = (event) => {
    document.getElementById("video").srcObject = event.streams[0] || new MediaStream([event.track]);
  };
  await pc.setLocalDescription(await pc.createOffer());
  await new Promise((resolve) => {  // every candidate in the offer, at most 5 s
    const timer = setTimeout(resolve, 5000);
    const check = () => {
      if (pc.iceGatheringState === "complete") { clearTimeout(timer); resolve(); }
    };
    pc.onicegatheringstatechange = check;
    check();
  });
  let response;
  try {
    response = await fetch(serverUrl + "/v1/rooms/" + room + "/whep", {
      method: "POST",
      headers: {Authorization: "Bearer " + token, "Content-Type": "application/sdp"},
      body: pc.localDescription.sdp,
    });
  } catch (err) {
    pc.close();
    return {error: String(err)};
  }
  const result = {status: response.status, location: response.headers.get("Location")};
  const text = await response.text();
  if (response.status === 201) {
    await pc.setRemoteDescription({type: "answer", sdp: text});
  } else {
    result.body = text;
    pc.close();
  }
  return result;
};
window.unwhep = async function (serverUrl, location, token) {
  const response = await fetch(new URL(location, serverUrl), {
    method: "DELETE", headers: {Authorization: "Bearer " + token}});
  window.pc.close();
  return response.status;
};
</script>
"""


def cors_headers(response: httpx.Response) -> dict[str, str]:
    return {k: v for k, v in response.headers.items() if k.lower().startswith("access-control")}


def preflight(client: httpx.Client, path: str, origin: str, method: str,
              headers: str = "authorization, content-type") -> httpx.Response:
    return client.options(path, headers={"Origin": origin,
                                         "Access-Control-Request-Method": method,
                                         "Access-Control-Request-Headers": headers})


@contextlib.contextmanager
def player_site(folder: Path) -> Iterator[str]:
    """A second local web server (another port: another origin) serving the player page;
    its origin, ``http://127.0.0.1:PORT``."""
    (folder / "player.html").write_text(PLAYER)

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args) -> None:  # noqa: D102 (keep the test output clean)
            pass

    site = http.server.ThreadingHTTPServer(
        ("127.0.0.1", 0), functools.partial(Quiet, directory=str(folder)))
    thread = threading.Thread(target=site.serve_forever, kwargs={"poll_interval": 0.1},
                              daemon=True, name="player-site")
    thread.start()
    try:
        yield f"http://127.0.0.1:{site.server_address[1]}"
    finally:
        site.shutdown()
        site.server_close()
        thread.join(5)


@pytest.fixture(scope="module")
def player(tmp_path_factory) -> Iterator[str]:
    with player_site(tmp_path_factory.mktemp("player")) as origin:
        yield origin


def _server(tmp_path_factory, name: str, **settings):
    return run_server(tmp_path_factory.mktemp(name), warmup=False, default_width=SIZE,
                      default_height=SIZE, **settings)


@pytest.fixture(scope="module")
def cors_server(tmp_path_factory, player):
    with _server(tmp_path_factory, "cors", cors_origins=[player]) as srv:
        yield srv


@pytest.fixture(scope="module")
def plain_server(tmp_path_factory):
    with _server(tmp_path_factory, "plain") as srv:
        yield srv


def _whep_paths(srv) -> list[tuple[str, str]]:
    room = srv.ctx.startup_links["room"]
    return [(f"/v1/rooms/{room}/whep", "POST"), (f"/v1/rooms/{room}/whip", "POST"),
            (f"/v1/rooms/{room}/whep/abc", "DELETE"), (f"/v1/rooms/{room}/whip/abc", "PATCH"),
            ("/v1/rooms", "GET"), ("/v1/rooms", "POST"), (f"/v1/rooms/{room}", "DELETE"),
            ("/v1/avatars", "GET"), ("/v1/health", "GET")]


# -- settings --------------------------------------------------------------------------------

def test_cors_origins_setting_parses_and_refuses_what_cannot_match():
    assert Settings().cors_origins == []
    env = {"TELESPLAT_CORS_ORIGINS": " https://Player.Example:443 , http://127.0.0.1:8080 "}
    assert load_settings(environ=env).cors_origins == ["https://player.example",
                                                       "http://127.0.0.1:8080"]
    env = {"TELESPLAT_CORS_ORIGINS": '["http://a.example", "http://[::1]:9000"]'}
    assert load_settings(environ=env).cors_origins == ["http://a.example", "http://[::1]:9000"]
    assert load_settings(environ={"TELESPLAT_CORS_ORIGINS": "*"}).cors_origins == ["*"]
    assert load_settings(environ={"TELESPLAT_CORS_ORIGINS": ""}).cors_origins == []
    with pytest.raises(ValidationError, match="cannot be combined"):
        Settings(cors_origins=["*", "http://a.example"])
    with pytest.raises(ValidationError, match="cannot be combined"):
        load_settings(environ={"TELESPLAT_CORS_ORIGINS": "http://a.example,*"})
    for bad in ("http://a.example/", "http://a.example/player", "a.example", "null",
                "file:///tmp/x.html", "ftp://a.example", "http://user@a.example",
                "http://a.example:99999", "http://a.example?x=1", "http://"):
        with pytest.raises(ValidationError, match="is not an origin"):
            Settings(cors_origins=[bad])
    with pytest.raises(ValidationError, match="not a JSON list"):
        load_settings(environ={"TELESPLAT_CORS_ORIGINS": '["http://a.example"'})
    with pytest.raises(ValidationError):
        Settings(cors_max_age_s=-1)


def test_any_origin_is_allowed_only_when_star_stands_alone(tmp_path):
    app = create_app(Settings(data_dir=tmp_path, demo_avatar="none", warmup=False,
                              startup_room=False, cors_origins="*"))
    client = TestClient(app)  # no lifespan: the middleware alone answers a preflight
    response = preflight(client, "/v1/rooms/r/whep", "https://anyone.example", "POST")
    assert response.status_code == 200
    assert response.headers["access-control-allow-origin"] == "*"
    assert "access-control-allow-credentials" not in response.headers


# -- a real server, over HTTP ----------------------------------------------------------------

def test_preflights_from_the_allowed_origin_get_the_methods_and_headers(cors_server, player):
    with httpx.Client(base_url=cors_server.url, timeout=TIMEOUT_S) as client:
        for path, method in _whep_paths(cors_server):
            response = preflight(client, path, player, method)
            assert response.status_code == 200, (path, method, response.text)
            got = response.headers
            assert got["access-control-allow-origin"] == player
            assert set(got["access-control-allow-methods"].split(", ")) == {
                "GET", "POST", "DELETE", "PATCH"}
            allowed = {h.strip().lower() for h in got["access-control-allow-headers"].split(",")}
            assert {"authorization", "content-type"} <= allowed
            assert got["access-control-max-age"] == str(cors_server.settings.cors_max_age_s)
            assert "access-control-allow-credentials" not in got  # no credentials mode
            assert "origin" in got["vary"].lower()
        # A header the server does not take is refused by name.
        response = preflight(client, _whep_paths(cors_server)[0][0], player, "POST",
                             headers="authorization, x-custom")
        assert response.status_code == 400 and "headers" in response.text


def test_another_origin_gets_no_allow_origin(cors_server):
    with httpx.Client(base_url=cors_server.url, timeout=TIMEOUT_S) as client:
        for path, method in _whep_paths(cors_server):
            response = preflight(client, path, OTHER, method)
            assert response.status_code == 400, (path, method)
            assert "access-control-allow-origin" not in response.headers
        response = client.get("/v1/health", headers={"Origin": OTHER})
        assert response.status_code == 200
        assert "access-control-allow-origin" not in response.headers


def test_default_settings_send_no_cors_header(plain_server, player):
    assert plain_server.settings.cors_origins == []
    with httpx.Client(base_url=plain_server.url, timeout=TIMEOUT_S) as client:
        for path, method in _whep_paths(plain_server):
            response = preflight(client, path, player, method)
            assert response.status_code != 200, (path, method)  # the static mount's 405
            assert cors_headers(response) == {}, (path, method)
        for response in (client.get("/v1/health", headers={"Origin": player}),
                         client.get("/v1/rooms", headers={"Origin": player,
                                                          **plain_server.headers()})):
            assert response.status_code == 200 and cors_headers(response) == {}


def test_whep_post_exposes_location_to_the_allowed_origin(cors_server, player):
    from tests.test_webrtc_signalling import offer_sdp

    room = cors_server.ctx.startup_links["room"]
    headers = {**cors_server.headers(), "Origin": player, "Content-Type": "application/sdp"}
    with httpx.Client(base_url=cors_server.url, timeout=TIMEOUT_S) as client:
        response = client.post(f"/v1/rooms/{room}/whep", content=offer_sdp(), headers=headers)
        assert response.status_code == 201, response.text
        assert response.headers["access-control-allow-origin"] == player
        exposed = {h.strip().lower() for h in
                   response.headers["access-control-expose-headers"].split(",")}
        assert {"location", "link", "etag"} <= exposed
        location = response.headers["location"]
        assert location.startswith(f"/v1/rooms/{room}/whep/")
        # An error is readable too (a player can tell 401 from a network failure).
        refused = client.post(f"/v1/rooms/{room}/whep", content="v=0",
                              headers={**headers, "Authorization": "Bearer tsk_nope"})
        assert refused.status_code == 401
        assert refused.headers["access-control-allow-origin"] == player
        gone = client.delete(location, headers=headers)
        assert gone.status_code == 204 and gone.headers["access-control-allow-origin"] == player
    wait_until(lambda: len(cors_server.ctx.webrtc_peers) == 0, TIMEOUT_S,
               what="the WHEP peer to be freed")


# -- a real Chromium on another origin ---------------------------------------------------------

browser_test = pytest.mark.skipif(chromium_missing() is not None,
                                  reason=chromium_missing() or "")


@pytest.fixture(scope="module")
def browser(player):
    from tests.test_webrtc_browser import make_webrtc_chromium

    driver = make_webrtc_chromium()
    try:
        driver.get(f"{player}/player.html")
        yield driver
    finally:
        driver.quit()


def _whep(driver, srv) -> dict:
    return driver.execute_async_script(
        "const done = arguments[arguments.length - 1];"
        "window.whep(arguments[0], arguments[1], arguments[2]).then(done,"
        " (err) => done({error: 'threw: ' + String(err)}));",
        srv.url, srv.ctx.startup_links["room"], srv.token)


@browser_test
def test_a_player_on_another_origin_plays_with_cors_origins_set(browser, cors_server, player):
    from tests.test_client_browser import wait_for

    assert browser.execute_script("return location.origin") == player != cors_server.url
    result = _whep(browser, cors_server)
    assert result.get("status") == 201, result
    assert result["location"].startswith(f"/v1/rooms/{cors_server.ctx.startup_links['room']}"
                                         "/whep/"), result  # readable: exposed
    wait_for(browser, "document.getElementById('video').videoWidth > 0", TIMEOUT_S,
             "a video frame from the other origin's server")
    status = browser.execute_async_script(
        "const done = arguments[arguments.length - 1];"
        "window.unwhep(arguments[0], arguments[1], arguments[2]).then(done,"
        " (err) => done('threw: ' + String(err)));",
        cors_server.url, result["location"], cors_server.token)
    assert status == 204  # DELETE passed its preflight too
    wait_until(lambda: len(cors_server.ctx.webrtc_peers) == 0, TIMEOUT_S,
               what="the WHEP peer to be freed")


@browser_test
def test_the_same_player_is_refused_without_cors_origins(browser, plain_server):
    result = _whep(browser, plain_server)
    assert "status" not in result and "Failed to fetch" in result.get("error", ""), result
    assert len(plain_server.ctx.webrtc_peers) == 0  # the POST never left the browser


def test_a_whep_player_without_a_data_channel_gets_frames(plain_server):
    """What a plain WHEP player offers (recvonly video, no data channel) plays: the session's
    control messages no longer wait for a channel that never opens (they held its frames)."""
    import asyncio

    from client.webrtc import WhepViewer

    async def run():
        links = plain_server.ctx.startup_links
        viewer = WhepViewer(plain_server.url, links["room"], links["watch"].split("#token=")[1],
                            data_channel=False, timeout_s=TIMEOUT_S)
        await viewer.start()
        try:
            return [(await viewer.next_frame(TIMEOUT_S))[0] for _ in range(3)]
        finally:
            await viewer.close()

    frames = asyncio.run(asyncio.wait_for(run(), 3 * TIMEOUT_S))
    assert all(f.shape == (SIZE, SIZE, 3) for f in frames)
    assert frames[-1].std() > 5  # the avatar, not a blank picture
    wait_until(lambda: len(plain_server.ctx.webrtc_peers) == 0, TIMEOUT_S,
               what="the WHEP peer to be freed")
