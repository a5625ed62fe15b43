"""How far the learned world-bone correction (`track.fit.world_correction`) puts the arm
bones from the truth, against BlazePose's own, on recordings it was not fitted on; and the
ridge chosen by leaving one training identity out.

    PYTHONPATH=. python bench/world_correction_eval.py --train out/wcorr/train \
        --ridges 10,100,1000,10000 --eval /tmp/w28/rec /tmp/p28/rec_hips
"""

from __future__ import annotations

import argparse
import pickle
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from avatar_core.synth.world_correction_build import pairs_of  # noqa: E402
from avatar_core.track.fit import world_correction as wc  # noqa: E402


def load(paths) -> dict[str, object]:
    out = {}
    for path in paths:
        with open(path, "rb") as f:
            out[Path(path).stem] = pickle.load(f)
    return out


def cell(errors: dict[str, float]) -> str:
    return (f"{errors['upper_median']:.1f} / {errors['fore_median']:.1f} "
            f"(p90 {errors['upper_p90']:.1f} / {errors['fore_p90']:.1f})")


def leave_one_identity_out(train: dict[str, object], ridge: float) -> tuple[float, ...]:
    """Mean over training identities of the held-out identity's median bone errors:
    (upper BlazePose, upper corrected, fore BlazePose, fore corrected)."""
    identities = sorted({name.split("_")[0] for name in train})
    rows = []
    for held in identities:
        fit = [r for n, r in train.items() if n.split("_")[0] != held]
        test = [r for n, r in train.items() if n.split("_")[0] == held]
        corr = wc.solve(*pairs_of(fit), ridge=ridge)
        before, after = wc.bone_errors_deg(test, None), wc.bone_errors_deg(test, corr)
        rows.append([before["upper_median"], after["upper_median"], before["fore_median"],
                     after["fore_median"]])
    return tuple(np.mean(rows, axis=0))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--train", type=Path, required=True,
                    help="the build's --work folder (its recordings)")
    ap.add_argument("--ridges", default="", help="comma-separated ridges to cross-validate")
    ap.add_argument("--asset", type=Path, default=None, help="default: the committed asset")
    ap.add_argument("--eval", type=Path, nargs="*", default=[],
                    help="folders of protocol recordings (bench/webcam_replay.py --record)")
    args = ap.parse_args()
    train = load(sorted(args.train.glob("*.pkl")))
    if args.ridges:
        print("| ridge | upper arms: BlazePose -> corrected (median deg) | forearms |")
        print("|---:|---|---|")
        for ridge in (float(r) for r in args.ridges.split(",")):
            ub, ua, fb, fa = leave_one_identity_out(train, ridge)
            print(f"| {ridge:g} | {ub:.1f} -> {ua:.1f} | {fb:.1f} -> {fa:.1f} |", flush=True)
    corr = wc.load_world_correction(args.asset)
    print("\n| recording | BlazePose: upper / fore median deg (p90) | corrected |")
    print("|---|---|---|")
    for folder in args.eval:
        for name, rec in load(sorted(folder.glob("*.pkl"))).items():
            print(f"| {folder.name}/{name} | {cell(wc.bone_errors_deg([rec], None))} | "
                  f"{cell(wc.bone_errors_deg([rec], corr))} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
