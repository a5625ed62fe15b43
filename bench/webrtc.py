"""Transports side by side in one run: WebSocket JPEG, WebSocket H.264, WebRTC VP8, WebRTC H.264.

Starts its own server (bench/stream.py's start_server: ``python -m server`` on a free port,
the demo avatar of ``--avatar``, a fresh data dir). Each transport joins a fresh room as the
performer of seat 0 (WebSocket: a room join; WebRTC: WHEP with ``seat=0&stamp=1``), drives a
talking-and-gesturing motion at ``--rate`` Hz for ``--seconds`` and decodes every frame:

- fps: decoded frames per second;
- server CPU per frame: the server process's CPU time (user + system, all threads) over the
  window divided by the frames the viewer decoded (render + pose + encode + send);
- bytes: WebSocket: the frames' payloads; WebRTC: bytes the DTLS transport received (RTP,
  RTCP and the data channel: a little more than the video alone);
- PSNR of decoded frames against the rendered ones: after the window, the same poses are
  rendered again losslessly (PNG over a WebSocket, a fresh room, same view) and compared; the
  top rows holding the frame stamp are left out of every comparison;
- equal-PSNR JPEG: what the server's JPEG (OpenCV, as server/stream/encoders/) needs for the same
  PSNR on those reference frames (lowest quality reaching it), times the row's fps: the
  bytes a JPEG stream would need for that picture quality;
- drive -> decoded-frame latency: WebSocket frames carry the seq of the newest drive they
  show; WebRTC frames carry it stamped in their pixels (protocol/stamp.py, ``stamp=1``). The
  WebRTC viewer's receiver releases each frame at its last packet, as a browser does
  (release_at_marker; ``--aiortc-jitter-buffer`` keeps aiortc's, one frame interval later).

Then the 500 kbit/s cap, at ``--cap-size``, for ``--cap-seconds``: WebRTC with the encoder's
bit rate capped (a second server with TELESPLAT_WEBRTC_MAX_BITRATE=500000; aiortc's
congestion control then works below it); the WebSocket streams through a TCP relay in this
process that forwards the server's bytes at 500 kbit/s. fps and latency in the first and the
last third, and the latency trend (least-squares slope, ms per second): a growing delay
shows as a positive slope that does not level off.

    nice -n 10 .venv/bin/python bench/webrtc.py [--sizes 512,1024] [--seconds 10]
        [--rate 30] [--samples 20] [--cap-seconds 20] [--cap-size 512] [--avatar trained]

Targets (issue 16): WebRTC >= 25 fps and p95 <= 100 ms on loopback for one viewer; under the
500 kbit/s cap >= 15 fps with no growing delay.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import platform
import sys
import tempfile
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from stream import motion_frame, percentile, start_server, stop_server  # noqa: E402

from client import StreamClient  # noqa: E402
from client.webrtc import WhepViewer  # noqa: E402
from protocol import Drive  # noqa: E402
from protocol.stamp import cell_size, read_stamp  # noqa: E402
from server.stream.encoders import H264Decoder, encode_jpeg  # noqa: E402

TRANSPORTS = ("ws-jpeg", "ws-h264", "webrtc-vp8", "webrtc-h264")
WARMUP_S = 2.0          # connect, first keyframe, the congestion estimate's first steps
CAP_BITRATE = 500_000   # bit/s
RELAY_CHUNK = 4096      # bytes the capped relay forwards at a time
GROWING_MS_PER_S = 1.0  # a latency trend above this counts as a growing delay


# -- measuring ------------------------------------------------------------------------------


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process, all its threads (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


@dataclass
class Run:
    transport: str
    size: int
    seconds: float = 0.0
    frames: int = 0
    bytes: int = 0
    cpu_s: float = 0.0
    codec: str = ""
    latencies: list[tuple[float, float]] = field(default_factory=list)  # (t since start, ms)
    samples: list[tuple[int, np.ndarray]] = field(default_factory=list)  # (seq, decoded rgb)
    psnr: float = float("nan")
    jpeg_equal_bytes_per_frame: float = float("nan")
    motion: Motion | None = field(default=None, repr=False)  # the drives sent

    @property
    def fps(self) -> float:
        return self.frames / self.seconds if self.seconds else 0.0

    def latency(self, q: float) -> float:
        return percentile([ms for _, ms in self.latencies], q)


class Motion:
    """The drives sent: seq -> (monotonic time sent, the pose)."""

    def __init__(self) -> None:
        self.sent: dict[int, tuple[float, dict[str, np.ndarray]]] = {}
        self.t0 = time.monotonic()

    def next(self) -> tuple[int, dict[str, np.ndarray]]:
        seq = len(self.sent) + 1
        pose = motion_frame(time.monotonic() - self.t0, 0.0)
        self.sent[seq] = (time.monotonic(), pose)
        return seq, pose


class Window:
    """The measured window after the warm-up: frames, latencies and evenly spread samples."""

    def __init__(self, run: Run, seconds: float, samples: int) -> None:
        self.run, self.samples = run, samples
        self.start = time.monotonic() + WARMUP_S
        self.end = self.start + seconds
        self.every = seconds / max(1, samples)
        self.next_sample = self.start

    def frame(self, rgb: np.ndarray, seq: int | None, received: float, motion: Motion) -> None:
        if not self.start <= received < self.end:
            return
        self.run.frames += 1
        if seq is None or seq not in motion.sent:
            return
        self.run.latencies.append((received - self.start,
                                   1000 * (received - motion.sent[seq][0])))
        if received >= self.next_sample and len(self.run.samples) < self.samples:
            self.run.samples.append((seq, rgb.copy()))
            self.next_sample += self.every


async def drive_loop(rate: float, end: float, send) -> None:
    """`send()` at `rate` Hz until the monotonic deadline `end`."""
    t0, i = time.monotonic(), 0
    while time.monotonic() < end:
        delay = t0 + i / rate - time.monotonic()
        if delay > 0:
            await asyncio.sleep(delay)
        await send()
        i += 1


async def new_room(url: str, token: str) -> str:
    async with httpx.AsyncClient(base_url=url, timeout=30,
                                 headers={"Authorization": f"Bearer {token}"}) as http:
        response = await http.post("/v1/rooms", json={"seats": [{"avatar": "demo"}]})
        response.raise_for_status()
        return response.json()["id"]


async def delete_room(url: str, token: str, room: str) -> None:
    async with httpx.AsyncClient(base_url=url, timeout=30,
                                 headers={"Authorization": f"Bearer {token}"}) as http:
        await http.delete(f"/v1/rooms/{room}")


# -- one transport --------------------------------------------------------------------------


async def run_websocket(url: str, token: str, codec: str, run: Run, pid: int | None,
                        seconds: float, rate: float, samples: int,
                        stream_url: str | None = None) -> None:
    """A room join over the WebSocket (at `stream_url`, e.g. a capped relay, if given)."""
    room = await new_room(url, token)
    run.motion = motion = Motion()
    decoder = H264Decoder() if codec == "h264" else None
    try:
        async with await StreamClient.connect(stream_url or url, token=token, room=room,
                                              role="perform", seat=0, client_name="bench-ws",
                                              timeout=60) as client:
            await client.request(width=run.size, height=run.size, codec=codec, max_fps=rate)
            window = Window(run, seconds, samples)
            cpu0 = cpu_at = None

            async def send() -> None:
                seq, pose = motion.next()
                await client.drive(pose, seq=seq)

            driver = asyncio.create_task(drive_loop(rate, window.end, send))
            try:
                while time.monotonic() < window.end:  # bounded by the window's end
                    if cpu0 is None and time.monotonic() >= window.start and pid:
                        cpu0, cpu_at = cpu_seconds(pid), time.monotonic()
                    try:
                        frame = await client.next_frame(max(0.01, window.end - time.monotonic()))
                    except TimeoutError:
                        break
                    if frame.codec != codec or frame.width != run.size:
                        continue  # sent before the request landed
                    if decoder is not None:
                        pictures = decoder.decode(frame.data)
                        if not pictures:
                            continue
                        rgb = pictures[-1]
                    else:
                        rgb = cv2.imdecode(np.frombuffer(frame.data, np.uint8),
                                           cv2.IMREAD_COLOR)[..., ::-1]
                    received = time.monotonic()
                    if window.start <= received < window.end:
                        run.bytes += len(frame.data)
                    window.frame(rgb, frame.seq, received, motion)
            finally:
                driver.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await driver
            if cpu0 is not None:
                run.cpu_s = cpu_seconds(pid) - cpu0
                run.seconds = time.monotonic() - cpu_at
            else:
                run.seconds = seconds
            run.codec = codec
    finally:
        await delete_room(url, token, room)


async def transport_bytes(viewer: WhepViewer) -> int:
    stats = await viewer.stats()
    return sum(getattr(s, "bytesReceived", 0) for s in stats.values()
               if type(s).__name__ == "RTCTransportStats")


async def run_webrtc(url: str, token: str, codec: str, run: Run, pid: int | None,
                     seconds: float, rate: float, samples: int, marker: bool = True) -> None:
    room = await new_room(url, token)
    run.motion = motion = Motion()
    try:
        viewer = WhepViewer(url, room, token, width=run.size, height=run.size, fps=rate, seat=0,
                            stamp=True, codec=codec, release_at_marker=marker, timeout_s=60)
        await viewer.start()
        try:
            await viewer.wait_open()
            welcome = await viewer.welcome()
            run.codec = (viewer.codec or codec).removeprefix("video/")
            window = Window(run, seconds, samples)
            limits = {"limits": welcome.limits}
            cpu0 = bytes0 = cpu_at = None

            async def send() -> None:
                seq, pose = motion.next()
                viewer.send(Drive.model_validate({"seq": seq, "smplx": pose}, context=limits))

            driver = asyncio.create_task(drive_loop(rate, window.end, send))
            try:
                while time.monotonic() < window.end:  # bounded by the window's end
                    if cpu0 is None and time.monotonic() >= window.start:
                        cpu0 = cpu_seconds(pid) if pid else 0.0
                        bytes0, cpu_at = await transport_bytes(viewer), time.monotonic()
                    try:
                        rgb, received = await viewer.next_frame(
                            max(0.01, window.end - time.monotonic()))
                    except TimeoutError:
                        break
                    window.frame(rgb, read_stamp(rgb), received, motion)
            finally:
                driver.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await driver
            if cpu0 is not None:
                run.cpu_s = (cpu_seconds(pid) - cpu0) if pid else 0.0
                run.bytes = await transport_bytes(viewer) - bytes0
                run.seconds = time.monotonic() - cpu_at
        finally:
            await viewer.close()
    finally:
        await delete_room(url, token, room)


# -- picture quality ------------------------------------------------------------------------


def psnr(a: np.ndarray, b: np.ndarray, skip_rows: int) -> float:
    diff = a[skip_rows:].astype(np.float64) - b[skip_rows:].astype(np.float64)
    mse = float(np.mean(diff * diff))
    return 99.0 if mse == 0 else 10 * np.log10(255.0 ** 2 / mse)


async def references(url: str, token: str, run: Run) -> list[np.ndarray]:
    """The run's sampled poses rendered again, lossless (PNG), in a fresh room."""
    room = await new_room(url, token)
    motion = run.motion
    out = []
    try:
        async with await StreamClient.connect(url, token=token, room=room, role="perform",
                                              seat=0, client_name="bench-ref",
                                              timeout=60) as client:
            await client.request(width=run.size, height=run.size, codec="png")
            for seq, _ in run.samples:
                sent = await client.drive(motion.sent[seq][1])
                frame = await client.wait_frame(sent, timeout=60)
                out.append(cv2.imdecode(np.frombuffer(frame.data, np.uint8),
                                        cv2.IMREAD_COLOR)[..., ::-1])
    finally:
        await delete_room(url, token, room)
    return out


