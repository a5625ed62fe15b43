"""The `telesplat` command line."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from tqdm import tqdm


def _make_synthetic(args: argparse.Namespace) -> int:
    from .synth.model_files import write_synthetic_models

    files = write_synthetic_models(args.out, seed=args.seed, resolution=args.resolution,
                                   num_identities=args.identities)
    print(f"wrote synthetic SMPL-X / FLAME / MANO files to {files.root}")
    return 0


def _demo(args: argparse.Namespace) -> int:
    from .synth.body_demo import render_demo

    with tqdm(total=args.frames, desc="rendering demo", unit="frame") as bar:
        out = render_demo(args.out, model_dir=args.models, frames=args.frames, size=args.size,
                          fps=args.fps, identity=args.identity,
                          progress=lambda i, n: bar.update(i - bar.n))
    print(f"wrote {out}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="telesplat", description=__doc__)
    groups = parser.add_subparsers(dest="group", required=True)
    body = groups.add_parser("body", help="parametric body models")
    body_cmds = body.add_subparsers(dest="command", required=True)

    make = body_cmds.add_parser("make-synthetic", help="write synthetic SMPL-X/FLAME/MANO files")
    make.add_argument("--out", type=Path, required=True, help="output folder")
    make.add_argument("--seed", type=int, default=0)
    make.add_argument("--resolution", type=float, default=1.0,
                      help="mesh density; 1.0 gives the SMPL-X vertex count or more")
    make.add_argument("--identities", type=int, default=2)
    make.set_defaults(func=_make_synthetic)

    demo = body_cmds.add_parser("demo", help="render the posed synthetic upper body")
    demo.add_argument("--out", type=Path, required=True, help=".mp4 video or .png strip")
    demo.add_argument("--models", type=Path, default=None,
                      help="synthetic model folder (generated there if missing; default: cache)")
    demo.add_argument("--frames", type=int, default=96)
    demo.add_argument("--size", type=int, default=384)
    demo.add_argument("--fps", type=int, default=24)
    demo.add_argument("--identity", type=int, default=0)
    demo.set_defaults(func=_demo)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, OSError) as exc:
        print(f"telesplat: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
