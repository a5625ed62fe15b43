"""What ground-truth quality costs in time: supersampling in the capture studio.

Renders the actor (identity 0) from all 17 studio cameras for a few frames of a gesture at
512x512 with supersampling 1..4, and reports milliseconds per view (one thread) next to the
PSNR of each against a 6x6-supersampled reference (how much edge aliasing is left).

    .venv/bin/python bench/capture.py [--size 512] [--frames 3]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from avatar_core.metrics.image import psnr  # noqa: E402
from avatar_core.motion.library import motion  # noqa: E402
from avatar_core.motion.rig import model_rig  # noqa: E402
from avatar_core.synth.actor import Actor  # noqa: E402
from avatar_core.synth.model_writer import ensure_models  # noqa: E402
from avatar_core.synth.studio import studio_rig  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--frames", type=int, default=3)
    args = ap.parse_args()
    files = ensure_models()
    actor = Actor.load(files, 0)
    rig, clip = studio_rig(args.size), motion("peace")
    params = model_rig(files, actor.model)
    posed = [actor.pose(clip.sample(clip.duration * (i + 1) / (args.frames + 1), params))
             for i in range(args.frames)]
    ref = [[actor.render(p, c.camera, supersample=6).rgb for c in rig] for p in posed]
    actor.render(posed[0], rig[0].camera, supersample=1)  # compile the kernels
    print("| supersample | ms / view | PSNR vs 6x6 (dB) |\n|---:|---:|---:|")
    for ss in (1, 2, 3, 4):
        t0, errs = time.perf_counter(), []
        imgs = [[actor.render(p, c.camera, supersample=ss).rgb for c in rig] for p in posed]
        ms = (time.perf_counter() - t0) * 1e3 / (len(rig) * len(posed))
        for a, b in zip(imgs, ref, strict=True):
            errs += [float(psnr(x, y)) for x, y in zip(a, b, strict=True)]
        print(f"| {ss}x{ss} | {ms:.1f} | {np.mean(errs):.1f} |")


if __name__ == "__main__":
    main()
