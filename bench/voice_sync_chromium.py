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
  event interval. Chromium lip-syncs the tracks itself (one MediaStream, RTCP sender reports),
  and the page holds its picture while a voice plays (client/web/lipsync.js).

Runs side by side, one fresh server each: every combination of ``--pacing``,
``--sender-clock`` (the server's ``webrtc_sender_clock``: capture or send),
``--max-delay-s`` (its ``voice_max_delay_s``; "default": unset) and ``--hold`` (the page's
hold as it ships, none, or a fixed one). Per track the page's
getStats() at the end: the mean jitter-buffer delay and target delay (ms), and the mean delay
Chromium's A/V sync added (RtpStreamsSynchronizer shows as the gap between them).

    nice -n 10 .venv/bin/python bench/voice_sync_chromium.py [--events 50] [--drive-hz 30]
        [--pacing even,frames] [--sender-clock capture,send] [--max-delay-s default,0]
        [--hold page,off,60] [--settle-s 15]
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
from voice_sync import (  # noqa: E402
    EVENT_EVERY_S,
    JAW_OPEN,
    OPEN_S,
    JawDrives,
    add_server_voice_args,
    click_microphone,
    server_voice_runs,
    spread_text,
)

from client.webrtc import WhepViewer  # noqa: E402

STAMP_ROWS = 12  # the frame stamp's strip (<= 8 px cells) and the codec's bleed below it

RECORDER = """
const [openPixels, stampRows] = arguments;
const rec = window.__sync = {mouth: [], clicks: [], frames: 0, blocks: 0, error: null,
                             mouthMeta: [], stats: [], arrivals: []};
// every 200 ms, each track's jitter-buffer totals (their deltas: the delay of that window)
let lastDisplay = null;  // the newest frame's expectedDisplayTime (rVFC), for the polls below
setInterval(() => window.telesplat.session.pc.getStats().then((stats) => {
  const row = {t: performance.now(), lastDisplay};
  stats.forEach((s) => {
    if (s.type === 'inbound-rtp') {
      row[s.kind] = [s.jitterBufferDelay, s.jitterBufferEmittedCount, s.jitterBufferTargetDelay,
                     s.jitterBufferMinimumDelay];
      // Chromium's own estimate of the capture instant (the sender reports' NTP clock, ms)
      // of what it plays out now: its sync, without the page's WebAudio tap
      row[s.kind + 'Playout'] = s.estimatedPlayoutTimestamp;
    }
  });
  rec.stats.push(row);
}), 200);
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
    if (isOpen && !open) {
      rec.mouth.push(meta.expectedDisplayTime);
      rec.mouthMeta.push({receive: meta.receiveTime, capture: meta.captureTime,
                          display: meta.expectedDisplayTime, rtp: meta.rtpTimestamp});
    }
    open = isOpen;
  }
  lastDisplay = meta.expectedDisplayTime;
  if (meta.receiveTime) rec.arrivals.push([meta.receiveTime, meta.rtpTimestamp]);
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
    rec.latency = {base: ac.baseLatency * 1000, output: ac.outputLatency * 1000};
  } catch (err) { rec.error = String(err); }
})();
"""


JITTER_BUFFERS = """
const done = arguments[arguments.length - 1];
window.telesplat.session.pc.getStats().then((stats) => {
  const out = {};
  stats.forEach((s) => {
    if (s.type === 'inbound-rtp' && s.jitterBufferEmittedCount) {
      const n = s.jitterBufferEmittedCount;
      out[s.kind] = Math.round(1000 * s.jitterBufferDelay / n);
      out[s.kind + '_target'] = Math.round(1000 * (s.jitterBufferTargetDelay || 0) / n);
      out[s.kind + '_minimum'] = Math.round(1000 * (s.jitterBufferMinimumDelay || 0) / n);
    }
  });
  done(out);
});
"""


# the video receiver's jitterBufferTarget (ms): how long Chromium holds the picture at least
VIDEO_TARGET = """for (const r of window.telesplat.session.pc.getReceivers())
  if (r.track.kind === 'video') r.jitterBufferTarget = arguments[0];"""


def hold_setting(text: str) -> str | float:
    """``--hold``'s value: "page" (the page's lip sync), "off" (``?lipsync=0``) or a fixed
    jitterBufferTarget in ms (the page's lip sync off)."""
    if text in ("page", "off"):
        return text
    ms = float(text)
    if not 0 <= ms <= 10_000:
        raise argparse.ArgumentTypeError(f"a hold is page, off or 0-10000 ms, not {text!r}")
    return ms


async def perform(url: str, token: str, room: str, size: int, events: int, drive_hz: float,
                  driver, open_pixels: int, edges: str = "tick", hold: str | float = "page",
                  settle_s: float = 2.0) -> dict:
    performer: WhepViewer | None = None
    drives = JawDrives(lambda drive: performer.send(drive), drive_hz, edges)
    mic = click_microphone(lambda: drives.jaw(JAW_OPEN), [])
    performer = WhepViewer(url, room, token, width=128, height=128, role="perform", seat=0,
                           microphone=mic, timeout_s=60)
    async with performer:
        await performer.wait_open()
        await asyncio.to_thread(join_page, driver, url, token, room, size, open_pixels, hold)
        end = time.monotonic() + settle_s + events * EVENT_EVERY_S
        tracker = asyncio.create_task(drives.run(end))
        await asyncio.sleep(settle_s)
        await asyncio.to_thread(driver.execute_script, "window.__sync.reference = true;")
        await asyncio.sleep(0.5)
        for _ in range(events):
            mic.fire()
            await asyncio.sleep(OPEN_S)
            drives.jaw(0.0)
            await asyncio.sleep(EVENT_EVERY_S - OPEN_S)
        await tracker
        await asyncio.sleep(1.0)
        rec = await asyncio.to_thread(driver.execute_script, "return window.__sync;")
        rec["buffers"] = await asyncio.to_thread(driver.execute_async_script, JITTER_BUFFERS)
        rec["hold"] = await asyncio.to_thread(
            driver.execute_script, "const l = window.telesplat.session.lipSync; "
            "return l ? {hold: l.hold} : null;")
        return rec


def join_page(driver, url: str, token: str, room: str, size: int, open_pixels: int,
              hold: str | float = "page") -> None:
    from tests.test_client_browser import wait_for
    from tests.test_webrtc_browser import wait_playing

    link = httpx.post(f"{url}/v1/rooms/{room}/invitations", json={"scope": "watch"},
                      headers={"Authorization": f"Bearer {token}"}, timeout=30).json()["link"]
    if hold != "page":  # the page's lip sync off
        link = link.replace("?", "?lipsync=0&", 1) if "?" in link else f"{link}?lipsync=0"
    driver.get(f"{url}{link}")
    wait_playing(driver, 512)  # the page's default, then its #size menu's choice
    driver.execute_script("""const size = document.getElementById('size');
        size.value = arguments[0]; size.dispatchEvent(new Event('change'));""", str(size))
    wait_for(driver, f"document.getElementById('video').videoWidth === {size}", 60, "the size")
    wait_for(driver, "document.querySelector('#voices audio')", 60, "the seat's <audio>")
    driver.execute_script(RECORDER, open_pixels, STAMP_ROWS)
    if not isinstance(hold, str):  # the picture held this long at least (before the events)
        driver.execute_script(VIDEO_TARGET, hold)
    wait_for(driver, "window.__sync.blocks > 10 || window.__sync.error", 30, "the worklet")


def window_delay(stats: list[dict], kind: str, at: float, span: float = 600.0) -> float | None:
    """``kind``'s mean jitter-buffer delay (ms) over the getStats samples within ``span`` ms
    before ``at`` (performance time): what the buffer held then, not the run's mean."""
    rows = [r for r in stats if kind in r and at - span <= r["t"] <= at]
    if len(rows) < 2 or rows[-1][kind][1] <= rows[0][kind][1]:
        return None
    return 1e3 * (rows[-1][kind][0] - rows[0][kind][0]) / (rows[-1][kind][1] - rows[0][kind][1])


def picture_lag(rec: dict, at: float, span: float = 2000.0) -> float:
    """The frames' arrival less their RTP time (capture, with the capture clock), median over
    the ``span`` ms before ``at``, less the run's least: how late the picture came then."""
    rows = np.asarray(rec.get("arrivals", []), dtype=float)
    if len(rows) < 2:
        return np.nan
    lag = rows[:, 0] - np.unwrap(rows[:, 1], period=2**32) / 90.0
    near = lag[(rows[:, 0] >= at - span) & (rows[:, 0] <= at)]
    return float(np.median(near) - lag.min()) if len(near) else np.nan


def explain(rec: dict) -> str:
    """Per paired event, the parts of its offset the page can see: the video frame's wait
    from its last packet to display (rVFC expectedDisplayTime - receiveTime), its receive time
    less the capture time Chromium estimated from the reports (captureTime), and the audio
    and video jitter-buffer delays of the 0.6 s before it; with each one's correlation with
    the offset (which part makes the spread)."""
    clicks = np.asarray(rec["clicks"])
    rows = []
    for meta in rec.get("mouthMeta", []):
        mouth = meta["display"]
        if not len(clicks):
            break
        nearest = clicks[np.argmin(np.abs(clicks - mouth))]
        if abs(nearest - mouth) >= EVENT_EVERY_S * 1e3 / 2:
            continue
        wait = mouth - meta["receive"] if meta.get("receive") else np.nan
        transit = (meta["receive"] - meta["capture"] if meta.get("capture") and meta.get("receive")
                   else np.nan)
        audio = window_delay(rec.get("stats", []), "audio", nearest)
        video = window_delay(rec.get("stats", []), "video", mouth)
        rows.append((nearest - mouth, wait, transit, np.nan if audio is None else audio,
                     np.nan if video is None else video, picture_lag(rec, mouth)))
    if len(rows) < 3:
        return "too few events to explain"
    arr = np.asarray(rows, dtype=float)
    parts = []
    for i, name in enumerate(("video wait (display - receive)", "video receive - capture",
                              "audio jitter buffer", "video jitter buffer",
                              "picture lag (receive - RTP time, 2 s median, less its least)"),
                             start=1):
        col = arr[:, i]
        ok = ~np.isnan(col)
        if ok.sum() < 3:
            parts.append(f"{name}: not given")
            continue
        r = np.corrcoef(arr[ok, 0], col[ok])[0, 1]
        parts.append(f"{name}: median {np.median(col[ok]):.0f}, p5-p95 "
                     f"{np.percentile(col[ok], 5):.0f}-{np.percentile(col[ok], 95):.0f} ms, "
                     f"corr with the offset {r:+.2f}")
    return "; ".join(parts)


def playout_skews(rec: dict) -> list[float]:
    """Chromium's own view of its sync, per getStats poll: the capture instant (the sender
    reports' NTP clock) the picture shows at the poll less the one the voice plays (> 0: the
    voice plays older capture than the picture, i.e. late, as the offset's sign). A track's
    ``estimatedPlayoutTimestamp`` is its last played media's: the picture's is its last
    frame's, so it is carried forward by the time since that frame's display (rVFC)."""
    out = []
    for r in rec.get("stats", []):
        video, audio, shown = r.get("videoPlayout"), r.get("audioPlayout"), r.get("lastDisplay")
        if video and audio and shown is not None and 0 <= r["t"] - shown < 200:
            out.append(video + (r["t"] - shown) - audio)
    return out


def hold_text(hold: str | float, page: dict | None) -> str:
    """The --hold setting, and the page's own hold at the end when its lip sync ran."""
    setting = hold if isinstance(hold, str) else f"{hold:g} ms"
    return f"{setting} ({page['hold']} ms)" if page else setting


def playout_skew(rec: dict, skew: list[float]) -> str:
    """Chromium's own sync (``skew``: playout_skews) for the log, or why it was not given."""
    if not skew:
        rows = rec.get("stats", [])
        return (f"estimatedPlayoutTimestamp: not given (of {len(rows)} polls, video's in "
                f"{sum(bool(r.get('videoPlayout')) for r in rows)}, audio's in "
                f"{sum(bool(r.get('audioPlayout')) for r in rows)}, a frame shown before in "
                f"{sum(r.get('lastDisplay') is not None for r in rows)})")
    return (f"Chromium's own sync (estimatedPlayoutTimestamp, the picture's carried to the "
            f"poll) video - audio, median (p5 / p95) ms: {spread_text(skew)} ({len(skew)} "
            f"polls); WebAudio latency ms {rec.get('latency')}")


def offsets(rec: dict) -> list[float]:
    clicks = np.asarray(rec["clicks"])
    out = []
    for mouth in rec["mouth"]:
        if len(clicks):
            nearest = clicks[np.argmin(np.abs(clicks - mouth))]
            if abs(nearest - mouth) < EVENT_EVERY_S * 1e3 / 2:
                out.append(float(nearest - mouth))
    return out


def run_once(args, hold: str | float = "page") -> dict:
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
                                     driver, args.open_pixels, args.edge_drive, hold,
                                     args.settle_s)

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
    parser.add_argument("--edge-drive", default="tick", choices=("tick", "extra"),
                        help="a jaw edge is one of the drive-hz drives, or a drive between "
                             "them (bench/voice_sync.py's JawDrives)")
    parser.add_argument("--avatar", default="synthetic")
    parser.add_argument("--hold", default="page",
                        help="how the page holds its picture for the voice, per run, side by "
                             "side with the server settings: page (its lip sync, "
                             "client/web/lipsync.js), off (?lipsync=0: Chromium's own sync "
                             "only) or a fixed video jitterBufferTarget in ms; e.g. page,off,60")
    parser.add_argument("--settle-s", type=float, default=15.0,
                        help="drives before the first event, for Chromium's sync and the "
                             "page's hold to settle")
    add_server_voice_args(parser)
    args = parser.parse_args()
    holds = [hold_setting(t) for t in args.hold.split(",")]

    os.environ["TELESPLAT_WEBRTC_MAX_PEERS"] = "4"
    print("| viewer | pacing | sender clock | voice_max_delay_s | drives/s | edge drive | events "
          "| paired | "
          "median ms | p5 / p95 ms | min / max ms | within -45/+125 | jitter buffer ms: "
          "audio (target) / video (target) | Chromium's own sync: median (p5 / p95) ms "
          "| picture hold: setting (the page's at the end, ms) |")
    print("|---" * 15 + "|")
    for pacing, clock, delay in server_voice_runs(args):  # sets the server's environment
        for hold in holds:
            rec = run_once(args, hold)
            arr = np.asarray(offsets(rec))
            print(f"# {pacing} {clock} {delay} hold {hold}: frames {rec['frames']}, audio blocks "
                  f"{rec['blocks']}, mouth edges {len(rec['mouth'])}, clicks {len(rec['clicks'])}, "
                  f"audio {rec.get('context')}, error {rec['error']}, getStats {rec['buffers']}; "
                  f"offsets ms {[round(x) for x in arr]}", file=sys.stderr, flush=True)
            skew = playout_skews(rec)
            print(f"# {pacing} {clock} {delay} hold {hold}, per event: {explain(rec)}; "
                  f"{playout_skew(rec, skew)}", file=sys.stderr, flush=True)
            b = rec["buffers"]
            buffers = (f"{b.get('audio', '-')} ({b.get('audio_target', '-')}) / "
                       f"{b.get('video', '-')} ({b.get('video_target', '-')})")
            if len(arr):
                print(f"| Chromium | {pacing} | {clock} | {delay} | {args.drive_hz:g} | "
                      f"{args.edge_drive} | "
                      f"{args.events} | {len(arr)} | "
                      f"{np.median(arr):.0f} | {np.percentile(arr, 5):.0f} / "
                      f"{np.percentile(arr, 95):.0f} | {arr.min():.0f} / {arr.max():.0f} | "
                      f"{((arr >= -45) & (arr <= 125)).mean():.0%} | {buffers} | "
                      f"{spread_text(skew)} | {hold_text(hold, rec.get('hold'))} |",
                      flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
