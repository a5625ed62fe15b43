"""The fitter's cost: the analytic keypoint Jacobian against the forward differences it
replaced, and whole fits (cold and warm), side by side in one run.

    OMP_NUM_THREADS=1 python bench/track_fit.py [--repeat 50]

The landmarks are the synthetic model's own keypoints for a webcam-like frame (head turned,
jaw open, arms raised, a peace and a fist gesture) with 1 px noise, as in
tests/test_track_fit.py. Reported: median milliseconds of

* keypoints: `KeypointKinematics.evaluate` (numpy, one frame) vs the torch `BodyKeypoints`;
* keypoints + Jacobian by all 148 free variables: analytic (one numpy pass) vs batched
  forward differences through `BodyKeypoints` (one model pass of batch N + 1, the fitter's
  method before the analytic Jacobian);
* a cold fit and a warm fit (the next frame, phase + 0.05), with their iteration counts.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
for path in (ROOT, ROOT / "tests"):
    if str(path) not in sys.path:
        sys.path.insert(0, str(path))

from test_track_fit import CAMERA, known_params  # noqa: E402

from avatar_core.gaussians.animate import synthetic_package  # noqa: E402
from avatar_core.motion.rig import model_rig  # noqa: E402
from avatar_core.synth.model_writer import ensure_models  # noqa: E402
from avatar_core.track.fit.fitter import FrameFitter  # noqa: E402
from avatar_core.track.fit.synthetic import synthetic_observations  # noqa: E402


def median_ms(fn, repeat: int) -> float:
    fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def torch_params(fitter: FrameFitter, x: np.ndarray, batch: int = 1) -> dict:
    p = {k: torch.as_tensor(v)[None].expand(batch, *np.shape(v)).clone()
         for k, v in fitter.to_params(x).items()}
    p["betas"] = fitter.betas.expand(batch, -1)
    return p


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=50)
    args = ap.parse_args()
    torch.set_num_threads(1)
    files = ensure_models()
    package, model = synthetic_package(files.root, 0)
    fitter = FrameFitter(model, np.asarray(package.body.betas))
    rig = model_rig(files, model)
    obs, _ = synthetic_observations(fitter, known_params(model, rig, 0.0), CAMERA, 1.0)
    cold = fitter.fit(obs, CAMERA)
    x = fitter.pack(cold.params)
    n = x.size
    kp = fitter.keypoints
    kp.model.cache.enabled = False  # time the whole pass, as the fitter's batches do
    one = torch_params(fitter, x)
    batch = torch_params(fitter, x, n + 1)
    rows = []
    with torch.no_grad():
        rows.append(("keypoints", median_ms(lambda: kp(one), args.repeat),
                     median_ms(lambda: fitter._keypoints(x, False), args.repeat)))
        rows.append((f"keypoints + Jacobian ({n} variables)",
                     median_ms(lambda: kp(batch), max(5, args.repeat // 5)),
                     median_ms(lambda: fitter._keypoints(x, True), args.repeat)))
    print(f"{'':40s} {'reference ms':>13s} {'analytic ms':>12s} {'speed-up':>9s}")
    for name, ref, fast in rows:
        print(f"{name:40s} {ref:13.2f} {fast:12.2f} {ref / fast:8.1f}x")
    obs2, _ = synthetic_observations(fitter, known_params(model, rig, 0.05), CAMERA, 1.0)
    cold_ms = median_ms(lambda: fitter.fit(obs, CAMERA), max(3, args.repeat // 10))
    warm_ms = median_ms(lambda: fitter.fit(obs2, CAMERA, cold.params), args.repeat)
    warm = fitter.fit(obs2, CAMERA, cold.params)
    print(f"cold fit: {cold_ms:.1f} ms ({cold.stats['iterations']} iterations, "
          f"{cold.stats['evaluations']} evaluations)")
    print(f"warm fit: {warm_ms:.1f} ms ({warm.stats['iterations']} iterations, "
          f"{warm.stats['evaluations']} evaluations)")


if __name__ == "__main__":
    main()
