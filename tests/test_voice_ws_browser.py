"""The page's voice over the WebSocket (issue 30, for clients without WebRTC) in real headless
Chromium against a real server: a performer page (?transport=ws) encodes its fake microphone
(Chromium's beeps) to Opus with WebCodecs and sends `voice` messages stamped with their
capture time; a viewer page (?transport=ws) decodes them (AudioDecoder), plays them in an
AudioContext at their capture time plus the picture's delay, with its own volume and mute;
the performer's Mute silences it."""

from __future__ import annotations

import json
import statistics
import time
from pathlib import Path

import numpy as np
import pytest

from tests.server_fixtures import server_fixture, wait_until  # noqa: F401 (`server`)
from tests.test_client_browser import server_log, wait_for  # noqa: F401 (a fixture)
from tests.test_client_units import node, run_node
from tests.test_voice_browser import LOUD_S, room, voice_counts, with_microphone  # noqa: F401
from tests.test_webrtc_browser import WEB, browser_test, make_webrtc_chromium

# Chromium plays the voice in real time: these pages run one at a time (one xdist group),
# never beside each other (two failed together under contention in a CI run, 27 Nov).
pytestmark = pytest.mark.xdist_group("voice_browser")

WARM_UP_S = 2.0      # the first drives' frames, before the viewer has measured the picture
EARLY_MS, LATE_MS = -45.0, 125.0  # ITU-R BT.1359: detectable when audio is earlier / later
RESYNC_MS = 20       # client/web/voice_ws.js: the voice's delay moves further only to resync
DRIVE_EVERY_MS = 100  # the performer's page drives the jaw this often

# Every 100 ms a drive of the jaw, stamped by the page (session.js) with its capture time.
DRIVE_JAW = f"""
let open = 0;
window.jawTimer = setInterval(() => {{
  open = 0.3 - open;
  window.telesplat.session?.drive({{smplx: {{jaw_pose: new Float32Array([open, 0, 0])}}}});
}}, {DRIVE_EVERY_MS});
"""


def join_ws(driver, server, link: str, mic: bool = False) -> None:
    extra = "transport=ws&" + ("mic=1&" if mic else "")
    driver.get(f"{server.url}{link.replace('?room=', f'?{extra}room=')}")
    wait_for(driver, "window.telesplat?.transport === 'ws' && window.telesplat.room", 60,
             "the WebSocket session's welcome")
    wait_for(driver, "window.telesplat.framesShown > 0", 90, "a frame on the canvas")


def sync_errors_ms(log: dict) -> list[float]:
    """For each frame that first showed a drive (captured at t): when the voice captured at t
    plays (interpolated within its packet) minus when that frame showed; + is voice late."""
    packets = sorted((t, at) for _, t, at in log["packets"] if t is not None)
    starts = np.array([t for t, _ in packets])
    errors = []
    for t, shown in log["frames"]:
        i = int(np.searchsorted(starts, t, side="right")) - 1
        if i < 0 or t - starts[i] > 0.02:  # no packet covers t (before the voice, or a gap)
            continue
        errors.append(packets[i][1] + (t - starts[i]) * 1000 - shown)
    return errors


