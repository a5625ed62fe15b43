"""Streaming end to end on loopback: 1, 2, 4 and 8 concurrent sessions at 512x512.

Starts its own server (``python -m server``, a subprocess on a free port, the demo avatar
of ``--avatar``, fresh data dir) and connects the sessions with ``client.StreamClient``. Each
session drives a procedural talking-and-gesturing motion (jaw, expression, head, arms,
fingers: every stage of the pipeline recomputes each frame) and measures, per frame, the
time from sending the drive to receiving the frame that reflects it.

Modes: ``lockstep`` (default): each session sends its next drive as soon as the frame for the
previous one came back, so fps is what the server sustains and latency is the pipeline time
with no client-side queueing. ``paced``: each session drives at ``--rate`` Hz whatever comes
back (the server coalesces drives it cannot keep up with); latency is then measured from the
newest drive a frame reflects.

    .venv/bin/python bench/stream.py [--sessions 1,2,4,8] [--seconds 8] [--size 512]
                                     [--mode lockstep|paced] [--rate 30] [--render-threads 1]
                                     [--avatar synthetic|trained|PACKAGE]

Prints a Markdown table: per-session fps (mean over sessions), the min/max fps ratio across
sessions (fairness), latency p50/p95 over all frames, and the server's median render time.
Targets (2 cores): one session p95 <= 50 ms and >= 30 fps; min/max fps ratio >= 0.8.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import math
import os
import platform
import re
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from client import StreamClient  # noqa: E402

START_TIMEOUT_S = 300.0  # first start compiles the numba kernels
WARMUP_S = 1.0


# -- the motion ----------------------------------------------------------------------------


def motion_frame(t: float, phase: float) -> dict[str, np.ndarray]:
    """Talking with the hands: every field changes every frame (nothing is cached)."""
    s = math.sin
    body = np.zeros((21, 3), np.float32)
    body[11] = (0.1 * s(1.3 * t + phase), 0.15 * s(0.7 * t), 0.0)  # neck
    body[14] = (0.15 * s(1.1 * t), 0.2 * s(0.9 * t + phase), 0.05 * s(2 * t))  # head
    body[15] = (0.0, 0.0, -1.1 + 0.3 * s(1.7 * t))   # left shoulder
    body[16] = (0.0, 0.0, 1.1 - 0.3 * s(1.9 * t + phase))  # right shoulder
    body[17] = (0.0, -0.6 - 0.4 * s(2.1 * t), 0.0)   # left elbow
    body[18] = (0.0, 0.6 + 0.4 * s(2.3 * t), 0.0)   # right elbow
    curl = 0.6 + 0.5 * s(3 * t + phase)
    hand = np.zeros((15, 3), np.float32)
    hand[:12, 2] = curl
    return {
        "body_pose": body,
        "jaw_pose": np.array([0.12 + 0.12 * s(9 * t + phase), 0, 0], np.float32),
        "expression": (0.6 * np.sin(np.arange(10) + 2 * t + phase)).astype(np.float32),
        "left_hand_pose": hand * np.array([1, -1, -1], np.float32),
        "right_hand_pose": hand,
    }


# -- one session ---------------------------------------------------------------------------


@dataclass
class SessionResult:
    frames: int = 0
    latencies_ms: list[float] = field(default_factory=list)
    seconds: float = 0.0
    render_ms: float | None = None

    @property
    def fps(self) -> float:
        return self.frames / self.seconds if self.seconds else 0.0


async def paced(rate: float, end: float, sent: dict[int, float],
                send: Callable[[int], Awaitable[int]]) -> None:
    """`send(i)` (returning the message's seq) at `rate` Hz until the monotonic deadline
    `end`; `sent[seq]` is when each was sent."""
    t0, i = time.monotonic(), 0
    while time.monotonic() < end:
        delay = t0 + i / rate - time.monotonic()
        if delay > 0:
            await asyncio.sleep(delay)
        now = time.monotonic()
        sent[await send(i)] = now
        i += 1


async def frames_until(client: StreamClient, end: float) -> AsyncIterator:
    """The frames as they arrive, until the monotonic deadline `end`."""
    while time.monotonic() < end:
        try:
            yield await client.next_frame(timeout=max(0.01, end - time.monotonic()))
        except TimeoutError:
            return


async def run_session(url: str, token: str, index: int, size: int, seconds: float,
                      mode: str, rate: float, start: asyncio.Event) -> SessionResult:
    result = SessionResult()
    async with await StreamClient.connect(url, "demo", token, timeout=60,
                                          client_name=f"bench-{index}") as client:
        await client.request(width=size, height=size, max_fps=client.limits.max_fps,
                             codec="jpeg")
        await client.view({"yaw_deg": 15.0 * index, "distance": 2.4})
        await start.wait()  # all sessions connected: measure them together
        phase = 0.7 * index
        t0 = time.monotonic()
        measure_from = t0 + WARMUP_S
        end = measure_from + seconds
        sent: dict[int, float] = {}
        if mode == "lockstep":
            while time.monotonic() < end:  # bounded by the deadline
                now = time.monotonic()
                seq = await client.drive(motion_frame(now - t0, phase))
                sent[seq] = now
                frame = await client.wait_frame(seq, timeout=30)
                got = time.monotonic()
                if got >= measure_from:
                    result.frames += 1
                    result.latencies_ms.append(1000 * (got - sent[frame.seq]))
        else:
            driver = asyncio.create_task(paced(
                rate, end, sent,
                lambda _: client.drive(motion_frame(time.monotonic() - t0, phase))))
            try:
                async for frame in frames_until(client, end):
                    got = time.monotonic()
                    if got >= measure_from and frame.seq in sent:
                        result.frames += 1
                        result.latencies_ms.append(1000 * (got - sent[frame.seq]))
            finally:
                driver.cancel()
        result.seconds = seconds
        if client.stats is not None:
            result.render_ms = client.stats.render_ms
    return result


async def run_config(url: str, token: str, sessions: int, size: int, seconds: float,
                     mode: str, rate: float) -> list[SessionResult]:
    start = asyncio.Event()
    tasks = [asyncio.create_task(run_session(url, token, i, size, seconds, mode, rate, start))
             for i in range(sessions)]
    await asyncio.sleep(0.5)  # let every session connect and get its welcome
    start.set()
    return await asyncio.gather(*tasks)


# -- the server ----------------------------------------------------------------------------


def start_server(data_dir: Path, render_threads: int | None, max_sessions: int, avatar: str):
    """``render_threads`` None: the server's own choice (its default)."""
    # A bench's crowd of viewers joins with one watch invitation: it may take every session.
    env = {k: v for k, v in os.environ.items() if k != "TELESPLAT_RENDER_THREADS"}
    if render_threads is not None:
        env["TELESPLAT_RENDER_THREADS"] = str(render_threads)
    env = {**env, "TELESPLAT_MAX_SESSIONS": str(max_sessions),
           "TELESPLAT_MAX_SESSIONS_PER_INVITATION": str(max_sessions),
           "TELESPLAT_RESERVED_SESSIONS": "0", "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "server", "--port", "0", "--data-dir", str(data_dir),
         "--demo-avatar", avatar, "--log-level", "warning"],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.monotonic() + START_TIMEOUT_S
    lines = []
    while time.monotonic() < deadline:  # readline blocks until the server prints
        line = proc.stdout.readline()
        if not line:
            break
        lines.append(line)
        found = re.search(r"serving at (http://[^/\s]+)/[?#]token=(\S+)", line)
        if found:
            # Keep reading what the server prints, or a long run fills the pipe and blocks it.
            # The last lines stay readable (``proc.tail``): a bench may report the server's
            # warnings, such as the event loop's stall stacks (loop_stall_log_ms).
            proc.tail = collections.deque(maxlen=400)
            threading.Thread(target=proc.tail.extend, args=(proc.stdout,),
                             daemon=True).start()
            return proc, found.group(1), found.group(2)
    proc.kill()
    raise RuntimeError("the server did not start:\n" + "".join(lines[-30:]))


def stop_server(proc: subprocess.Popen) -> None:
    proc.terminate()
    try:
        proc.wait(15)
    except subprocess.TimeoutExpired:
        proc.kill()


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) if values else float("nan")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sessions", default="1,2,4,8")
    parser.add_argument("--seconds", type=float, default=8.0, help="measured per config")
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--mode", choices=("lockstep", "paced"), default="lockstep")
    parser.add_argument("--rate", type=float, default=30.0, help="drives per second (paced)")
    parser.add_argument("--render-threads", type=int, default=1)
    parser.add_argument("--avatar", default="synthetic",
                        help="the server's demo avatar: synthetic (untrained, 16k Gaussians), "
                             "trained (make run's, built first if missing) or a package path")
    args = parser.parse_args()
    counts = [int(n) for n in args.sessions.split(",")]

    with tempfile.TemporaryDirectory(prefix="telesplat-bench-") as tmp:
        proc, url, token = start_server(Path(tmp), args.render_threads, max(counts),
                                        args.avatar)
        try:
            rows = []
            for n in counts:
                results = asyncio.run(run_config(url, token, n, args.size, args.seconds,
                                                 args.mode, args.rate))
                fps = [r.fps for r in results]
                lat = [x for r in results for x in r.latencies_ms]
                render = [r.render_ms for r in results if r.render_ms is not None]
                rows.append((n, float(np.mean(fps)), min(fps) / max(fps) if max(fps) else 0.0,
                             percentile(lat, 50), percentile(lat, 95), sum(r.frames for r in
                                                                            results),
                             float(np.median(render)) if render else float("nan")))
                print(f"{n} session(s): {rows[-1][1]:.1f} fps each, p95 {rows[-1][4]:.0f} ms",
                      file=sys.stderr, flush=True)
        finally:
            stop_server(proc)

    load = os.getloadavg() if hasattr(os, "getloadavg") else ("?",) * 3
    print(f"\nStreaming on loopback, {args.size}x{args.size} JPEG, {args.avatar} demo avatar, "
          f"mode {args.mode}" + (f" at {args.rate:g} Hz" if args.mode == "paced" else "")
          + f", {args.seconds:g} s per row, render threads {args.render_threads}; "
          f"{os.cpu_count()} CPUs ({platform.processor() or platform.machine()}), "
          f"load average {load[0]:.1f} at the end.\n")
    print("| sessions | fps / session | min/max fps | latency p50 (ms) | latency p95 (ms) "
          "| frames | server render (ms) |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    for n, fps, ratio, p50, p95, frames, render in rows:
        print(f"| {n} | {fps:.1f} | {ratio:.2f} | {p50:.0f} | {p95:.0f} | {frames} "
              f"| {render:.1f} |")
    one = next((r for r in rows if r[0] == 1), None)
    if one:
        ok = one[4] <= 50 and one[1] >= 30
        print(f"\none session: p95 {one[4]:.0f} ms, {one[1]:.1f} fps "
              f"({'meets' if ok else 'misses'} the target p95 <= 50 ms and >= 30 fps)")
    worst = min(r[2] for r in rows)
    print(f"worst min/max fps ratio {worst:.2f} "
          f"({'meets' if worst >= 0.8 else 'misses'} the target >= 0.8)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