def jpeg_bytes_at(refs: list[np.ndarray], target_db: float, skip_rows: int) -> float:
    """Mean JPEG bytes per frame at the lowest quality whose mean PSNR reaches `target_db`."""
    def at(quality: int) -> tuple[float, float]:
        sizes, values = [], []
        for ref in refs:
            data = encode_jpeg(ref, quality)
            sizes.append(len(data))
            back = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
            values.append(psnr(back, ref, skip_rows))
        return float(np.mean(values)), float(np.mean(sizes))

    lo, hi = 1, 100
    if at(hi)[0] < target_db:
        return float("nan")  # JPEG cannot reach it
    while lo < hi:  # PSNR grows with quality: the lowest quality that reaches the target
        mid = (lo + hi) // 2
        if at(mid)[0] >= target_db:
            hi = mid
        else:
            lo = mid + 1
    return at(lo)[1]


async def score(url: str, token: str, run: Run) -> None:
    if not run.samples:
        return
    refs = await references(url, token, run)
    skip = cell_size(run.size)
    run.psnr = float(np.mean([psnr(rgb, ref, skip)
                              for (_, rgb), ref in zip(run.samples, refs, strict=True)]))
    run.jpeg_equal_bytes_per_frame = jpeg_bytes_at(refs, run.psnr, skip)


