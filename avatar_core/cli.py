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


def _render(args: argparse.Namespace) -> int:
    from .pipeline import render_sequence
    from .render.types import RenderRequest

    request = RenderRequest(backend=args.backend, sh_degree=args.sh_degree, budget=args.budget,
                            background=tuple(args.background))
    with tqdm(total=args.frames, desc="rendering", unit="frame") as bar:
        def progress(i: int, n: int) -> None:
            bar.total = n
            bar.update(i - bar.n)

        out = render_sequence(args.avatar, args.motion, args.camera, args.out, size=args.size,
                              fps=args.fps, frames=args.frames, model_dir=args.models,
                              request=request, progress=progress)
    print(f"wrote {out}")
    return 0


def _budget(text: str) -> int | float:
    value = float(text)
    return value if "." in text else int(value)


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

    render = groups.add_parser("render", help="render an avatar under a motion")
    render.add_argument("avatar", help="avatar package (folder or .zip) or synthetic[:IDENTITY]")
    render.add_argument("--motion", default="demo",
                        help="built-in clip (demo, rest), or a .json / .npz parameter file")
    render.add_argument("--camera", default="orbit", help="'orbit' or a JSON camera file")
    render.add_argument("--out", type=Path, required=True, help="folder of PNGs or FILE.mp4")
    render.add_argument("--models", type=Path, default=None, help="synthetic model folder")
    render.add_argument("--size", type=int, default=512)
    render.add_argument("--fps", type=float, default=25.0)
    render.add_argument("--frames", type=int, default=None, help="at most this many frames")
    render.add_argument("--backend", default="auto", choices=["auto", "torch", "cpu", "gsplat"])
    render.add_argument("--sh-degree", type=int, default=None)
    render.add_argument("--budget", type=_budget, default=None,
                        help="render only the K (int) or fraction (float) most important splats")
    render.add_argument("--background", type=float, nargs=3, default=(1.0, 1.0, 1.0))
    render.set_defaults(func=_render)
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
