"""Split a drive's remaining gap by part: its fitted parameters with each part (root,
spine, collars, arms, wrists, head, hands, face) swapped for the truth, alone and all but
it, scored at the score camera (`synth/tracking_eval/part_swap.py`), per framing.

    PYTHONPATH=. python bench/webcam_part_swap.py /tmp/wc28/id0/runs.pkl \
        /tmp/wc28/id1/runs.pkl --drives true_all_depth,live --out /tmp/w28/swap
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

KEYS = ("psnr", "root", "shoulders", "elbows", "wrists", "neck_head")


def _table(rows: dict[str, dict[str, dict[str, float]]], framings: list[str]) -> list[str]:
    head = " | ".join(f"PSNR {f}" for f in framings)
    lines = [f"| parts from the truth | PSNR | {head} | root° | shoulders° | elbows° | "
             "wrists° | neck/head° |", "|---|" + "---:|" * (6 + len(framings))]
    for label, per in rows["all"].items():
        cells = [f"{per['psnr']:.2f}", *(f"{rows[f][label]['psnr']:.2f}" for f in framings),
                 *(f"{per[k]:.1f}" for k in KEYS[1:])]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="runs.pkl files (our own output)")
    ap.add_argument("--drives", default="true_all_depth")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--parts", default=None,
                    help="comma-separated parts to swap alone and all-but (default: all)")
    ap.add_argument("--arm-split", action="store_true",
                    help="also the arms' world directions apart from their twist about each "
                         "bone (part_swap.arm_split_variants)")
    ap.add_argument("--stride", type=int, default=1,
                    help="score every n-th frame (the renders are the cost)")
    ap.add_argument("--score-size", type=int, default=320, help="as the runs used (4:3)")
    args = ap.parse_args()
    from avatar_core.synth.actor import Actor
    from avatar_core.synth.model_writer import ensure_models
    from avatar_core.synth.tracking_eval.part_swap import score_swaps, swap_variants
    from avatar_core.synth.tracking_eval.protocol import (
        framed_transl,
        score_camera,
        webcam_camera,
    )
    from avatar_core.synth.tracking_eval.protocol_report import load_runs

    runs = load_runs(args.runs)
    for res in runs:
        res.truth = res.truth[::args.stride]
        res.smooth = {d: v[::args.stride] for d, v in res.smooth.items()}
    size = (args.score_size, args.score_size * 3 // 4)
    args.out.mkdir(parents=True, exist_ok=True)
    drives = [d.strip() for d in args.drives.split(",") if d.strip()]
    framings = sorted({r.condition.framing for r in runs})
    parts = tuple(p.strip() for p in args.parts.split(",")) if args.parts else None
    variants = swap_variants(parts) if parts else None
    result, md = {}, []
    for drive in drives:
        per_cond = []
        for res in runs:
            actor = Actor.load(ensure_models(), res.condition.identity)
            cam = score_camera(framed_transl(actor, webcam_camera(), res.condition.framing),
                               actor, *size)
            per_cond.append((res, score_swaps(actor, res, drive, cam, variants, args.arm_split)))
            print(f"{drive} {res.condition}: done", flush=True)
        rows = {}
        for key, sel in [("all", None), *((f, f) for f in framings)]:
            use = [(r, s) for r, s in per_cond if sel is None or r.condition.framing == sel]
            n = np.array([len(r.truth) for r, _ in use], dtype=float)
            rows[key] = {label: {k: float(np.average([s[label][k] for _, s in use],
                                                     weights=n)) for k in KEYS}
                         for label in use[0][1]}
        result[drive] = {"overall": rows, "conditions": [
            {"identity": r.condition.identity, "framing": r.condition.framing, "swaps": s}
            for r, s in per_cond]}
        md += [f"### {drive}", "", *_table(rows, framings), ""]
    (args.out / "part_swap.json").write_text(json.dumps(result, indent=1))
    (args.out / "part_swap.md").write_text("\n".join(md))
    print("\n".join(md))


if __name__ == "__main__":
    main()
