"""The browser's webcam path end to end: JPEG frames in, server-side tracking, frames out.

    OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python bench/stream_webcam.py [--seconds 10]
        [--rate 30] [--size 512] [--avatar synthetic|trained|PACKAGE] [--frames 90]

Starts its own server (as `bench/stream.py` does: a subprocess on a free port, the demo
avatar, a fresh data dir). One session streams at `--size` while it sends `image` messages at
`--rate` Hz, as the browser page's webcam toggle does: renders of the synthetic actor
talking with its hands (`synth.tracking_eval`'s scene, 640x480, JPEG quality 85), looped.
The server tracks the newest image (latest wins), fits it and drives the avatar.

Reported: frames received per second; tracked updates per second (frames whose
`timings.track` is set: each tracked image shows in one frame); images superseded before
tracking; the server's tracking time (decode + landmarks + fit, median); and the latency from
sending an image to the frame that shows it (p50 / p95).
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
for path in (ROOT, ROOT / "bench"):
    if str(path) not in sys.path:
        sys.path.insert(0, str(path))

from stream import frames_until, paced, percentile, start_server, stop_server  # noqa: E402

from client import StreamClient  # noqa: E402


def webcam_jpegs(frames: int) -> list[bytes]:
    """Rendered webcam frames of talk_animated (hands rising into view), JPEG-encoded."""
    from avatar_core.synth import tracking_eval as te

    scene = te.make_scene()
    rng = np.random.default_rng(0)
    out = []
    for params in te.clip_params(scene, "talk_animated", 30.0, 1.0, frames):
        bgr = te.render_frame(scene.actor, params, scene.camera, scene.bg, 2 / 255, rng)
        ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 85])
        assert ok
        out.append(buf.tobytes())
    return out


async def run(url: str, token: str, jpegs: list[bytes], seconds: float, rate: float,
              size: int) -> dict[str, float]:
    async with await StreamClient.connect(url, "demo", token, timeout=60,
                                          client_name="bench-webcam") as client:
        await client.request(width=size, height=size, max_fps=client.limits.max_fps,
                             codec="jpeg")
        sent: dict[int, float] = {}
        end = time.monotonic() + seconds
        frames, tracked, track_ms, latency_ms = 0, 0, [], []
        sender = asyncio.create_task(
            paced(rate, end, sent, lambda i: client.image(jpegs[i % len(jpegs)])))
        start = time.monotonic()
        try:
            async for frame in frames_until(client, end):
                frames += 1
                if frame.timings.track > 0:
                    tracked += 1
                    track_ms.append(frame.timings.track)
                    if frame.seq in sent:
                        latency_ms.append(1000 * (time.monotonic() - sent[frame.seq]))
        finally:
            sender.cancel()
        elapsed = time.monotonic() - start
        return {"fps": frames / elapsed, "tracked_per_s": tracked / elapsed,
                "images": len(sent), "superseded": len(sent) - tracked,
                "track_ms": float(np.median(track_ms)) if track_ms else float("nan"),
                "latency_p50": percentile(latency_ms, 50),
                "latency_p95": percentile(latency_ms, 95)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--rate", type=float, default=30.0, help="images per second")
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--frames", type=int, default=90, help="distinct webcam frames, looped")
    ap.add_argument("--render-threads", type=int, default=2)
    ap.add_argument("--avatar", default="synthetic")
    args = ap.parse_args()
    jpegs = webcam_jpegs(args.frames)
    with tempfile.TemporaryDirectory(prefix="telesplat-bench-") as tmp:
        proc, url, token = start_server(Path(tmp), args.render_threads, 1, args.avatar)
        try:
            # A first image loads the landmark models and makes the cold fit.
            asyncio.run(run(url, token, jpegs[:1], 3.0, 2.0, args.size))
            r = asyncio.run(run(url, token, jpegs, args.seconds, args.rate, args.size))
        finally:
            stop_server(proc)
    print(f"load {os.getloadavg()[0]:.2f}; {args.rate:g} images/s of 640x480 JPEG, "
          f"{args.size}x{args.size} frames, {args.render_threads} render threads, "
          f"avatar {args.avatar}")
    print("| frames / s | tracked updates / s | images superseded | server track ms "
          "(median) | image -> frame p50 / p95 ms |")
    print("|---:|---:|---:|---:|---:|")
    print(f"| {r['fps']:.1f} | {r['tracked_per_s']:.1f} | {r['superseded']} of "
          f"{r['images']} | {r['track_ms']:.1f} | {r['latency_p50']:.0f} / "
          f"{r['latency_p95']:.0f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
