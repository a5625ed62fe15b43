"""Tracking speed: per-stage ms and FPS of face + hands + body at 640x480 (CPU).

    python bench/track.py [--frames 60] [--only iris]

The frame is scikit-image's astronaut photo (512x512) resized to 480 high and padded to
640x480. Timings are in tracking mode: the first frames (detectors, warm-up) are dropped, so
the face and body detectors no longer run; the palm detector runs every frame while fewer
than two hands are tracked (MediaPipe's rule; the photo has no bare hand) unless
palm_interval says otherwise. Stage times are medians; FPS is frames / wall time. The "+ iris"
rows add the eyes (two iris_landmark runs after the face mesh, `Tracker(iris=True)`).
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import cv2
import numpy as np


def astronaut_640x480() -> np.ndarray:
    from skimage import data

    img = cv2.cvtColor(cv2.resize(data.astronaut(), (480, 480), interpolation=cv2.INTER_AREA),
                       cv2.COLOR_RGB2BGR)
    frame = np.zeros((480, 640, 3), np.uint8)
    frame[:, 80:560] = img
    return frame


def run(frame: np.ndarray, frames: int, **kwargs) -> dict[str, float]:
    from avatar_core.track.tracker import Tracker

    tracker = Tracker(**kwargs)
    for _ in range(3):
        tracker.track(frame)
    stages: dict[str, list[float]] = {}
    start = time.perf_counter()
    for _ in range(frames):
        result = tracker.track(frame)
        for k, v in result.timings_ms.items():
            stages.setdefault(k, []).append(v)
    wall = time.perf_counter() - start
    tracker.close()
    out = {k: statistics.median(v) for k, v in stages.items()}
    out["fps"] = frames / wall
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--only", default="", help="run the configurations whose name has this")
    args = parser.parse_args()
    frame = astronaut_640x480()
    configs = [
        ("1 thread", dict(threads=1)),
        ("2 threads", dict(threads=2)),
        ("stages at once, 1 thread each", dict(threads=1, parallel=True)),
        ("1 thread, palm every 5th frame", dict(threads=1, palm_interval=5)),
        ("2 threads, palm every 5th frame", dict(threads=2, palm_interval=5)),
        ("stages at once, palm every 5th", dict(threads=1, parallel=True, palm_interval=5)),
        ("stages at once, palm every 5th, lite hands", dict(threads=1, parallel=True,
                                                           palm_interval=5,
                                                           hand_model="lite")),
        ("1 thread + iris", dict(threads=1, iris=True)),
        ("1 thread, palm every 5th frame + iris", dict(threads=1, palm_interval=5, iris=True)),
        ("stages at once, palm every 5th + iris", dict(threads=1, parallel=True,
                                                      palm_interval=5, iris=True)),
    ]
    configs = [(name, kwargs) for name, kwargs in configs if args.only in name]
    print(f"load average before: {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} "
          f"{os.getloadavg()[2]:.2f}; cpus: {os.cpu_count()}")
    print("| configuration | face ms | iris ms | hands ms | pose ms | total ms | FPS |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for name, kwargs in configs:
        r = run(frame, args.frames, **kwargs)
        iris = f"{r['iris']:.1f}" if "iris" in r else "-"
        print(f"| {name} | {r['face']:.1f} | {iris} | {r['hands']:.1f} | {r['pose']:.1f} | "
              f"{r['total']:.1f} | {r['fps']:.1f} |", flush=True)
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