# -- the capped WebSocket: a TCP relay at 500 kbit/s ----------------------------------------


async def capped_relay(target_port: int, bitrate: float) -> tuple[asyncio.AbstractServer, int]:
    """A loopback TCP relay to `target_port` forwarding the server's bytes at `bitrate`
    bit/s (a token bucket; the client's bytes go through unthrottled)."""

    async def pipe(reader, writer, rate: float | None) -> None:
        sent_at, credit = time.monotonic(), 0.0
        try:
            while data := await reader.read(RELAY_CHUNK):
                if rate:
                    now = time.monotonic()
                    credit = min(credit + (now - sent_at) * rate / 8, RELAY_CHUNK)
                    sent_at = now
                    if credit < len(data):
                        await asyncio.sleep((len(data) - credit) * 8 / rate)
                        sent_at, credit = time.monotonic(), 0.0
                    else:
                        credit -= len(data)
                writer.write(data)
                await writer.drain()
        except (ConnectionError, asyncio.CancelledError):
            pass
        finally:
            writer.close()

    async def serve(client_reader, client_writer) -> None:
        server_reader, server_writer = await asyncio.open_connection("127.0.0.1", target_port)
        await asyncio.gather(pipe(client_reader, server_writer, None),
                             pipe(server_reader, client_writer, bitrate))

    relay = await asyncio.start_server(serve, "127.0.0.1", 0)
    return relay, relay.sockets[0].getsockname()[1]