@browser_test
def test_a_websocket_performer_speaks_and_a_websocket_viewer_hears_in_sync(server, room):  # noqa: F811
    room, links = room
    performer = with_microphone()
    viewer = make_webrtc_chromium()
    try:
        join_ws(performer, server, links["perform"], mic=True)
        assert performer.execute_script("return window.telesplat.room.role") == "perform"
        wait_for(performer, "document.getElementById('mic-status').textContent === 'speaking'",
                 30, "the microphone on")
        join_ws(viewer, server, links["watch"])
        performer.execute_script(DRIVE_JAW)
        # The viewer decodes seat 0's packets and a beep is loud in them.
        heard = wait_for(viewer, "(window.telesplat.voices || []).find(v => v.seat === 0 && "
                                 "v.played > 100 && v.peak > 0.05)", LOUD_S, "seat 0 heard")
        assert heard["errors"] == 0 and heard["dropped"] == 0
        assert heard["volume"] == 1 and heard["muted"] is False
        counts = voice_counts(server, room["id"])
        assert counts.get("forwarded", 0) > 100
        assert not {"garbage", "too_large", "rate"} & set(counts)
        # Presence says who speaks (the level_dbov the page put in each message).
        says = "document.getElementById('presence').textContent.includes('performing, speaking')"
        wait_for(viewer, says, LOUD_S, "presence: seat 0 speaking")
        # Lips and voice: the sound captured with a drive plays when that drive's frame shows.
        past_warm_up = (  # drives' frames shown past the warm-up, enough for >= 10 events
            "(() => { const f = window.telesplat.wsVoices.log.frames; if (!f.length) "
            "return false; const first = Math.min(...f.map(x => x[1])); "
            f"return f.filter(x => x[1] > first + {WARM_UP_S * 1000}).length >= 20; }})()")
        wait_for(viewer, past_warm_up, 30, "frames past the warm-up")
        log = viewer.execute_script("return window.telesplat.wsVoices.log")
        first = min(shown for _, shown in log["frames"])
        log["frames"] = [f for f in log["frames"] if f[1] > first + WARM_UP_S * 1000]
        errors = sync_errors_ms(log)
        assert len(errors) >= 10, errors
        # The voice keeps one delay (no chasing each frame: that would cut gaps in it), after
        # the median of the picture's; each event's error is then that frame's own lag jitter
        # (renders on two shared cores), so the median is bounded, and most events.
        delays = [at - t * 1000 for _, t, at in log["packets"]
                  if t is not None and at > first + WARM_UP_S * 1000]
        lags = [shown - t * 1000 for t, shown in log["frames"]]
        print(f"sync error ms: median {statistics.median(errors):.1f}, "
              f"{len(errors)} events, min {min(errors):.1f} max {max(errors):.1f}, "
              f"{sum(EARLY_MS <= e <= LATE_MS for e in errors)} within -45/+125; "
              f"voice delay spread {max(delays) - min(delays):.1f} ms, picture lag spread "
              f"{max(lags) - min(lags):.1f} ms")
        assert EARLY_MS <= statistics.median(errors) <= LATE_MS, errors
        assert sum(EARLY_MS <= e <= LATE_MS for e in errors) >= 0.5 * len(errors), errors
        # the voice moves (in RESYNC_MS steps, after the median) less than the picture jitters
        assert max(delays) - min(delays) < max(lags) - min(lags) + RESYNC_MS, (delays, lags)
        # The viewer's own volume and mute act on its seat's gain only.
        viewer.execute_script("""
            const [volume, mute] = document.querySelectorAll('#voices .voice input');
            volume.value = '0.25'; volume.dispatchEvent(new Event('input'));
            mute.click();""")
        wait_for(viewer, "(window.telesplat.voices || []).find(v => v.seat === 0 && v.muted && "
                         "v.volume === 0.25)", 10, "the viewer's mute")
        # The performer mutes: packets go on (silence), no beep reaches the viewer.
        performer.find_element("id", "mic-mute").click()
        assert performer.find_element("id", "mic-mute").text == "Unmute"
        wait_for(viewer, "(window.telesplat.voices.find(v => v.seat === 0) || {}).level < 0.005",
                 10, "the muted performer's silence")
        played = viewer.execute_script(
            "return window.telesplat.voices.find(v => v.seat === 0).played")
        levels = []  # sampled until 100 more packets (several beeps' worth) have played
        deadline = time.monotonic() + 15.0
        while not levels or levels[-1]["played"] <= played + 100:
            assert time.monotonic() < deadline, levels[-1:]
            time.sleep(0.2)
            levels.append(viewer.execute_script(
                "return window.telesplat.voices.find(v => v.seat === 0)"))
        assert max(v["level"] for v in levels) < 0.005, levels
        assert levels[-1]["played"] > played + 100  # silence still arrives
        assert not viewer.execute_script(f"return {says}")  # silence is not speech
    finally:
        performer.quit()
        viewer.quit()


