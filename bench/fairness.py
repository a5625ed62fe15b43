"""Fair share of render time: a cheap session's fps alone and beside an expensive one.

For each fair-share policy (``frames``: first come first served, the old behaviour; ``time``:
cost-aware, the default) it starts its own server (``python -m server``, a subprocess on a
free port, the demo avatar of ``--avatar``), then measures on loopback

1. the cheap session alone: ``--cheap-size`` px JPEG, drives at 30 Hz, max_fps 30;
2. the cheap session beside an expensive one: ``--big-width`` x ``--big-height`` PNG with
   alpha and depth, also driven at 30 Hz.

Both sessions drive the talking-and-gesturing motion of ``bench/stream.py`` (every frame
re-poses). Prints a Markdown table, one row per policy: the cheap session's fps alone and
shared, the expensive session's fps, and the expensive session's share of the render time
(from the frames' own timings).

    .venv/bin/python bench/fairness.py [--seconds 8] [--cheap-size 512]
                                       [--big-width 1920] [--big-height 1080]
                                       [--policies frames,time] [--avatar synthetic]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from stream import frames_until, motion_frame, paced, start_server, stop_server  # noqa: E402

from client import StreamClient  # noqa: E402

DRIVE_HZ = 30.0
WARMUP_S = 1.5


@dataclass
class Measured:
    frames: int = 0
    seconds: float = 0.0
    busy_ms: float = 0.0  # pose + render + encode of the measured frames

    @property
    def fps(self) -> float:
        return self.frames / self.seconds if self.seconds else 0.0


async def run_session(client: StreamClient, seconds: float, phase: float) -> Measured:
    """Drive at 30 Hz for WARMUP_S + seconds; count the frames of the last `seconds`."""
    out = Measured(seconds=seconds)
    t0 = time.monotonic()
    measure_from, end = t0 + WARMUP_S, t0 + WARMUP_S + seconds
    driver = asyncio.create_task(paced(
        DRIVE_HZ, end, {}, lambda _: client.drive(motion_frame(time.monotonic() - t0, phase))))
    try:
        async for frame in frames_until(client, end):
            if time.monotonic() >= measure_from:
                out.frames += 1
                t = frame.timings
                out.busy_ms += t.pose + t.render + t.encode
    finally:
        driver.cancel()
    return out


async def measure(url: str, token: str, args) -> tuple[Measured, Measured, Measured]:
    async with await StreamClient.connect(url, "demo", token, timeout=60,
                                          client_name="cheap") as cheap:
        await cheap.request(width=args.cheap_size, height=args.cheap_size, codec="jpeg",
                            max_fps=30)
        alone = await run_session(cheap, args.seconds, 0.0)
        async with await StreamClient.connect(url, "demo", token, timeout=60,
                                              client_name="expensive") as big:
            await big.request(width=args.big_width, height=args.big_height, codec="png",
                              outputs=["rgb", "alpha", "depth"], max_fps=30)
            shared, expensive = await asyncio.gather(run_session(cheap, args.seconds, 0.0),
                                                     run_session(big, args.seconds, 1.0))
    return alone, shared, expensive


def run_policy(policy: str, args) -> tuple[Measured, Measured, Measured]:
    os.environ["TELESPLAT_FAIR_SHARE"] = policy
    os.environ["TELESPLAT_LIMITS"] = json.dumps({"max_width": max(args.big_width, 1920),
                                                 "max_height": max(args.big_height, 1080)})
    with tempfile.TemporaryDirectory() as tmp:
        proc, url, token = start_server(Path(tmp), 1, 4, args.avatar)
        try:
            return asyncio.run(measure(url, token, args))
        finally:
            stop_server(proc)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=8.0, help="measured per phase")
    parser.add_argument("--cheap-size", type=int, default=512)
    parser.add_argument("--big-width", type=int, default=1920)
    parser.add_argument("--big-height", type=int, default=1080)
    parser.add_argument("--policies", default="frames,time")
    parser.add_argument("--avatar", default="synthetic")
    args = parser.parse_args()
    rows = []
    for policy in args.policies.split(","):
        alone, shared, expensive = run_policy(policy, args)
        window_ms = 1000 * args.seconds
        rows.append(f"| {policy} | {alone.fps:.1f} | {shared.fps:.1f} | {expensive.fps:.2f} | "
                    f"{100 * expensive.busy_ms / max(window_ms, 1e-9):.0f}% | "
                    f"{100 * shared.busy_ms / max(window_ms, 1e-9):.0f}% |")
    print(f"\n{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"avatar {args.avatar}, 1 render thread; cheap {args.cheap_size}px JPEG, expensive "
          f"{args.big_width}x{args.big_height} PNG + alpha + depth, both driven at "
          f"{DRIVE_HZ:g} Hz, {args.seconds:g} s measured\n")
    print("| fair_share | cheap fps alone | cheap fps shared | expensive fps | "
          "expensive render time | cheap render time |")
    print("|---|---|---|---|---|---|")
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
