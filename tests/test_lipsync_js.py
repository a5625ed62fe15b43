"""client/web/lipsync.js in node: the picture is held while new voice packets come, and let
go after RELEASE_POLLS polls without any (the page in Chromium: tests/test_voice_browser.py)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.test_client_units import node, run_node

LIPSYNC = (Path(__file__).resolve().parent.parent / "client" / "web" / "lipsync.js").as_uri()

pytestmark = pytest.mark.skipif(node() is None, reason="node is not installed")


def run(script: str):
    return json.loads(run_node(f"import * as L from {json.dumps(LIPSYNC)};\n{script}"))


def report(*rows):
    """A getStats() report's forEach over `rows`."""
    return f"{{forEach: (f) => {json.dumps(list(rows))}.forEach(f)}}"


def test_voice_packets_sum_every_voice_line_and_nothing_else():
    out = run(f"""console.log(JSON.stringify([
      L.voicePackets({report()}),
      L.voicePackets({report({"type": "inbound-rtp", "kind": "video", "packetsReceived": 9})}),
      L.voicePackets({report({"type": "inbound-rtp", "kind": "audio", "packetsReceived": 3},
                             {"type": "inbound-rtp", "kind": "audio"},
                             {"type": "outbound-rtp", "kind": "audio", "packetsSent": 7},
                             {"type": "inbound-rtp", "kind": "audio", "packetsReceived": 4})})
    ]));""")
    assert out == [None, None, 7]  # no voice line; a line that has heard nothing counts 0


def test_the_hold_follows_the_voice_and_goes_after_quiet_polls():
    out = run("""
      const receiver = {track: {kind: "video"}, jitterBufferTarget: null};
      const pc = {getReceivers: () => [{track: {kind: "audio"}}, receiver]};
      const sync = new L.LipSync(pc);
      const voice = (n) => ({forEach: (f) => f({type: "inbound-rtp", kind: "audio",
                                                packetsReceived: n})});
      const holds = [];
      for (const n of [0, 0, 50, 100, 100, 100, 100, 100, 100, 150])
        holds.push([sync.update(voice(n)), receiver.jitterBufferTarget]);
      console.log(JSON.stringify({holds, release: L.RELEASE_POLLS, hold: L.PICTURE_HOLD_MS}));""")
    assert out["release"] == 5 and out["hold"] == 60
    held = [[0, None], [0, None], [60, 60], [60, 60]]  # nothing heard yet; then packets
    quiet = [[60, 60]] * 4 + [[0, 0]]                   # four quiet polls hold; the fifth lets go
    assert out["holds"] == held + quiet + [[60, 60]]    # and the voice back holds again


def test_a_browser_without_jitter_buffer_target_keeps_no_hold():
    out = run("""
      const pc = {getReceivers: () => [{track: {kind: "video"}}]};
      const sync = new L.LipSync(pc);
      const voice = (n) => ({forEach: (f) => f({type: "inbound-rtp", kind: "audio",
                                                packetsReceived: n})});
      console.log(JSON.stringify([sync.update(voice(10)), sync.update(voice(20))]));""")
    assert out == [0, 0]  # said as 0 in the overlay: nothing is held


def test_next_hold_is_pure():
    out = run("""console.log(JSON.stringify([
      L.nextHold(0, true, 0), L.nextHold(60, false, 4), L.nextHold(60, false, 5),
      L.nextHold(0, false, 9)]));""")
    assert out == [60, 60, 0, 0]
