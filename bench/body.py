"""Time the upper-body forward pass on CPU: batch 1 and 64, with and without the stage cache.

The cached case is the streaming one: only the expression changes between frames, so the
shape, pose-corrective and joint-transform stages are reused. Both variants run interleaved in
one process, so their ratio is meaningful even on a noisy machine.

    .venv/bin/python bench/body.py [--repeats 30] [--models DIR]
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from avatar_core.body.model_data import load_smplx  # noqa: E402
from avatar_core.body.upper_body import UpperBodyModel, load_segmentation  # noqa: E402
from avatar_core.synth.model_writer import ensure_models  # noqa: E402


def _params(batch: int, rng: np.random.Generator) -> dict[str, torch.Tensor]:
    p = {
        "betas": rng.normal(0, 1, (batch, 10)), "expression": rng.normal(0, 1, (batch, 10)),
        "global_orient": rng.normal(0, 0.2, (batch, 3)),
        "body_pose": rng.normal(0, 0.2, (batch, 21, 3)), "jaw_pose": rng.normal(0, 0.1, (batch, 3)),
        "left_hand_pose": rng.normal(0, 0.3, (batch, 15, 3)),
        "right_hand_pose": rng.normal(0, 0.3, (batch, 15, 3)),
    }
    return {k: torch.as_tensor(v, dtype=torch.float32) for k, v in p.items()}


def bench(model_cached, model_plain, batch: int, repeats: int) -> dict[str, float]:
    rng = np.random.default_rng(batch)
    base = _params(batch, rng)
    exprs = [torch.as_tensor(rng.normal(0, 1, (batch, 10)), dtype=torch.float32)
             for _ in range(repeats + 3)]
    times = {"full": [], "cached": []}
    with torch.inference_mode():
        for i, expr in enumerate(exprs):
            params = {**base, "expression": expr}
            t0 = time.perf_counter()
            model_plain(params)
            t1 = time.perf_counter()
            model_cached(params)
            t2 = time.perf_counter()
            if i >= 3:  # warm-up
                times["full"].append((t1 - t0) * 1e3)
                times["cached"].append((t2 - t1) * 1e3)
    full, cached = statistics.median(times["full"]), statistics.median(times["cached"])
    return {"full_ms": full, "cached_ms": cached, "speedup": full / cached}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--models", type=Path, default=None)
    args = parser.parse_args()
    files = ensure_models(args.models)
    data = load_smplx(files.smplx_npz)
    seg = load_segmentation(files.segmentation, data.num_vertices)
    plain = UpperBodyModel(data, seg, cache=False)
    cached = UpperBodyModel(data, seg, cache=True)
    print(f"# upper-body forward, float32, {plain.num_vertices} vertices, "
          f"{torch.get_num_threads()} torch threads, {platform.processor() or platform.machine()}")
    print("| batch | no cache (ms) | cache, expression-only change (ms) | speed-up |")
    print("|---:|---:|---:|---:|")
    for batch in (1, 64):
        r = bench(cached, plain, batch, args.repeats)
        print(f"| {batch} | {r['full_ms']:.2f} | {r['cached_ms']:.2f} | {r['speedup']:.1f}x |")


if __name__ == "__main__":
    main()