# -- tables -------------------------------------------------------------------------------


def merge(runs: list[Run]) -> list[Run]:
    """One row per (transport, size): the repeats' frames, seconds, bytes, CPU and latencies
    summed, PSNR and equal-PSNR JPEG bytes averaged (each repeat scored its own samples)."""
    rows: dict[tuple[str, int], Run] = {}
    scores: dict[tuple[str, int], list[tuple[float, float]]] = {}
    for r in runs:
        row = rows.setdefault((r.transport, r.size), Run(r.transport, r.size, codec=r.codec))
        offset = row.seconds
        row.seconds += r.seconds
        row.frames += r.frames
        row.bytes += r.bytes
        row.cpu_s += r.cpu_s
        row.latencies += [(offset + t, ms) for t, ms in r.latencies]
        scores.setdefault((r.transport, r.size), []).append(
            (r.psnr, r.jpeg_equal_bytes_per_frame))
    for key, row in rows.items():
        values = np.array(scores[key])  # [repeats, 2]
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN: nothing was scored
            row.psnr, row.jpeg_equal_bytes_per_frame = (float(v) for v in
                                                        np.nanmean(values, axis=0))
    return list(rows.values())



def thirds(run: Run) -> tuple[float, float, float, float, float]:
    """fps and median latency in the first and last third, and the latency slope (ms/s)."""
    third = run.seconds / 3 if run.seconds else 1.0
    first = [ms for t, ms in run.latencies if t < third]
    last = [ms for t, ms in run.latencies if t >= 2 * third]
    if len(run.latencies) >= 2:
        t, ms = np.array(run.latencies).T
        slope = float(np.polyfit(t, ms, 1)[0])
    else:
        slope = float("nan")
    return (len(first) / third, len(last) / third, percentile(first, 50), percentile(last, 50),
            slope)


