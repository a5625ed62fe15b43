"""A viewer page asks for the room's mix (issue 30): ?mix=1 or its "one mixed voice" box, over
WebRTC (WHEP ?voice=mix: one voice line) and over the WebSocket (hello.voice_mix: seatless
`voice` messages), in real headless Chromium against a real server, two aiortc performers
speaking a tone each."""

from __future__ import annotations

import asyncio
import threading

import pytest

from tests.server_fixtures import server_fixture, wait_until  # noqa: F401 (`server`)
from tests.test_client_browser import server_log, wait_for  # noqa: F401 (a fixture)
from tests.test_server_rooms import create_room, invite, live
from tests.test_voice_browser import LOUD_S
from tests.test_voice_mix import SIZE, TIMEOUT_S, TONES, tone_track
from tests.test_webrtc_browser import browser_test, make_webrtc_chromium, wait_playing

# Chromium plays the voice in real time: these pages run one at a time (one xdist group),
# never beside each other (two failed together under contention in a CI run, 27 Nov).
pytestmark = pytest.mark.xdist_group("voice_browser")

SPEAKING_S = 120  # bounded: how long the performers speak at most (the test stops them)


class TonePerformers:
    """Two aiortc performers, one tone per seat, on their own thread until stopped."""

    def __init__(self, srv, room_id: str, tokens: list[str]) -> None:
        self.srv, self.room_id, self.tokens = srv, room_id, tokens
        self._stop: asyncio.Event | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, daemon=True, name="tone-performers")

    def __enter__(self) -> TonePerformers:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        if self._loop is not None and self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(TIMEOUT_S)

    def _run(self) -> None:
        try:
            asyncio.run(self._speak())
        except BaseException as exc:  # noqa: BLE001 - reported by the test
            self.error = exc

    async def _speak(self) -> None:
        from client.webrtc import WhepViewer

        self._loop, self._stop = asyncio.get_running_loop(), asyncio.Event()
        peers = [WhepViewer(self.srv.url, self.room_id, token, width=SIZE, height=SIZE,
                            timeout_s=TIMEOUT_S, microphone=tone_track(tone))
                 for token, tone in zip(self.tokens, TONES, strict=True)]
        async with peers[0], peers[1]:
            try:
                await asyncio.wait_for(self._stop.wait(), SPEAKING_S)
            except TimeoutError:
                pass


def mixed_voice(driver) -> dict:
    return wait_for(driver, "(window.telesplat.voices || []).find(v => v.mixed && "
                            "v.packets > 50 && v.speaking)", LOUD_S, "the mix heard")


@browser_test
def test_a_viewer_page_asks_for_the_mix_over_webrtc_and_the_websocket(server):  # noqa: F811
    room = create_room(server, seats=[{"avatar": "demo"}, {"avatar": "demo"}])
    tokens = [invite(server, room["id"], "perform", seat=i)["token"] for i in (0, 1)]
    link = invite(server, room["id"], "watch")["link"]
    viewer = make_webrtc_chromium()
    try:
        with TonePerformers(server, room["id"], tokens) as performers:
            # WebRTC, ?mix=1: one voice line, the mix, both seats in it
            viewer.get(f"{server.url}{link.replace('?room=', '?mix=1&room=')}")
            wait_playing(viewer)
            assert viewer.find_element("id", "voice-mix").is_selected()
            heard = mixed_voice(viewer)
            assert heard["seat"] == 0 and heard["volume"] == 1
            assert viewer.execute_script("return window.telesplat.voices.length") == 1
            assert "all seats (mix)" in viewer.find_element("id", "voices").text
            mix = live(server, room["id"]).voice_mix
            assert mix.running and len(mix.subscribers) == 1
            # unticked: the page joins again and hears each seat on its own line
            viewer.find_element("id", "voice-mix").click()
            seats = wait_for(viewer, "(() => { const v = window.telesplat.voices || []; "
                                     "return v.length === 2 && v.every(s => !s.mixed && "
                                     "s.packets > 20) && v; })()", LOUD_S, "both seats' lines")
            assert sorted(s["seat"] for s in seats) == [0, 1]
            wait_until(lambda: not mix.subscribers and not mix.running, TIMEOUT_S,
                       what="the mix stopped with its last viewer")
            # the WebSocket, ?mix=1: seatless voice messages, decoded as the one mix
            viewer.get(f"{server.url}{link.replace('?room=', '?transport=ws&mix=1&room=')}")
            wait_for(viewer, "window.telesplat?.transport === 'ws' && window.telesplat.room",
                     60, "the WebSocket session's welcome")
            viewer.execute_script("document.body.dispatchEvent(new PointerEvent("
                                  "'pointerdown', {bubbles: true}))")  # autoplay rules
            ws_heard = wait_for(viewer, "(window.telesplat.voices || []).find(v => v.mixed && "
                                        "v.played > 50 && v.peak > 0.05)", LOUD_S,
                                "the mix over the WebSocket")
            assert ws_heard["errors"] == 0
            assert viewer.execute_script("return window.telesplat.voices.length") == 1
            assert live(server, room["id"]).voice_mix.running
        assert performers.error is None, performers.error
    finally:
        viewer.quit()
