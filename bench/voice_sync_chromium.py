"""Lip sync of a room's voice as a Chromium viewer plays it: click onset vs mouth opening.

The performer is bench/voice_sync.py's (aiortc, WHEP role=perform: a click in the 20 ms audio
frame of each jaw opening, every 0.7 s, drives at ``--drive-hz`` between). The viewer is the
page itself, headless Chromium joined with a watch link over WebRTC; a script put into the page
records, on the page's clock (performance.now()):

- the mouth opening: the ``expectedDisplayTime`` (requestVideoFrameCallback) of the first
  frame with more than ``--open-pixels`` pixels 25 grey levels off the closed-mouth frame (the
  stamp strip at the top left left out);
- the click onset: when the first sample above 0.3 of the seat's voice is heard, from an
  AudioWorklet on the page's received track, mapped to performance time by
  ``AudioContext.getOutputTimestamp()``;
- offset = click - mouth, each mouth edge paired with the click nearest it within half an
  event interval. Chromium lip-syncs the tracks itself (one MediaStream, RTCP sender reports).

    nice -n 10 .venv/bin/python bench/voice_sync_chromium.py [--events 50] [--drive-hz 30]
        [--pacing even,frames]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from stream import start_server, stop_server  # noqa: E402
from voice_sync import EVENT_EVERY_S, JAW_OPEN, OPEN_S, click_microphone  # noqa: E402

from client.webrtc import WhepViewer  # noqa: E402
from protocol import Drive  # noqa: E402

STAMP_ROWS = 12  # the frame stamp's strip (<= 8 px cells) and the codec's bleed below it

RECORDER = """
const [openPixels, stampRows] = arguments;
const rec = window.__sync = {mouth: [], clicks: [], frames: 0, blocks: 0, error: null};
const video = document.getElementById('video');
const canvas = document.createElement('canvas');
const g = canvas.getContext('2d', {willReadFrequently: true});
let closed = null, open = false;
function onFrame(now, meta) {
  const w = video.videoWidth, h = video.videoHeight;
  canvas.width = w; canvas.height = h;
  g.drawImage(video, 0, 0);
  const d = g.getImageData(0, 0, w, h).data;
  const grey = new Float32Array(w * h);
  for (let i = 0; i < w * h; i++) grey[i] = (d[4*i] + d[4*i+1] + d[4*i+2]) / 3;
  if (rec.reference) { closed = grey; rec.reference = false; }
  else if (closed) {
    let n = 0;
    for (let i = stampRows * w; i < w * h; i++) if (Math.abs(grey[i] - closed[i]) > 25) n++;
    const isOpen = n > openPixels;
    if (isOpen && !open) rec.mouth.push(meta.expectedDisplayTime);
    open = isOpen;
  }
  rec.frames++;
  video.requestVideoFrameCallback(onFrame);
}
video.requestVideoFrameCallback(onFrame);
const worklet = `class Onset extends AudioWorkletProcessor {
  constructor() { super(); this.lastLoud = -1; }
  process(inputs) {
    const x = inputs[0][0];
    if (x) for (let i = 0; i < x.length; i++) {
      if (Math.abs(x[i]) <= 0.3) continue;
      const t = currentTime + i / sampleRate;  // an onset: loud after 0.1 s of quiet
      if (t - this.lastLoud > 0.1) this.port.postMessage(t);
      this.lastLoud = t;
    }
    this.port.postMessage(null);
    return true;
  }
}
registerProcessor('onset', Onset);`;
(async () => {
  try {
    const audio = document.querySelector('#voices audio');
    const ac = new AudioContext({latencyHint: 'interactive'});
    await ac.audioWorklet.addModule(URL.createObjectURL(new Blob([worklet],
      {type: 'application/javascript'})));
    const node = new AudioWorkletNode(ac, 'onset');
    node.port.onmessage = (e) => {
      if (e.data === null) { rec.blocks++; return; }
      const ts = ac.getOutputTimestamp();
      rec.clicks.push(ts.performanceTime + (e.data - ts.contextTime) * 1000);
    };
    ac.createMediaStreamSource(audio.srcObject).connect(node).connect(ac.destination);
    await ac.resume();
    rec.context = ac.state;
  } catch (err) { rec.error = String(err); }
})();
"""


JITTER_BUFFERS = """
const done = arguments[arguments.length - 1];
window.telesplat.session.pc.getStats().then((stats) => {
  const out = {};
  stats.forEach((s) => {
    if (s.type === 'inbound-rtp' && s.jitterBufferEmittedCount) {
      out[s.kind] = Math.round(1000 * s.jitterBufferDelay / s.jitterBufferEmittedCount);
    }
  });
  done(out);
});
"""


async def perform(url: str, token: str, room: str, size: int, events: int, drive_hz: float,
                  driver, open_pixels: int) -> dict:
    seq = iter(range(1, 10**6))
    pose = {"jaw": 0.0}
    performer: WhepViewer | None = None

    def jaw(angle: float) -> None:
        pose["jaw"] = angle
        performer.send(Drive(seq=next(seq), smplx={"jaw_pose": [angle, 0.0, 0.0]},
                             t_capture=time.monotonic()))

    async def tracker(until: float) -> None:
        while drive_hz and time.monotonic() < until:
            jaw(pose["jaw"])
            await asyncio.sleep(1 / drive_hz)

    mic = click_microphone(lambda: jaw(JAW_OPEN), [])
    performer = WhepViewer(url, room, token, width=128, height=128, role="perform", seat=0,
                           microphone=mic, timeout_s=60)
    async with performer:
        await performer.wait_open()
        await asyncio.to_thread(join_page, driver, url, token, room, size, open_pixels)
        end = time.monotonic() + 2.0 + events * EVENT_EVERY_S
        drives = asyncio.create_task(tracker(end))
        await asyncio.sleep(2.0)
        await asyncio.to_thread(driver.execute_script, "window.__sync.reference = true;")
        await asyncio.sleep(0.5)
        for _ in range(events):
            mic.fire()
            await asyncio.sleep(OPEN_S)
            jaw(0.0)
            await asyncio.sleep(EVENT_EVERY_S - OPEN_S)
        await drives
        await asyncio.sleep(1.0)
        rec = await asyncio.to_thread(driver.execute_script, "return window.__sync;")
        rec["buffers"] = await asyncio.to_thread(driver.execute_async_script, JITTER_BUFFERS)
        return rec


def join_page(driver, url: str, token: str, room: str, size: int, open_pixels: int) -> None:
    from tests.test_client_browser import wait_for
    from tests.test_webrtc_browser import wait_playing

    link = httpx.post(f"{url}/v1/rooms/{room}/invitations", json={"scope": "watch"},
                      headers={"Authorization": f"Bearer {token}"}, timeout=30).json()["link"]
    driver.get(f"{url}{link}")
    wait_playing(driver, 512)  # the page's default, then its #size menu's choice
    driver.execute_script("""const size = document.getElementById('size');
        size.value = arguments[0]; size.dispatchEvent(new Event('change'));""", str(size))
    wait_for(driver, f"document.getElementById('video').videoWidth === {size}", 60, "the size")
    wait_for(driver, "document.querySelector('#voices audio')", 60, "the seat's <audio>")
    driver.execute_script(RECORDER, open_pixels, STAMP_ROWS)
    wait_for(driver, "window.__sync.blocks > 10 || window.__sync.error", 30, "the worklet")


def offsets(rec: dict) -> list[float]:
    clicks = np.asarray(rec["clicks"])
    out = []
    for mouth in rec["mouth"]:
        if len(clicks):
            nearest = clicks[np.argmin(np.abs(clicks - mouth))]
            if abs(nearest - mouth) < EVENT_EVERY_S * 1e3 / 2:
                out.append(float(nearest - mouth))
    return out


def run_once(args) -> dict:
    """One server (its settings from the environment), one page, one take."""
    from tests.test_webrtc_browser import make_webrtc_chromium

    with tempfile.TemporaryDirectory() as tmp:
        proc, url, token = start_server(Path(tmp), 1, 8, args.avatar)
        driver = make_webrtc_chromium()
        try:
            async def run() -> dict:
                async with httpx.AsyncClient(base_url=url, timeout=30) as http:
                    room = (await http.post("/v1/rooms", json={"seats": [{"avatar": "demo"}]},
                                            headers={"Authorization": f"Bearer {token}"})
                            ).json()["id"]
                return await perform(url, token, room, args.size, args.events, args.drive_hz,
                                     driver, args.open_pixels)

            return asyncio.run(run())
        finally:
            driver.quit()
            stop_server(proc)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--events", type=int, default=50)
    parser.add_argument("--size", type=int, default=256, help="the page's frame size (its "
                        "#size menu: 256, 384, 512, 768)")
    parser.add_argument("--open-pixels", type=int, default=8)
    parser.add_argument("--drive-hz", type=float, default=30.0)
    parser.add_argument("--avatar", default="synthetic")
    parser.add_argument("--pacing", default="frames", help="the server's voice_pacing per run, "
                        "side by side: even, frames or even,frames")
    args = parser.parse_args()

    os.environ["TELESPLAT_WEBRTC_MAX_PEERS"] = "4"
    print("| viewer | pacing | drives/s | events | paired | median ms | p5 / p95 ms | "
          "min / max ms | within -45/+125 | jitter buffer ms (audio / video) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for pacing in args.pacing.split(","):
        os.environ["TELESPLAT_VOICE_PACING"] = pacing
        rec = run_once(args)
        arr = np.asarray(offsets(rec))
        print(f"# {pacing}: frames {rec['frames']}, audio blocks {rec['blocks']}, mouth edges "
              f"{len(rec['mouth'])}, clicks {len(rec['clicks'])}, audio {rec.get('context')}, "
              f"error {rec['error']}, mean jitter-buffer delay ms {rec['buffers']}; "
              f"offsets ms {[round(x) for x in arr]}", file=sys.stderr, flush=True)
        buffers = f"{rec['buffers'].get('audio', '-')} / {rec['buffers'].get('video', '-')}"
        if len(arr):
            print(f"| Chromium | {pacing} | {args.drive_hz:g} | {args.events} | {len(arr)} | "
                  f"{np.median(arr):.0f} | {np.percentile(arr, 5):.0f} / "
                  f"{np.percentile(arr, 95):.0f} | {arr.min():.0f} / {arr.max():.0f} | "
                  f"{((arr >= -45) & (arr <= 125)).mean():.0%} | {buffers} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