def print_tables(runs: list[Run], capped: list[Run], args, load: tuple) -> None:
    print(f"\nTransports on loopback, one viewer performing seat 0 of a room, {args.avatar} demo "
          f"avatar, drives at {args.rate:g} Hz, {args.seconds:g} s per row after {WARMUP_S:g} s "
          f"warm-up; {os.cpu_count()} CPUs ({platform.processor() or platform.machine()}), "
          f"load average {load[0]:.1f} at the end; run under nice on a shared machine.\n")
    print("| transport | size | fps | server CPU / frame (ms) | kB/s | PSNR (dB) "
          "| JPEG at that PSNR (kB/s) | latency p50 (ms) | p95 (ms) |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in runs:
        jpeg = r.jpeg_equal_bytes_per_frame * r.fps / 1000
        cpu = 1000 * r.cpu_s / r.frames if r.frames else float("nan")
        print(f"| {r.transport} ({r.codec}) | {r.size} | {r.fps:.1f} | {cpu:.1f} "
              f"| {r.bytes / max(r.seconds, 1e-9) / 1000:.0f} | {r.psnr:.1f} | {jpeg:.0f} "
              f"| {r.latency(50):.0f} | {r.latency(95):.0f} |")
    if not capped:
        print()
    else:
        print_capped(capped, args)
    verdicts(runs, capped)


def print_capped(capped: list[Run], args) -> None:
    print(f"\nUnder a {CAP_BITRATE // 1000} kbit/s cap, {args.cap_size}x{args.cap_size}, "
          f"{args.cap_seconds:g} s (WebRTC: encoder capped; WebSocket: relayed at that rate).\n")
    print("| transport | kB/s | fps first third | fps last third | latency p50 first (ms) "
          "| latency p50 last (ms) | latency trend (ms/s) |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for r in capped:
        f1, f3, l1, l3, slope = thirds(r)
        print(f"| {r.transport} ({r.codec}) | {r.bytes / max(r.seconds, 1e-9) / 1000:.0f} "
              f"| {f1:.1f} | {f3:.1f} | {l1:.0f} | {l3:.0f} | {slope:+.1f} |")
    print()


def verdicts(runs: list[Run], capped: list[Run]) -> None:
    for r in runs:
        if r.transport.startswith("webrtc") and r.size == min(run.size for run in runs):
            ok = r.fps >= 25 and r.latency(95) <= 100
            print(f"{r.transport} at {r.size}: {r.fps:.1f} fps, p95 {r.latency(95):.0f} ms "
                  f"({'meets' if ok else 'misses'} >= 25 fps, p95 <= 100 ms)")
    for r in capped:
        if r.transport.startswith("webrtc"):
            f1, f3, l1, l3, slope = thirds(r)
            ok = f3 >= 15 and not slope > GROWING_MS_PER_S
            print(f"{r.transport} capped: {f3:.1f} fps in the last third, latency p50 "
                  f"{l1:.0f} -> {l3:.0f} ms, trend {slope:+.1f} ms/s ({'meets' if ok else 'misses'}"
                  f" >= 15 fps with no growing delay, i.e. a trend <= {GROWING_MS_PER_S:g} ms/s)")


# -- main ---------------------------------------------------------------------------------


async def measure(url: str, token: str, pid: int, transport: str, size: int, args,
                  stream_url: str | None = None, seconds: float | None = None,
                  scored: bool = True) -> Run:
    run = Run(transport, size)
    kind, codec = transport.split("-")
    seconds = seconds or args.seconds
    if kind == "ws":
        await run_websocket(url, token, codec, run, pid, seconds, args.rate, args.samples,
                            stream_url)
    else:
        await run_webrtc(url, token, codec, run, pid, seconds, args.rate, args.samples,
                         marker=not args.aiortc_jitter_buffer)
    if scored:
        await score(url, token, run)
    print(f"{transport} {size}: {run.fps:.1f} fps, p95 {run.latency(95):.0f} ms, "
          f"PSNR {run.psnr:.1f} dB", file=sys.stderr, flush=True)
    return run


async def capped_websockets(url: str, token: str, pid: int, args,
                            transports: list[str]) -> list[Run]:
    port = int(url.rsplit(":", 1)[1])
    relay, relay_port = await capped_relay(port, CAP_BITRATE)
    try:
        return [await measure(url, token, pid, t, args.cap_size, args,
                              stream_url=f"http://127.0.0.1:{relay_port}",
                              seconds=args.cap_seconds, scored=False)
                for t in transports if t.startswith("ws")]
    finally:
        relay.close()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="512,1024")
    parser.add_argument("--transports", default=",".join(TRANSPORTS))
    parser.add_argument("--seconds", type=float, default=10.0, help="measured per row")
    parser.add_argument("--rate", type=float, default=30.0, help="drives (and fps asked) per s")
    parser.add_argument("--samples", type=int, default=20, help="frames scored for PSNR per row")
    parser.add_argument("--cap-seconds", type=float, default=20.0)
    parser.add_argument("--cap-size", type=int, default=512)
    parser.add_argument("--repeat", type=int, default=1,
                        help="rounds over the transports, in alternating order; rows merge them")
    parser.add_argument("--aiortc-jitter-buffer", action="store_true",
                        help="keep aiortc's stock receiver, which holds each frame until the "
                             "next one starts (adds one frame interval to WebRTC latency)")
    parser.add_argument("--render-threads", type=int, default=1)
    parser.add_argument("--avatar", default="trained",
                        help="the server's demo avatar: trained (cached), synthetic or a path")
    args = parser.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    transports = [t for t in args.transports.split(",") if t]
    unknown = set(transports) - set(TRANSPORTS)
    if unknown:
        parser.error(f"unknown transports {sorted(unknown)}; choose from {TRANSPORTS}")

    runs: list[Run] = []
    capped: list[Run] = []
    with tempfile.TemporaryDirectory(prefix="telesplat-bench-") as tmp:
        for name in ("a", "b"):
            (Path(tmp) / name).mkdir()
        proc, url, token = start_server(Path(tmp) / "a", args.render_threads, 8, args.avatar)
        try:
            for i in range(args.repeat):  # alternating order: load drift shows as spread
                for size in sizes:
                    for transport in (transports if i % 2 == 0 else transports[::-1]):
                        runs.append(asyncio.run(measure(url, token, proc.pid, transport, size,
                                                        args)))
            if args.cap_seconds > 0:
                capped += asyncio.run(capped_websockets(url, token, proc.pid, args, transports))
        finally:
            stop_server(proc)
        if args.cap_seconds > 0 and any(t.startswith("webrtc") for t in transports):
            os.environ["TELESPLAT_WEBRTC_MAX_BITRATE"] = str(CAP_BITRATE)
            proc, url, token = start_server(Path(tmp) / "b", args.render_threads, 8,
                                            args.avatar)
            try:
                for transport in transports:
                    if transport.startswith("webrtc"):
                        capped.append(asyncio.run(measure(
                            url, token, proc.pid, transport, args.cap_size, args,
                            seconds=args.cap_seconds, scored=False)))
            finally:
                stop_server(proc)
    load = os.getloadavg() if hasattr(os, "getloadavg") else ("?",) * 3
    print_tables(merge(runs), capped, args, load)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
