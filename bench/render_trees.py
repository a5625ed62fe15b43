"""One rasterize of the synthetic demo avatar (rest pose, 512x512, cpu backend, one thread),
timed in several source trees side by side: a process per tree, the trees interleaved five
frames at a time, so load drift on a shared machine hits them all alike.

    .venv/bin/python bench/render_trees.py TREE [TREE ...] [--rounds 10]

A TREE is a checkout of a commit (``git worktree add ../before <commit>``). Prints the median
and 10th percentile per tree.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time


def child(tree: str) -> None:
    sys.path.insert(0, tree)
    import numba
    import numpy as np
    import torch

    torch.set_num_threads(1)
    numba.set_num_threads(1)
    from avatar_core.gaussians.loading import load_avatar
    from avatar_core.render import rasterize
    from avatar_core.render.camera import orbit
    from avatar_core.render.camera_path import framing_target
    from avatar_core.render.types import RenderRequest

    module = sys.modules["avatar_core.render.rasterize"].__file__
    assert module.startswith(os.path.abspath(tree)), module
    animator = load_avatar("synthetic", None).animator
    with torch.no_grad():
        gaussians = animator.pose({}).gaussians
    cam = orbit(np.asarray(framing_target(animator.body_model.joint_template)), 20, 0, 2.4,
                width=512, height=512, fov_y_deg=35)
    request = RenderRequest(outputs=("rgb",), backend="cpu")
    for _ in range(3):  # numba compiled, caches warm
        rasterize(gaussians, cam, request)
    print("ready", flush=True)
    for line in sys.stdin:  # one batch a line, until the parent closes stdin
        times = []
        for _ in range(int(line)):
            t0 = time.perf_counter()
            rasterize(gaussians, cam, request)
            times.append((time.perf_counter() - t0) * 1e3)
        print(json.dumps(times), flush=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("trees", nargs="+")
    parser.add_argument("--rounds", type=int, default=10)
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args.trees[0])
        return 0
    env = {**os.environ, "OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}
    procs = [subprocess.Popen([sys.executable, __file__, "--child", os.path.abspath(t)],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                              env=env) for t in args.trees]
    times: dict[str, list[float]] = {t: [] for t in args.trees}
    try:
        for proc in procs:
            if proc.stdout.readline().strip() != "ready":
                raise SystemExit("a tree's renderer did not start")
        for _ in range(args.rounds):
            for tree, proc in zip(args.trees, procs, strict=True):
                proc.stdin.write("5\n")
                proc.stdin.flush()
                times[tree] += json.loads(proc.stdout.readline())
    finally:
        for proc in procs:
            proc.stdin.close()
            proc.wait(timeout=60)
    print("| tree | rasterize median (ms) | p10 (ms) | frames |")
    print("|---|---:|---:|---:|")
    for tree in args.trees:
        t = sorted(times[tree])
        print(f"| {tree} | {statistics.median(t):.1f} | {t[len(t) // 10]:.1f} | {len(t)} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
