"""What an enrollment video costs before the pipeline: the probe (run inside the upload
request, before the job exists) against the decode (the job's first stage), side by side on
the same files. Videos are written by PyAV here: the page's WebM (VP8, 640 x 480) and a
phone-like H.264 MP4 (1280 x 720), both 30 fps.

    .venv/bin/python bench/enroll_video.py --seconds 10 30 --repeat 3
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from avatar_core.enroll.video import VideoLimits, probe_video, read_video  # noqa: E402
from tests.enroll_videos import write_video  # noqa: E402

FORMATS = {"webm 640x480 (page)": (".webm", 640, 480), "mp4 1280x720 (phone)": (".mp4", 1280, 720)}


def timed(fn, repeat: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seconds", type=float, nargs="+", default=[10.0, 30.0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--long-side", type=int, default=512)
    args = parser.parse_args()
    limits = VideoLimits()
    print("| video | s | MB | probe ms | decode ms | decode / probe | frames kept | "
          "decode x realtime |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    with tempfile.TemporaryDirectory() as tmp:
        for name, (suffix, width, height) in FORMATS.items():
            for seconds in args.seconds:
                path = write_video(Path(tmp) / f"v{seconds:g}{suffix}", seconds=seconds,
                                   fps=30, width=width, height=height)
                probe_s, _ = timed(lambda p=path: probe_video(p, limits), args.repeat)
                decode_s, video = timed(
                    lambda p=path: read_video(p, limits, long_side=args.long_side), args.repeat)
                print(f"| {name} | {seconds:g} | {path.stat().st_size / 1e6:.1f} | "
                      f"{probe_s * 1e3:.0f} | {decode_s * 1e3:.0f} | "
                      f"{decode_s / probe_s:.1f} | {len(video.frames)} | "
                      f"{seconds / decode_s:.1f} |", flush=True)


if __name__ == "__main__":
    main()
