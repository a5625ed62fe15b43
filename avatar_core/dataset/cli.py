"""`telesplat dataset ...`: validate a dataset, zip one for upload, import other tools'
captures.

`register(subparsers)` adds the "dataset" command group to the main parser; each command's
`func(args)` returns the exit status.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from tqdm import tqdm

__all__ = ["register"]


def _validate(args: argparse.Namespace) -> int:
    from .problems import ERROR
    from .validate import validate_dataset

    problems = validate_dataset(args.dataset, deep=args.deep)
    for p in problems:
        print(p)
    errors = sum(p.severity == ERROR for p in problems)
    warnings = len(problems) - errors
    print(f"{args.dataset}: {errors} error(s), {warnings} warning(s)"
          + (" (deep)" if args.deep else ""))
    return 1 if errors or (args.strict and warnings) else 0


def _preview(args: argparse.Namespace) -> int:
    from .loader import load_dataset
    from .preview import contact_sheet, write_png

    ds = load_dataset(args.dataset)
    sequence = args.sequence or next(iter(ds.sequences))
    out = write_png(args.out, contact_sheet(ds, sequence, args.frame, columns=args.columns,
                                            size=args.size))
    print(f"wrote {out}")
    return 0


def _progress(bar: tqdm):
    def update(done: int, total: int) -> None:
        bar.total = total
        bar.update(done - bar.n)
    return update


def _zip(args: argparse.Namespace) -> int:
    from .pack import DatasetIncomplete, zip_dataset

    try:
        with tqdm(desc="zipping", unit="file") as bar:
            out = zip_dataset(args.dataset, args.out, progress=_progress(bar))
    except DatasetIncomplete as exc:
        print(f"telesplat: error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {out} ({out.stat().st_size / 2**20:.1f} MiB); upload it with "
          f"'telesplat-client jobs submit --archive {out}'")
    return 0


def _import_vhap(args: argparse.Namespace) -> int:
    from .importers.vhap import import_vhap

    with tqdm(desc="importing", unit="view") as bar:
        out = import_vhap(args.src, args.out, name=args.name, identity=args.identity,
                          fps=args.fps, progress=_progress(bar))
    print(f"wrote dataset {out}")
    return 0


def _import_easymocap(args: argparse.Namespace) -> int:
    from .importers.easymocap import import_easymocap

    holdout = tuple(c for c in (args.holdout_cameras or "").split(",") if c)
    with tqdm(desc="importing", unit="view") as bar:
        out = import_easymocap(
            args.src, args.out, sequence=args.sequence, person=args.person,
            smpl_dir=args.smpl_dir, mask_dir=args.mask_dir, smplx_model=args.smplx_model,
            holdout_cameras=holdout, fps=args.fps, image_format=args.image_format,
            identity=args.identity, progress=_progress(bar))
    print(f"wrote dataset {out}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `dataset validate`, `dataset preview`, `dataset zip` and
    `dataset import {vhap,easymocap}`."""
    group = subparsers.add_parser("dataset", help="multi-view capture datasets")
    cmds = group.add_subparsers(dest="command", required=True)

    val = cmds.add_parser("validate", help="list every problem of a dataset")
    val.add_argument("dataset", type=Path)
    val.add_argument("--deep", action="store_true",
                     help="decode every image (part values, empty masks); slower")
    val.add_argument("--strict", action="store_true", help="warnings fail too")
    val.set_defaults(func=_validate)

    pre = cmds.add_parser("preview", help="contact sheet of one frame across all cameras")
    pre.add_argument("dataset", type=Path)
    pre.add_argument("--out", type=Path, required=True, help="PNG to write")
    pre.add_argument("--sequence", default=None, help="default: the first sequence")
    pre.add_argument("--frame", type=int, default=0)
    pre.add_argument("--columns", type=int, default=6)
    pre.add_argument("--size", type=int, default=256, help="tile size in pixels")
    pre.set_defaults(func=_preview)

    zp = cmds.add_parser("zip", help="zip a dataset for 'telesplat-client jobs submit "
                         "--archive' (refuses one with validation errors)")
    zp.add_argument("dataset", type=Path)
    zp.add_argument("--out", type=Path, required=True, help="FILE.zip to write")
    zp.set_defaults(func=_zip)

    imp = cmds.add_parser("import", help="convert another tool's capture layout")
    kinds = imp.add_subparsers(dest="layout", required=True)

    vhap = kinds.add_parser("vhap", help="GaussianAvatars / VHAP (NeRSemble) export")
    vhap.add_argument("src", type=Path, help="folder with transforms_{train,val,test}.json")
    vhap.add_argument("--out", type=Path, required=True, help="dataset folder to create")
    vhap.add_argument("--name", default=None)
    vhap.add_argument("--identity", default=None, help="default: SRC's name up to '_'")
    vhap.add_argument("--fps", type=float, default=25.0, help="not recorded by the layout")
    vhap.set_defaults(func=_import_vhap)

    em = kinds.add_parser("easymocap", help="EasyMocap multi-view capture + SMPL-X fit")
    em.add_argument("src", type=Path, help="folder with intri.yml, extri.yml, images/")
    em.add_argument("--out", type=Path, required=True, help="dataset folder to create")
    em.add_argument("--sequence", default=None, help="default: SRC's name")
    em.add_argument("--person", type=int, default=None,
                    help="person id (default: the smallest id present in every frame)")
    em.add_argument("--smpl-dir", default="output-smplx/smpl")
    em.add_argument("--mask-dir", default="mask", help="used when it exists")
    em.add_argument("--smplx-model", type=Path, default=None,
                    help="SMPL-X model file: convert Rh/Th to smplx's pelvis-centred root")
    em.add_argument("--holdout-cameras", default=None,
                    help="comma-separated cameras for the novel_view split")
    em.add_argument("--fps", type=float, default=30.0, help="not recorded by the layout")
    em.add_argument("--image-format", choices=["png", "jpg"], default=None,
                    help="default: the source images' format")
    em.add_argument("--identity", default=None, help="default: SRC's name")
    em.set_defaults(func=_import_easymocap)