@browser_test
def test_the_page_encodes_within_the_servers_voice_bounds(server, room):  # noqa: F811
    """The welcome (protocol minor 4) carries voice_max_bitrate and voice_max_packet_bytes;
    a performer page set to a server bound below its 32 kbit/s encodes at that bound, and
    nothing it sends is dropped for rate or size."""
    room, links = room
    settings = server.ctx.settings
    before = settings.voice_max_bitrate, settings.voice_max_packet_bytes
    settings.voice_max_bitrate, settings.voice_max_packet_bytes = 12_000, 400
    performer = with_microphone()
    try:
        join_ws(performer, server, links["perform"], mic=True)
        wait_for(performer, "document.getElementById('mic-status').textContent === 'speaking'",
                 30, "the microphone on")
        bounds = performer.execute_script("return window.telesplat.session.welcome.voice")
        assert bounds == {"max_bitrate": 12_000, "max_packet_bytes": 400}
        mic = wait_for(performer, "window.telesplat.wsMic?.sent > 150 && "
                                  "({bitrate: window.telesplat.wsMic.bitrate, "
                                  "sent: window.telesplat.wsMic.sent, "
                                  "oversized: window.telesplat.wsMic.oversized})",
                       LOUD_S, "3 s of packets sent")
        assert mic["bitrate"] == 12_000 and mic["oversized"] == 0, mic
        counts = wait_until(lambda: (c := voice_counts(server, room["id"])).get(
            "forwarded", 0) > 150 and c, 10, what="the packets forwarded")
        assert not {"garbage", "too_large", "rate"} & set(counts), counts
    finally:
        performer.quit()
        settings.voice_max_bitrate, settings.voice_max_packet_bytes = before


@pytest.mark.skipif(node() is None, reason="node is not installed")
def test_the_bit_rate_within_the_servers_bounds_in_node():
    url = Path(WEB, "voice_ws.js").resolve().as_uri()
    out = json.loads(run_node(f"""
        import {{ voiceBitrate }} from {json.dumps(url)};
        console.log(JSON.stringify([
          voiceBitrate(null), voiceBitrate({{max_bitrate: 128000, max_packet_bytes: 1276}}),
          voiceBitrate({{max_bitrate: 12000, max_packet_bytes: 1276}}),
          voiceBitrate({{max_bitrate: 128000, max_packet_bytes: 40}}),
          voiceBitrate({{max_bitrate: 6000, max_packet_bytes: 2}})]));"""))
    # default; the page's own 32k under a high bound; the server's bit rate; a packet bound
    # of 40 B at 50 packets/s with 2x VBR headroom; never below Opus' 6 kbit/s
    assert out == [32_000, 32_000, 12_000, 8_000, 6_000]


@pytest.mark.skipif(node() is None, reason="node is not installed")
def test_levels_in_dbov_and_the_missing_webcodecs_said_in_node():
    url = Path(WEB, "voice_ws.js").resolve().as_uri()
    out = json.loads(run_node(f"""
        import {{ levelDbov, voiceUnsupported }} from {json.dumps(url)};
        const square = (a) => Float32Array.from({{length: 960}}, (_, i) => (i % 2 ? a : -a));
        console.log(JSON.stringify({{
          full: levelDbov(square(1)), tenth: levelDbov(square(0.1)),
          silence: levelDbov(new Float32Array(960)), tiny: levelDbov(square(1e-9)),
          missing: voiceUnsupported()}}));"""))
    assert out["full"] == 0 and out["tenth"] == pytest.approx(-20)
    assert out["silence"] == -127 and out["tiny"] == -127  # clamped to RFC 6464's range
    assert "WebCodecs" in out["missing"]  # node has no AudioEncoder: said, not thrown


@pytest.mark.skipif(node() is None, reason="node is not installed")
def test_the_webrtc_level_is_the_mean_since_the_last_poll_in_node():
    """A beep between two polls lifts the level even when each poll's instant is silent."""
    url = Path(WEB, "voice.js").resolve().as_uri()
    out = json.loads(run_node(f"""
        import {{ intervalLevel }} from {json.dumps(url)};
        console.log(JSON.stringify([
          intervalLevel(null, 1.0, 2.0),
          intervalLevel({{energy: 0.0, duration: 1.0}}, null, 2.0),
          intervalLevel({{energy: 0.0, duration: 1.0}}, 0.025, 2.0),
          intervalLevel({{energy: 0.5, duration: 2.0}}, 0.5, 3.0),
          intervalLevel({{energy: 0.5, duration: 2.0}}, 0.6, 2.0),
          intervalLevel({{energy: 0.5, duration: 2.0}}, 0.4, 3.0)]));"""))
    # no previous poll or no stats: none; a 0.5-level beep for 0.1 s in a one-second
    # interval: sqrt(0.25 x 0.1 / 1) = 0.158; silence: 0; no time passed: none; a counter
    # that went back (a new receiver): never negative
    assert out[:2] == [None, None]
    assert out[2] == pytest.approx(0.158, abs=1e-3)
    assert out[3] == 0 and out[4] is None and out[5] == 0
