"""What the page's new default costs on the CPU backend: a frame of the synthetic demo avatar
in the T-pose from the old default orbit (chest, 2.7 m) against the rest pose from the same
orbit and from the welcome's framing (the page's new default, closer, so the avatar covers
more pixels), interleaved in one process so the ratios hold on a noisy machine; and the time
the welcome's framing adds to a join (a rest forward pass at an avatar's first join, kept),
and how many pixels the page's hand-curl slider changes in each case.

    OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 .venv/bin/python bench/page_view.py [--repeats 10]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from avatar_core.body.rest_pose import rest_body_pose  # noqa: E402
from avatar_core.gaussians.loading import load_avatar  # noqa: E402
from avatar_core.render.camera import orbit  # noqa: E402
from avatar_core.render.camera_path import framing_target  # noqa: E402
from avatar_core.render.types import RenderRequest  # noqa: E402
from avatar_core.render.views import render_views  # noqa: E402
from server.stream.framing import pose_at_rest, room_framing  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--repeats", type=int, default=10)
    args = ap.parse_args()
    torch.set_num_threads(1)
    animator = load_avatar("synthetic").animator
    seat = SimpleNamespace(index=0, avatar="demo",
                           placement=SimpleNamespace(rotation=(0, 0, 0), translation=(0, 0, 0)))
    framing = room_framing([seat], 0, lambda _: animator)
    chest = framing_target(animator.body_model.joint_template)
    n = args.size
    old_view = orbit(chest, 0, 0, 2.7, width=n, height=n)
    new_view = orbit(np.asarray(framing.target), 0, 0, framing.distance, width=n, height=n)
    cases = {
        "T-pose, old view (chest, 2.7 m)": (np.zeros((21, 3)), old_view),
        "rest, old view": (rest_body_pose(), old_view),
        f"rest, framing ({framing.distance:.2f} m)": (rest_body_pose(), new_view),
    }
    worlds = {k: animator.pose({"body_pose": pose}).gaussians for k, (pose, _) in cases.items()}
    times: dict[str, list[float]] = {k: [] for k in cases}
    pairs = {}
    for _ in range(args.repeats + 1):  # the first round warms the kernels up, not counted
        for name, (_, camera) in cases.items():
            t0 = time.perf_counter()
            out = render_views(worlds[name], [camera], RenderRequest(backend="cpu"))[0]
            times[name].append((time.perf_counter() - t0) * 1e3)
            pairs[name] = out.stats.get("tile_pairs")
    base = statistics.median(times["T-pose, old view (chest, 2.7 m)"][1:])
    print(f"{n} px frame, cpu backend, median of {args.repeats}:")
    for name, ms in times.items():
        med = statistics.median(ms[1:])
        print(f"  {name:34s} {med:7.1f} ms  x{med / base:4.2f}  tile pairs {pairs[name]}")
    # What the page's "left hand curl" slider at 1.5 (client/web/controls.js) changes: pixels
    # (sum of |RGB| over 60 of 765) of the same frames.
    curl = np.zeros((15, 3))
    curl[:12, 2], curl[12:, 2] = -1.5, -0.75
    for name, (pose, camera) in cases.items():
        frames = [render_views(animator.pose({"body_pose": pose, **hand}).gaussians, [camera],
                               RenderRequest(backend="cpu", background=(1, 1, 1)))[0].rgb
                  for hand in ({}, {"left_hand_pose": curl})]
        changed = int(((frames[0] - frames[1]).abs().sum(-1) * 255 > 60).sum())
        print(f"  hand curl changes, {name:34s} {changed:6d} px")
    for what, run in (("first join of an avatar", lambda: pose_at_rest(animator)),
                      ("a later join", lambda: room_framing([seat], 0, lambda _: animator))):
        ms = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            run()
            ms.append((time.perf_counter() - t0) * 1e3)
        print(f"  welcome framing, {what:22s} {statistics.median(ms):7.2f} ms")

if __name__ == "__main__":
    main()
