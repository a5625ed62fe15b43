"""Webcam driving end to end: frames -> landmarks -> fitted SMPL-X, serial against pipelined.

    OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python bench/track_live.py [--clip talk_animated]
        [--frames 90] [--rounds 2]

The frames are renders of the synthetic actor (`synth.tracking_eval`'s scene: 640x480, the
subject head to waist, both hands in view during talk_animated's gestures), rendered once
before timing. Each round runs the live configuration (`Tracker(threads=1,
palm_interval=LIVE_PALM_INTERVAL, iris=True)`, a fresh `SequenceFit` with smoothing and gaze)
over the same frames twice, interleaved:

* serial: `tracker.track` then `sequence_fit.step`, frame after frame (the server's per-session
  loop);
* pipelined: `tracked_frames` (telesplat track, telesplat-client drive): frame i + 1's
  landmarks while frame i is fitted, on a second thread.

Reported: wall time per frame and FPS over the whole sequence (the first frame's cold start
included), the median landmark and fit times, and the ratio.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from avatar_core.synth import tracking_eval as te  # noqa: E402
from avatar_core.track.fit.observations import from_track_result  # noqa: E402
from avatar_core.track.fit.video import tracked_frames  # noqa: E402


def live_tracker_and_fit(scene: te.Scene):
    from avatar_core.gaussians.animate import synthetic_package
    from avatar_core.track.fit.sequence import SequenceFit, SequenceFitConfig
    from avatar_core.track.tracker import LIVE_PALM_INTERVAL, Tracker

    tracker = Tracker(threads=1, palm_interval=LIVE_PALM_INTERVAL, iris=True)
    package, model = synthetic_package(scene.model_dir, 0)
    sequence_fit = SequenceFit(model, np.asarray(package.body.betas),
                               SequenceFitConfig(fov_x_deg=te.FOV_X_DEG))
    return tracker, sequence_fit


def run_serial(frames, tracker, sequence_fit) -> tuple[float, list[float], list[float]]:
    track_ms, fit_ms = [], []
    t0 = time.perf_counter()
    for frame, t in frames:
        a = time.perf_counter()
        result = tracker.track(frame)
        b = time.perf_counter()
        sequence_fit.step(from_track_result(result), t)
        track_ms.append((b - a) * 1e3)
        fit_ms.append((time.perf_counter() - b) * 1e3)
    return time.perf_counter() - t0, track_ms, fit_ms


def run_pipelined(frames, tracker, sequence_fit) -> tuple[float, list[float], list[float]]:
    t0 = time.perf_counter()
    out = list(tracked_frames(frames, sequence_fit, tracker))
    return (time.perf_counter() - t0, [f.track_ms for f in out], [f.fit_ms for f in out])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--clip", default="talk_animated")
    ap.add_argument("--frames", type=int, default=90)
    ap.add_argument("--start", type=float, default=1.0, help="clip time of the first frame")
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args()
    scene = te.make_scene()
    rng = np.random.default_rng(0)
    gt = te.clip_params(scene, args.clip, 30.0, args.start, args.frames)
    frames = [(te.render_frame(scene.actor, p, scene.camera, scene.bg, 2 / 255, rng), i / 30)
              for i, p in enumerate(gt)]
    print(f"{len(frames)} frames of {args.clip} rendered; load {os.getloadavg()[0]:.2f}")
    rows: dict[str, list] = {"serial": [], "pipelined": []}
    for _ in range(args.rounds):
        for name, run in (("serial", run_serial), ("pipelined", run_pipelined)):
            tracker, sequence_fit = live_tracker_and_fit(scene)
            rows[name].append(run(frames, tracker, sequence_fit))
            tracker.close()
    print(f"{'':10s} {'ms/frame':>9s} {'FPS':>6s} {'landmarks ms':>13s} {'fit ms':>7s}")
    per_frame = {}
    for name, runs in rows.items():
        wall = min(r[0] for r in runs)  # the least disturbed round
        per_frame[name] = wall / len(frames) * 1e3
        track = statistics.median([m for r in runs for m in r[1]])
        fit = statistics.median([m for r in runs for m in r[2]])
        print(f"{name:10s} {per_frame[name]:9.1f} {1e3 / per_frame[name]:6.1f} {track:13.1f} "
              f"{fit:7.1f}")
    print(f"pipelined / serial throughput: {per_frame['serial'] / per_frame['pipelined']:.2f}x;"
          f" load {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
