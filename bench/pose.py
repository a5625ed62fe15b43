"""Time the pose stage (triangle frames -> world-space Gaussians) on CPU: the torch reference
against the numba kernel, interleaved in one process so their ratio holds on a noisy machine.

    OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 .venv/bin/python bench/pose.py [--repeats 30]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from avatar_core.gaussians.animate import AvatarAnimator, synthetic_package  # noqa: E402
from avatar_core.gaussians.avatar import GaussianAvatar, pose_gaussians  # noqa: E402
from avatar_core.synth.model_writer import ensure_models  # noqa: E402


def _avatar(num: int, num_faces: int, rng: np.random.Generator) -> GaussianAvatar:
    parents = np.sort(np.concatenate([np.arange(num_faces),
                                      rng.integers(0, num_faces, max(num - num_faces, 0))]))[:num]
    t = lambda a: torch.as_tensor(a, dtype=torch.float32)  # noqa: E731
    return GaussianAvatar(parents=torch.as_tensor(parents),
                          local_means=t(rng.normal(0, .3, (num, 3))),
                          log_scales=t(rng.normal(-3, .5, (num, 3))),
                          quats=t(rng.normal(size=(num, 4))),
                          opacity_logits=t(rng.normal(size=num)), sh=torch.zeros(num, 16, 3))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=30)
    args = ap.parse_args()
    torch.set_num_threads(1)
    package, model = synthetic_package(ensure_models().root)
    rng = np.random.default_rng(0)
    faces = model.faces
    print(f"torch {torch.__version__}, {faces.shape[0]} faces, 1 torch thread")
    print(f"{'gaussians':>9} {'torch ms':>9} {'kernel ms':>9} {'speedup':>8} {'animator ms':>12}")
    for num in (16_016, 35_000, 60_000):
        animator = AvatarAnimator(model, _avatar(num, faces.shape[0], rng),
                                  betas=package.body.betas)
        times = {"torch": [], "kernel": [], "animator": []}
        with torch.no_grad():
            for i in range(args.repeats + 3):
                params = {"body_pose": rng.normal(0, 0.2, (21, 3)),
                          "expression": rng.normal(0, 1, 10)}
                t0 = time.perf_counter()
                posed = animator.pose(params)  # body model + kernel (cached constants)
                t1 = time.perf_counter()
                pose_gaussians(animator.avatar, posed.vertices, faces, backend="torch")
                t2 = time.perf_counter()
                animator._gaussians(posed.vertices)
                t3 = time.perf_counter()
                if i >= 3:
                    for name, dt in zip(times, (t2 - t1, t3 - t2, t1 - t0), strict=True):
                        times[name].append(dt * 1e3)
        med = {k: statistics.median(v) for k, v in times.items()}
        print(f"{num:>9} {med['torch']:>9.2f} {med['kernel']:>9.2f} "
              f"{med['torch'] / med['kernel']:>7.1f}x {med['animator']:>12.2f}")


if __name__ == "__main__":
    main()
