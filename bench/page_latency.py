"""The page's own drive -> frame latency, WebSocket and WebRTC side by side in one run.

    OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python bench/page_latency.py [--drives 40]
        [--rate 5] [--render-threads 2]

Starts its own server (as `bench/stream.py` does: a subprocess on a free port, the demo
avatar, a fresh data dir) and, one after the other, a headless Chromium page per transport
(`?transport=ws`; WebRTC: the page's default, WHEP with `stamp=1`). Each page moves its "jaw
open" slider `--drives` times at `--rate` Hz, as a user would, and records every latency the
page measures: WebSocket frames carry their drive's seq; WebRTC frames carry it stamped in
their pixels, read back from each presented frame (client/web/rtcstats.js). Reported: drives
sent, latencies measured, p50 / p95 / max, and what reading one stamp costs the page (drawImage
of the strip + getImageData + readStamp, mean over 200 reads of the playing <video>).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
for path in (ROOT, ROOT / "bench"):
    if str(path) not in sys.path:
        sys.path.insert(0, str(path))

from stream import percentile, start_server, stop_server  # noqa: E402

from tests.test_client_browser import wait_for  # noqa: E402
from tests.test_client_units import make_chromium  # noqa: E402
from tests.test_webrtc_browser import make_webrtc_chromium  # noqa: E402

WAIT_S = 120.0
# Every latency the page measures, kept (the overlay keeps only the last 2 s).
COLLECT = """
window.__latencies = [];
const s = window.telesplat.session;
s.addEventListener("frame", (e) => {
  if (e.detail.latencyMs != null) window.__latencies.push(e.detail.latencyMs); });
s.addEventListener("shown", (e) => window.__latencies.push(e.detail.latencyMs));
"""
STAMP_READ_COST = """
const { readStamp, stampCell } = await import("./rtcstats.js");
const video = document.getElementById("video");
const cell = stampCell(video.videoWidth);
const canvas = document.createElement("canvas");
canvas.width = 32 * cell; canvas.height = cell;
const ctx = canvas.getContext("2d", { willReadFrequently: true });
const t0 = performance.now();
let read = 0;
for (let i = 0; i < 200; i += 1) {
  ctx.drawImage(video, 0, 0, canvas.width, cell, 0, 0, canvas.width, cell);
  if (readStamp(ctx.getImageData(0, 0, canvas.width, cell).data, cell) !== null) read += 1;
}
return { ms: (performance.now() - t0) / 200, read };
"""


def run_page(driver, url: str, transport: str, drives: int, rate: float) -> dict:
    driver.get(url)
    wait_for(driver, f"window.telesplat?.transport === '{transport}' && "
                     "window.telesplat.session?.welcome && window.telesplat.framesShown > 0",
             WAIT_S, f"the {transport} page's frames")
    driver.execute_script(COLLECT)
    for i in range(drives):
        driver.execute_script(
            "const input = document.querySelector('input[data-param=\"jaw open\"]');"
            f"input.value = {0.05 + 0.4 * (i % 2)}; input.dispatchEvent(new Event('input'));")
        time.sleep(1.0 / rate)
    time.sleep(2.0)  # the last frames
    latencies = driver.execute_script("return window.__latencies")
    cost = (driver.execute_async_script(
        "const done = arguments[arguments.length - 1];"
        f"(async () => {{ {STAMP_READ_COST} }})().then(done);")
        if transport == "webrtc" else None)
    return {"latencies": latencies, "cost": cost}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--drives", type=int, default=40)
    parser.add_argument("--rate", type=float, default=5.0, help="drives per second")
    parser.add_argument("--render-threads", type=int, default=2)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        proc, base, token = start_server(Path(tmp), args.render_threads, 8, "synthetic")
        try:
            rows = []
            for transport, make in (("ws", make_chromium), ("webrtc", make_webrtc_chromium)):
                driver = make()
                try:
                    query = "transport=ws" if transport == "ws" else "transport=webrtc"
                    out = run_page(driver, f"{base}/?{query}#token={token}", transport,
                                   args.drives, args.rate)
                finally:
                    driver.quit()
                rows.append((transport, out))
        finally:
            stop_server(proc)
    print(f"\n{args.drives} drives at {args.rate:g} Hz, 512 px frames (the page's default), "
          "page in headless Chromium, server on this machine")
    print("| transport | latencies measured | p50 ms | p95 ms | max ms "
          "| stamp read ms (reads ok) |")
    print("|---|---:|---:|---:|---:|---:|")
    for transport, out in rows:
        ms = sorted(out["latencies"])
        cost = out["cost"]
        read = "–" if cost is None else f"{cost['ms']:.3f} ({cost['read']} of 200)"
        p50, p95 = percentile(ms, 50), percentile(ms, 95)
        print(f"| {transport} | {len(ms)} | {p50:.0f} | {p95:.0f} | {max(ms):.0f} | {read} |"
              if ms else f"| {transport} | 0 | – | – | – | {read} |")


if __name__ == "__main__":
    main()
