"""The studio webcam protocol in two halves: film and track each condition once
(`--record`), then fit and score drives and fit variants on the very same landmarks
(`--replay`), side by side, without tracking again.

    OMP_NUM_THREADS=1 PYTHONPATH=. python bench/webcam_replay.py --record /tmp/w28/rec \
        --identities 0,1 --fps 10
    OMP_NUM_THREADS=1 PYTHONPATH=. python bench/webcam_replay.py --replay /tmp/w28/rec \
        --drives live,true_all_depth --out /tmp/w28/base
"""

from __future__ import annotations

import argparse
import pickle
import time
from pathlib import Path


def _conditions(args):
    from avatar_core.synth.tracking_eval.protocol import Condition

    ids = [int(x) for x in args.identities.split(",") if x.strip()]
    framings = [x.strip() for x in args.framings.split(",") if x.strip()]
    turns = [float(x) for x in args.turns.split(",") if x.strip()]
    leans = [float(x) for x in args.leans.split(",") if x.strip()]
    return [Condition(i, f, t, lean) for i in ids for f in framings for t in turns
            for lean in leans]


def _top_level_split(text: str) -> list[str]:
    """Split on the commas outside brackets: 'a=1,b=((1,2),(3,4))' -> ['a=1', 'b=((1,2),(3,4))']."""
    parts, depth, start = [], 0, 0
    for i, ch in enumerate(text):
        depth += (ch in "([{") - (ch in ")]}")
        if ch == "," and depth == 0:
            parts.append(text[start:i])
            start = i + 1
    return [*parts, text[start:]]


def parse_variants(text: str) -> dict[str, dict]:
    """'a:hold_arms=1,edge_margin=0.02;b:fit.temporal_weight=2' -> {"": {}, "a": {...}}
    (values parsed as Python literals; fit.X changes the drive's FitConfig: under "fit")."""
    import ast
    import dataclasses

    from avatar_core.track.fit.sequence import SequenceFitConfig

    out: dict[str, dict] = {"": {}}
    base = SequenceFitConfig()
    for item in filter(None, (t.strip() for t in text.split(";"))):
        label, _, fields = item.partition(":")
        changes, fit = {}, {}
        for pair in filter(None, (f.strip() for f in _top_level_split(fields))):
            key, _, value = pair.partition("=")
            (fit if key.startswith("fit.") else changes)[key.removeprefix("fit.")] = \
                ast.literal_eval(value)
        dataclasses.replace(base, fit=dataclasses.replace(base.fit, **fit),
                            **changes)  # unknown fields fail here, before any fitting
        if fit:
            changes["fit"] = fit  # changed on each drive's own fit (protocol.with_variant)
        out[label.strip()] = changes
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--record", type=Path, help="folder to write one recording per condition")
    ap.add_argument("--replay", type=Path, help="folder of recordings to fit and score")
    ap.add_argument("--identities", default="0,1")
    ap.add_argument("--framings", default="head_shoulders,waist_up")
    ap.add_argument("--turns", default="0", help="comma-separated turns of the whole body "
                    "about the vertical, deg (recordings named ID_FRAMING_turnDEG)")
    ap.add_argument("--leans", default="0", help="comma-separated forward leans of the whole "
                    "body, deg (recordings named ID_FRAMING[_turnDEG]_leanDEG)")
    ap.add_argument("--fps", type=float, default=10.0)
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--drives", default="live", help="comma-separated protocol drives")
    ap.add_argument("--out", type=Path, help="replay: folder for the summary and runs.pkl")
    ap.add_argument("--variants", default="",
                    help="fit variants beside the base, fitted side by side: "
                         "'label:field=value,field=value;label2:...' (SequenceFitConfig "
                         "fields; FitConfig fields as fit.field)")
    ap.add_argument("--no-curve", action="store_true", help="skip the One Euro curve")
    args = ap.parse_args()
    from avatar_core.synth.tracking_eval import protocol as wp
    from avatar_core.synth.tracking_eval.protocol_report import summarise, write_protocol

    if args.record:
        args.record.mkdir(parents=True, exist_ok=True)
        for cond in _conditions(args):
            t0 = time.perf_counter()
            rec = wp.record_condition(cond, args.fps, max_frames=args.max_frames)
            path = args.record / f"{cond.name}.pkl"
            with open(path, "wb") as f:
                pickle.dump(rec, f)
            print(f"wrote {path} ({len(rec.truth)} frames, {time.perf_counter() - t0:.0f} s)",
                  flush=True)
        return
    if not args.replay or not args.out:
        ap.error("give --record DIR, or --replay DIR --out DIR")
    drives = [d.strip() for d in args.drives.split(",") if d.strip()]
    variants = parse_variants(args.variants)
    runs = []
    for cond in _conditions(args):
        path = args.replay / f"{cond.name}.pkl"
        with open(path, "rb") as f:
            rec = pickle.load(f)  # noqa: S301 (our own file)
        t0 = time.perf_counter()
        runs.append(wp.fit_recording(rec, drives=drives, curve=not args.no_curve,
                                     variants=variants))
        print(f"{path.name}: {time.perf_counter() - t0:.0f} s", flush=True)
    js, md = write_protocol(summarise(runs), args.out)
    with open(args.out / "runs.pkl", "wb") as f:
        pickle.dump(runs, f)
    print(md.read_text())


if __name__ == "__main__":
    main()
