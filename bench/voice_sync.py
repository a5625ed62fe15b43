"""Lip sync of a room's voice at aiortc viewers: click onset vs mouth opening (issue 30).

Starts its own server (bench/stream.py's start_server). A performer (aiortc, WHEP with
role=perform and a microphone track) opens the jaw at each event and, in the same instant, puts
a 5 ms click in its next 20 ms audio frame; 300 ms later the jaw closes. ``--viewers`` aiortc
WHEP viewers (one recvonly audio line each, video released at its RTP marker as a browser
does) record, for every event:

- the mouth opening: the decode time of the first frame in which more than ``--open-pixels``
  pixels differ from the closed-mouth frame by more than 25 grey levels;
- the click onset: the arrival time of the RTP packet whose decoded frame holds the click
  (arrival, not aiortc's jitter-buffer release, which adds ~4 packets a browser would not);
- offset = click - mouth (ms): positive when the voice is late. Targets (ITU-R BT.1359):
  |median| <= 20 ms, every event within -45 / +125 ms;
- the longest gap between audio packets each viewer received (target <= 60 ms at 16 viewers).

Each line of the table is one run: (viewers, bit-rate cap). The cap is the server's
``webrtc_max_bitrate`` (TELESPLAT_WEBRTC_MAX_BITRATE), on the video encoder.

    nice -n 10 .venv/bin/python bench/voice_sync.py [--events 50] [--viewers 1,16]
        [--caps 0,500000] [--size 128]
"""

from __future__ import annotations

import argparse
import asyncio
import fractions
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
from webrtc import cpu_seconds, release_at_marker  # noqa: E402

from client.webrtc import WhepViewer  # noqa: E402
from protocol import Drive  # noqa: E402

RATE = 48_000
FRAME = 960
EVENT_EVERY_S = 0.7
OPEN_S = 0.3
JAW_OPEN = 0.5
CLICK_LEVEL = 0.3


def click_microphone(on_click):
    """An aiortc audio track in real time; ``fire()`` puts a click in the next frame and calls
    ``on_click()`` as that frame is handed to the encoder (one instant for voice and jaw)."""
    import av
    from aiortc import MediaStreamTrack

    class Mic(MediaStreamTrack):
        kind = "audio"

        def __init__(self) -> None:
            super().__init__()
            self.sent, self.start, self.pending = 0, None, False

        def fire(self) -> None:
            self.pending = True

        async def recv(self):
            if self.start is None:
                self.start = time.monotonic()
            due = self.start + self.sent * FRAME / RATE
            await asyncio.sleep(max(0.0, due - time.monotonic()))
            samples = np.zeros((1, FRAME), np.int16)
            if self.pending:
                self.pending = False
                t = np.arange(240) / RATE
                samples[0, :240] = (30000 * np.sin(2 * np.pi * 2000 * t)).astype(np.int16)
                on_click()
            frame = av.AudioFrame.from_ndarray(samples, format="s16", layout="mono")
            frame.sample_rate, frame.pts = RATE, self.sent * FRAME
            frame.time_base = fractions.Fraction(1, RATE)
            self.sent += 1
            return frame

    return Mic()


class Ear:
    """One viewer's record: mouth-open edges and click onsets (time.monotonic())."""

    def __init__(self, viewer: WhepViewer, open_pixels: int) -> None:
        self.viewer, self.open_pixels = viewer, open_pixels
        self.closed: np.ndarray | None = None
        self.mouth: list[float] = []
        self.clicks: list[float] = []
        self.arrivals: dict[int, float] = {}  # RTP timestamp - first -> arrival
        self.packet_times: list[float] = []
        self._open = False
        self._first_ts: int | None = None

    def hook_audio(self) -> None:
        receiver = next(r for r in self.viewer.pc.getReceivers() if r.track.kind == "audio")
        original = receiver._handle_rtp_packet

        async def handle(packet, arrival_time_ms: int = 0):
            now = time.monotonic()
            if self._first_ts is None:
                self._first_ts = packet.timestamp
            self.arrivals[(packet.timestamp - self._first_ts) % 2**32] = now
            self.packet_times.append(now)
            await original(packet, arrival_time_ms=arrival_time_ms)

        receiver._handle_rtp_packet = handle

    async def watch_video(self, end: float) -> None:
        while time.monotonic() < end:
            try:
                rgb, at = await self.viewer.next_frame(timeout=2.0)
            except TimeoutError:
                continue
            grey = rgb.mean(axis=2)
            if self.closed is None:
                self.closed = grey
                continue
            is_open = int((np.abs(grey - self.closed) > 25).sum()) > self.open_pixels
            if is_open and not self._open:
                self.mouth.append(at)
            self._open = is_open

    async def listen(self, end: float) -> None:
        loud = False
        while time.monotonic() < end:
            try:
                frame, at = await self.viewer.next_audio(timeout=2.0)
            except TimeoutError:
                continue
            peak = np.abs(frame.to_ndarray()).max() / 32768
            if peak > CLICK_LEVEL and not loud:
                self.clicks.append(self.arrivals.get(frame.pts, at))
            loud = peak > CLICK_LEVEL


def pair(events: list[float], later: list[float], window: float = EVENT_EVERY_S
         ) -> list[float | None]:
    """For each event, the first time in ``later`` within ``window`` s after it."""
    out = []
    for t in events:
        hits = [x for x in later if t <= x <= t + window]
        out.append(hits[0] if hits else None)
    return out


