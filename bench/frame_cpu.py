"""Where the server's CPU per frame goes: sessions at distinct views, every thread accounted.

Starts its own server (bench/stream.py's ``start_server``), warms it with one session, then
runs ``--sessions`` plain sessions at distinct views in lockstep (bench/stream.py's
``run_config``) and, over the measured window:

* reads every server thread's CPU time (utime+stime of /proc/PID/task/TID/stat), and
* samples the Python stacks of every thread with py-spy (``--nonblocking``: the server is
  never paused) to split each thread's CPU into the stages its stacks are in.

A thread with CPU time but no Python stack is a native pool's (OpenMP / numba workers that
the rasterizer and torch spread a frame over). Each Python thread's CPU is split over its
stages in proportion to its samples (py-spy records only samples where the thread runs).

    .venv/bin/python bench/frame_cpu.py [--sessions 4] [--seconds 10] [--size 512]
                                        [--render-threads auto|N] [--rate 200]
                                        [--samples FILE]

py-spy: ``.venv/bin/pip install py-spy``. Prints one Markdown table: ms of server CPU per
delivered frame, by thread and stage.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from stream import WARMUP_S, run_config, start_server, stop_server  # noqa: E402

# A sample belongs to the first stage (in this order) whose marker is in its stack.
STAGES: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("pose", ("SeatPoser.world", "DeviceCopies.get", "union (avatar_core/gaussians")),
    ("render", ("render_views (",)),
    ("rgb to uint8", ("frame_rgb (", "to_uint8 (")),
    ("encode", ("FrameEncoders.encode", "encoders/")),
    ("frame bookkeeping", ("SceneFrames.make", "RenderScheduler._worker", "Scene.submit")),
    ("drive: decode + validate", ("InboundDecoder", "fit_drive", "DriveState.apply",
                                   "protocol/codec", "pydantic")),
    ("frame send (msgpack + websocket)", ("deliver", "websockets/", "uvicorn/protocols",
                                          "Session._send_frame", "_control_sender")),
    ("session loops", ("server/stream/session.py",)),
    ("asyncio / other", ("",)),
)


def thread_cpu(pid: int) -> dict[int, float]:
    """CPU seconds (utime+stime) of each thread of ``pid``."""
    out = {}
    tick = os.sysconf("SC_CLK_TCK")
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue  # the thread ended
        out[int(task.name)] = (int(fields[11]) + int(fields[12])) / tick
    return out


def stage_of(stack: str) -> str:
    return next(name for name, marks in STAGES if any(m in stack for m in marks))


def read_samples(path: Path) -> tuple[dict[int, str], dict[int, collections.Counter]]:
    """py-spy raw output: (thread id -> name, thread id -> samples per stage)."""
    names: dict[int, str] = {}
    stages: dict[int, collections.Counter] = collections.defaultdict(collections.Counter)
    for line in path.read_text().splitlines():
        found = re.match(r"thread \((?:0x)?(\w+)\): ([^;]*);(.*) (\d+)$", line)
        if not found:
            continue
        tid_text, name, stack, count = found.groups()
        tid = int(tid_text, 16) if line.startswith("thread (0x") else int(tid_text)
        names[tid] = name
        stages[tid][stage_of(stack)] += int(count)
    return names, stages


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sessions", type=int, default=4)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--render-threads", default="auto",
                        help="the server's render threads; auto: its own choice")
    parser.add_argument("--rate", type=int, default=200, help="py-spy samples per second")
    parser.add_argument("--avatar", default="synthetic")
    parser.add_argument("--samples", type=Path, default=None,
                        help="keep py-spy's raw stacks here (to read the top functions)")
    args = parser.parse_args()
    spy = shutil.which("py-spy") or str(Path(sys.executable).parent / "py-spy")
    if not Path(spy).exists():
        parser.error("py-spy is not installed (.venv/bin/pip install py-spy)")

    with tempfile.TemporaryDirectory(prefix="telesplat-bench-") as tmp:
        threads = None if args.render_threads == "auto" else int(args.render_threads)
        proc, url, token = start_server(Path(tmp), threads, args.sessions, args.avatar)
        try:
            asyncio.run(run_config(url, token, 1, args.size, 2.0, "lockstep", 30.0))  # warm
            raw = Path(tmp) / "spy.txt"

            async def measured() -> tuple[list, dict, dict]:
                run = asyncio.create_task(run_config(url, token, args.sessions, args.size,
                                                     args.seconds, "lockstep", 30.0))
                await asyncio.sleep(0.5 + WARMUP_S)  # run_config's connect wait + warm-up
                before = thread_cpu(proc.pid)
                sampler = subprocess.Popen(
                    [spy, "record", "--pid", str(proc.pid), "--threads", "--nonblocking",
                     "-r", str(args.rate), "-d", str(int(args.seconds)), "-f", "raw",
                     "-o", str(raw)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                await asyncio.sleep(args.seconds)
                after = thread_cpu(proc.pid)
                results = await run
                await asyncio.to_thread(sampler.wait, 60)
                return results, before, after

            results, before, after = asyncio.run(measured())
        finally:
            stop_server(proc)
        names, stages = read_samples(raw)
        if args.samples is not None:
            shutil.copyfile(raw, args.samples)

    frames = sum(r.frames for r in results)
    fps = frames / args.seconds / args.sessions
    used = {tid: after[tid] - before.get(tid, 0.0) for tid in after}
    per_frame = {tid: 1000 * s / frames for tid, s in used.items() if s > 0}
    total = sum(per_frame.values())
    rows: dict[tuple[str, str], float] = collections.defaultdict(float)
    for tid, ms in per_frame.items():
        if tid not in stages:
            rows[("native pool threads", "(OpenMP / numba workers)")] += ms
            continue
        name = "main (event loop)" if names[tid] == "MainThread" else \
            "render" if names[tid].startswith("render_") else names[tid]
        n = sum(stages[tid].values())
        for stage, count in stages[tid].items():
            rows[(name, stage)] += ms * count / n

    load = os.getloadavg()
    print(f"\nServer CPU per delivered frame: {args.sessions} sessions at distinct views, "
          f"{args.size}x{args.size} JPEG, lockstep, {args.seconds:g} s, render threads "
          f"{args.render_threads}; {fps:.1f} fps per session, {frames} frames; "
          f"{os.cpu_count()} CPUs ({platform.processor() or platform.machine()}), load average "
          f"{load[0]:.1f} at the end.\n")
    print("| thread | stage | CPU per frame (ms) | share |")
    print("|---|---|---:|---:|")
    for (thread, stage), ms in sorted(rows.items(), key=lambda kv: -kv[1]):
        print(f"| {thread} | {stage} | {ms:.1f} | {100 * ms / total:.0f}% |")
    print(f"| **all** | | **{total:.1f}** | |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
