"""Tracking on renders with known parameters: the real Tracker + SequenceFit on the textured
synthetic actor, against the SMPL-X parameters that posed it.

    OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python bench/track_eval.py \
        [--clips smile,mouth_open,...] [--fps 30] [--max-frames N] \
        [--contact docs/track_synthetic.png] [--json out.json]

The evaluation itself (scene, metrics, reports) is `avatar_core.synth.tracking_eval`; its
docstring says what is measured.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from avatar_core.synth.tracking_eval import (  # noqa: E402
    CLIPS,
    IGNORABLE,
    contact_sheet,
    make_scene,
    make_tracker_and_fit,
    offset_table,
    run_clip,
    tables,
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--clips", default=",".join(CLIPS))
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--max-frames", type=int, default=None)
    parser.add_argument("--background", choices=("noise", "plain"), default="noise")
    parser.add_argument("--contact", type=Path, default=None)
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--ignore", default="",
                        help="ablation: landmark classes left out of the fit, comma-separated "
                             f"({', '.join(IGNORABLE)})")
    args = parser.parse_args()
    torch.set_num_threads(1)
    log = lambda msg: print(msg, file=sys.stderr, flush=True)  # noqa: E731
    t0 = time.perf_counter()
    scene = make_scene(args.background)
    tracker, sequence_fit = make_tracker_and_fit(scene)
    log(f"setup {time.perf_counter() - t0:.1f} s; subject transl {np.round(scene.transl, 3)}; "
        f"load {os.getloadavg()[0]:.2f}")
    results = [run_clip(scene, name.strip(), tracker, sequence_fit, args.fps, args.max_frames,
                        keep_frames=args.contact is not None,
                        ignore=tuple(c for c in args.ignore.split(",") if c), log=log)
               for name in args.clips.split(",") if name.strip()]
    print(tables(results))
    print()
    print(offset_table(results))
    print(f"\nload average after: {os.getloadavg()[0]:.2f}; "
          f"median track+fit {statistics.median([x for r in results for x in r.ms]):.0f} ms")
    if args.contact:
        log(f"wrote {contact_sheet(results, args.contact)}")
    if args.json:
        args.json.write_text(json.dumps({r.name: r.metrics for r in results}, indent=1))


if __name__ == "__main__":
    main()