async def run(url: str, token: str, viewers: int, events: int, size: int,
              open_pixels: int, pid: int, voice: bool = True) -> dict:
    async with httpx.AsyncClient(base_url=url, timeout=30) as http:
        room = (await http.post("/v1/rooms", headers={"Authorization": f"Bearer {token}"},
                                json={"seats": [{"avatar": "demo"}]})).json()["id"]
    fired: list[float] = []
    seq = iter(range(1, 10**6))
    performer: WhepViewer | None = None

    def jaw(angle: float) -> None:
        performer.send(Drive(seq=next(seq), smplx={"jaw_pose": [angle, 0.0, 0.0]},
                             t_capture=time.monotonic()))

    def clicked() -> None:
        fired.append(time.monotonic())
        jaw(JAW_OPEN)

    mic = click_microphone(clicked)
    performer = WhepViewer(url, room, token, width=size, height=size, role="perform", seat=0,
                           microphone=mic if voice else None, timeout_s=60)
    ears = [Ear(WhepViewer(url, room, token, width=size, height=size, role="watch",
                           voices=1, timeout_s=60), open_pixels) for _ in range(viewers)]
    async with performer:
        await performer.wait_open()
        for ear in ears:
            await ear.viewer.start()
            release_at_marker(ear.viewer)
            ear.hook_audio()
        await asyncio.gather(*(e.viewer.next_frame() for e in ears))
        await asyncio.sleep(2.0)  # the closed-mouth reference settles
        end = time.monotonic() + 3.0 + events * EVENT_EVERY_S
        tasks = [asyncio.create_task(t) for e in ears
                 for t in (e.watch_video(end), e.listen(end) if voice else asyncio.sleep(0))]
        cpu0, t0 = cpu_seconds(pid), time.monotonic()
        for _ in range(events):
            if voice:
                mic.fire()
            else:
                clicked()
            await asyncio.sleep(OPEN_S)
            jaw(0.0)
            await asyncio.sleep(EVENT_EVERY_S - OPEN_S)
        await asyncio.gather(*tasks)
        cpu = (cpu_seconds(pid) - cpu0) / (time.monotonic() - t0)
        for ear in ears:
            await ear.viewer.close()
    offsets, missed, gaps = [], 0, []
    for ear in ears:
        for mouth, click in zip(pair(fired, ear.mouth), pair(fired, ear.clicks), strict=True):
            if mouth is None or click is None:
                missed += 1
            else:
                offsets.append((click - mouth) * 1e3)
        times = np.diff(ear.packet_times[len(ear.packet_times) // 10:])
        gaps.append(float(times.max() * 1e3) if len(times) else float("nan"))
    arr = np.asarray(offsets)
    print(f"# {viewers} viewers: fired {len(fired)}, mouth edges {[len(e.mouth) for e in ears]},"
          f" clicks {[len(e.clicks) for e in ears]}, audio packets "
          f"{[len(e.packet_times) for e in ears]}; first ear, ms after each event: mouth "
          f"{[round((m - f) * 1e3) for f, m in zip(fired, ears[0].mouth, strict=False)]}, "
          f"click {[round((c - f) * 1e3) for f, c in zip(fired, ears[0].clicks, strict=False)]}",
          file=sys.stderr, flush=True)
    return {"viewers": viewers, "events": len(fired), "paired": len(offsets), "missed": missed,
            "median_ms": float(np.median(arr)) if len(arr) else float("nan"),
            "p5_ms": float(np.percentile(arr, 5)) if len(arr) else float("nan"),
            "p95_ms": float(np.percentile(arr, 95)) if len(arr) else float("nan"),
            "min_ms": float(arr.min()) if len(arr) else float("nan"),
            "max_ms": float(arr.max()) if len(arr) else float("nan"),
            "within": float(((arr >= -45) & (arr <= 125)).mean()) if len(arr) else 0.0,
            "max_gap_ms": max(gaps), "cpu": cpu}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--events", type=int, default=50)
    parser.add_argument("--viewers", default="1,16")
    parser.add_argument("--caps", default="0,500000", help="webrtc_max_bitrate per run; 0: "
                                                           "the default")
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--open-pixels", type=int, default=8)
    parser.add_argument("--avatar", default="synthetic")
    parser.add_argument("--voice", default="on", help="on, off or on,off: runs with and "
                                                      "without the performer's microphone "
                                                      "(the server CPU it costs)")
    args = parser.parse_args()
    print("| viewers | cap bit/s | events | paired | missed | median ms | p5 / p95 ms | "
          "min / max ms | within -45/+125 | longest audio gap ms | voice | server CPU s/s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    most = max(int(v) for v in args.viewers.split(","))
    os.environ["TELESPLAT_WEBRTC_MAX_PEERS"] = str(most + 2)  # the viewers and the performer
    for cap in (int(c) for c in args.caps.split(",")):
        if cap:
            os.environ["TELESPLAT_WEBRTC_MAX_BITRATE"] = str(cap)
            os.environ["TELESPLAT_WEBRTC_MIN_BITRATE"] = str(min(cap, 250_000))
        with tempfile.TemporaryDirectory() as tmp:
            proc, url, token = start_server(Path(tmp), 1, 64, args.avatar)
            try:
                for n in (int(v) for v in args.viewers.split(",")):
                    for voice in args.voice.split(","):
                        r = asyncio.run(run(url, token, n, args.events, args.size,
                                            args.open_pixels, proc.pid, voice == "on"))
                        print(f"| {n} | {cap or 'default'} | {r['events']} | {r['paired']} | "
                              f"{r['missed']} | {r['median_ms']:.0f} | {r['p5_ms']:.0f} / "
                              f"{r['p95_ms']:.0f} | {r['min_ms']:.0f} / {r['max_ms']:.0f} | "
                              f"{r['within']:.0%} | {r['max_gap_ms']:.0f} | {voice} | "
                              f"{r['cpu']:.2f} |", flush=True)
            finally:
                stop_server(proc)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
