"""The page reconnects after a server restart, in a real headless Chromium against a real server
subprocess: two viewers open the start-up room's watch link (one over the WebSocket, one over
WebRTC), the server is SIGTERMed and started again on the same port and data dir, and both
pages come back by themselves (error ``restarting``, then the backoff of reconnect.js) into
the same room as viewers, showing new frames. reconnect.js's rules run in node."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import threading
import time

import pytest

from tests.server_process import ServerProcess
from tests.test_client_browser import wait_for
from tests.test_client_units import node, run_node
from tests.test_webrtc_browser import NO_BROWSER_TEST, make_webrtc_chromium

WEB = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "client", "web"))
WAIT_S = 90.0    # each browser wait (bounded)


@pytest.mark.skipif(node() is None, reason="node is not installed")
def test_reconnect_rules_and_backoff():
    script = f"""
    import {{ RECONNECT, backoffDelay, reconnectDecision, reconnectPolicy, stopReason }}
      from "{WEB}/reconnect.js";
    const delays = [0, 1, 2, 3, 4, 5, 9].map((a) => backoffDelay(a, RECONNECT, () => 0));
    const jittered = [0, 4].map((a) => backoffDelay(a, RECONNECT, () => 0.999999));
    const d = (o) => reconnectDecision(o);
    console.log(JSON.stringify({{
      delays, jittered,
      restarting: d({{ closeCode: 1012, errorCode: "restarting" }}),
      dropped: [1001, 1006, 1012].map((c) => d({{ closeCode: c }})),
      ordinary: [d({{ closeCode: 1000 }}), d({{ closeCode: 1011 }}), d({{}})],
      final: [d({{ closeCode: 4404 }}), d({{ closeCode: 4410 }}), d({{ closeCode: 4401 }}),
              d({{ closeCode: 4410, errorCode: "gone" }}), d({{ errorCode: "not_found" }})],
      failures: [d({{ failure: new TypeError("Failed to fetch") }}),
                 d({{ failure: {{ code: "internal" }} }}), d({{ failure: {{ code: "busy" }} }}),
                 d({{ failure: {{ code: "not_found" }} }}),
                 d({{ failure: {{ code: "unauthorized" }} }})],
      gone: stopReason({{ closeCode: 4410 }}),
      policies: ["", "?reconnect=3", "?reconnect=0", "?reconnect=x", "?reconnect=-1"]
        .map((q) => reconnectPolicy(q).attempts),
    }}));
    """
    out = json.loads(run_node(script))
    assert out["delays"] == [250, 500, 1000, 2000, 4000, 4000, 4000]
    assert out["jittered"] == [pytest.approx(125, abs=0.01), pytest.approx(2000, abs=0.01)]
    assert out["restarting"] == "retry" and out["dropped"] == ["retry"] * 3
    assert out["ordinary"] == [None, None, None]
    assert out["final"] == ["stop"] * 5
    assert out["failures"] == ["retry", "retry", "retry", "stop", "stop"]
    assert "gone" in out["gone"]
    assert out["policies"] == [12, 3, 0, 12, 12]


def _perform(url: str, room: str, token: str, stop: threading.Event, errors: list) -> None:
    """A Python performer (reconnecting too) opening and closing the jaw at 5 Hz until
    ``stop``: a still room sends no new frames, a driven one does."""
    from client.stream import Backoff, StreamClient

    async def drive() -> None:
        client = await StreamClient.connect(url, token=token, room=room, role="perform",
                                            client_name="performer", timeout=30,
                                            reconnect=Backoff(attempts=40))
        try:
            i = 0
            while not stop.is_set():  # bounded by the test, which sets `stop`
                await asyncio.wait_for(client.drive(jaw_pose=[0.3 * (i % 2), 0.0, 0.0]),
                                       WAIT_S)
                i += 1
                await asyncio.sleep(0.2)
        finally:
            await client.close()

    try:
        asyncio.run(drive())
    except Exception as exc:  # noqa: BLE001 - reported by the test
        errors.append(exc)


@pytest.mark.skipif(NO_BROWSER_TEST is not None, reason=NO_BROWSER_TEST or "")
def test_the_page_reconnects_into_the_same_room_after_a_restart(tmp_path):
    with ServerProcess(tmp_path) as srv:
        link = srv.links["watch"]  # the start-up room's: kept across restarts, and its links
        room = link.split("?room=")[1].split("#")[0]
        perform_token = srv.links["perform"].split("#token=")[1]
        stop, performer_errors = threading.Event(), []
        performer = threading.Thread(target=_perform, args=(srv.url, room, perform_token, stop,
                                                            performer_errors), daemon=True)
        performer.start()
        pages = {}
        try:
            pages["ws"] = make_webrtc_chromium()
            pages["webrtc"] = make_webrtc_chromium()
            pages["ws"].get(link.replace("/?room=", "/?transport=ws&room=", 1))
            pages["webrtc"].get(link)  # WebRTC: both ends can
            for transport, page in pages.items():
                try:
                    wait_for(page, f"window.telesplat.transport === '{transport}' && "
                                   f"window.telesplat.room?.id === '{room}' && "
                                   "window.telesplat.framesShown > 2", WAIT_S,
                             f"the {transport} page's first frames")
                except TimeoutError as exc:
                    seen = page.execute_script(
                        "const t = window.telesplat; return JSON.stringify({transport: "
                        "t.transport, room: t.room, shown: t.framesShown, errors: t.errors, "
                        "status: document.getElementById('status').textContent})")
                    raise AssertionError(f"{exc}\npage: {seen}\nperformer: "
                                         f"{performer_errors}\n" + "".join(srv.output)
                                         ) from None
            before = {t: p.execute_script("return window.telesplat.framesShown")
                      for t, p in pages.items()}

            stopped = time.monotonic()
            assert srv.stop(signal.SIGTERM) in (0, -signal.SIGTERM)
            for transport, page in pages.items():
                wait_for(page, "window.telesplat.reconnecting", WAIT_S,
                         f"the {transport} page to start reconnecting")
            srv.start()
            shown = {}
            for transport, page in pages.items():
                state = wait_for(page, f"window.telesplat.reconnects === 1 && "
                                       f"window.telesplat.framesShown > "
                                       f"{before[transport] + 2} && window.telesplat", WAIT_S,
                                 f"the {transport} page's frames after the restart")
                shown[transport] = (time.monotonic() - srv.started_at,
                                    state["lastReconnect"]["downMs"] / 1000)
                assert state["room"]["id"] == room and state["room"]["role"] == "watch"
                assert state["transport"] == transport  # no fall-back to the WebSocket
                assert not state["reconnecting"]
                codes = [e["code"] for e in state["errors"]]
                assert "restarting" in codes, codes
                assert state["lastReconnect"]["reason"] == "the server is restarting"
                text = page.execute_script("return document.getElementById('status')"
                                           ".textContent")
                assert "watching" in text, text
            print(f"\npage reconnects: server down to up {srv.started_at - stopped:.1f} s; "
                  + ", ".join(f"{t}: frames again by {up:.1f} s after the new server's "
                              f"start, rejoined {down:.1f} s after the connection was lost"
                              for t, (up, down) in shown.items()))
            assert performer.is_alive() and not performer_errors, performer_errors
        finally:
            stop.set()
            performer.join(WAIT_S)
            for page in pages.values():
                page.quit()
