"""``telesplat enroll VIDEO --out DIR``: one person, one fixed camera -> an avatar package
(DIR/avatar), with a progress bar."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from tqdm import tqdm

from .config import EnrollConfig
from .errors import EnrollmentRefused

STAGES = ("decode", "select", "preflight", "track", "fit", "dataset", "train", "done")


def _enroll(args: argparse.Namespace) -> int:
    import logging

    from .pipeline import enroll_video

    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    config = EnrollConfig(iterations=args.iterations, resolution=args.resolution,
                          seed=args.seed, fine_tune=not args.no_fine_tune,
                          masks=not args.no_masks)
    with tqdm(total=1000, desc="enroll", unit="‰", bar_format="{l_bar}{bar}| {elapsed}") as bar:
        def progress(stage: str, fraction: float) -> None:
            # each stage fills its slot of the bar (training the largest)
            slots = {"decode": (0, 10), "select": (10, 20), "preflight": (20, 40),
                     "track": (40, 250), "fit": (250, 300), "dataset": (300, 320),
                     "train": (320, 1000), "done": (1000, 1000)}
            lo, hi = slots.get(stage, (bar.n, bar.n))
            bar.set_description(f"enroll: {stage}")
            bar.update(max(0, int(lo + fraction * (hi - lo)) - bar.n))

        try:
            result = enroll_video(args.video, args.out, config=config, progress=progress,
                                  body_models=args.body_models, focal_px=args.focal_px)
        except EnrollmentRefused as exc:
            bar.close()
            print(f"telesplat: refused ({exc.reason}): {exc.message}\n  what to do: "
                  f"{exc.what_to_do}", file=sys.stderr)
            return 3
    doc = result.to_dict()
    print(json.dumps({k: doc[k] for k in ("frames", "yaw_range_deg", "focal_px", "train")},
                     indent=1))
    print(f"wrote avatar {result.package}")
    return 0


def register(groups: argparse._SubParsersAction, add_body_models) -> None:
    p = groups.add_parser("enroll", help="make an avatar from one video of yourself turning "
                          "slowly in front of a fixed camera")
    p.add_argument("video", type=Path, help="the video (mp4, mov, webm, ...)")
    p.add_argument("--out", type=Path, required=True,
                   help="output folder: avatar/ (the package), dataset/, enroll.json")
    p.add_argument("--iterations", type=int, default=EnrollConfig.iterations)
    p.add_argument("--resolution", type=int, default=EnrollConfig.resolution,
                   help="longest side of the training images, px")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--focal-px", type=float, default=None,
                   help="the camera's focal length in px at the video's size, when known "
                        "(else a 60 deg prior refined by the fit)")
    p.add_argument("--no-fine-tune", action="store_true",
                   help="keep the tracked per-frame parameters fixed while training")
    p.add_argument("--no-masks", action="store_true",
                   help="no person masks and no mask loss (the ablation)")
    add_body_models(p)
    p.set_defaults(func=_enroll)
