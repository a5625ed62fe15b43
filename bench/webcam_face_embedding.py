"""The learned embedding's face rows alone (every other row's offset and pose basis zeroed)
beside the arm cues, on one recorded condition of the studio webcam protocol: does the
embedding's face help once the arms come from BlazePose's world bones? (docs/tracking.md)

    OMP_NUM_THREADS=1 PYTHONPATH=. python bench/webcam_face_embedding.py \
        out/w28/rec/0_waist_up.pkl --out out/w29/face_0_waist_up.pkl
"""

from __future__ import annotations

import argparse
import dataclasses
import pickle
from pathlib import Path

import numpy as np


def rows_only(embedding, rows: np.ndarray):
    """`embedding` with every row but `rows` at no offset and no pose correction."""
    from avatar_core.track.fit import correspondence as cor

    keep = np.zeros(cor.NUM_KEYPOINTS, dtype=bool)
    keep[rows] = True
    basis = None if embedding.pose_basis is None else \
        np.where(keep[:, None, None], embedding.pose_basis, 0.0)
    return dataclasses.replace(embedding, offset=np.where(keep[:, None], embedding.offset, 0.0),
                               pose_basis=basis)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recording", type=Path, help="one condition's .pkl (webcam_replay --record)")
    ap.add_argument("--out", type=Path, help="write the RunResult list here (runs.pkl format)")
    args = ap.parse_args()
    from avatar_core.body.skeleton import JOINT
    from avatar_core.synth.tracking_eval import protocol as wp
    from avatar_core.track.fit import correspondence as cor
    from avatar_core.track.fit.embedding import load_embedding

    full = load_embedding()
    face = np.arange(cor.FACE_SLICE.start, cor.FACE_SLICE.stop)
    head = cor.POSE_SLICE.start + np.flatnonzero(full.joint[cor.POSE_SLICE] == JOINT["head"])
    # changes on the arm_cues drive's own fit (protocol.with_variant)
    variants = {
        "face": {"fit": {"embedding": rows_only(full, face)}},
        "facehead": {"fit": {"embedding": rows_only(full, np.concatenate([face, head]))}}}
    with open(args.recording, "rb") as f:
        rec = pickle.load(f)
    res = wp.fit_recording(rec, drives=["arm_cues", *(f"arm_cues+{v}" for v in variants)],
                           variants=variants, curve=False)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        with open(args.out, "wb") as f:
            pickle.dump([res], f)
    for drive, values in res.psnr.items():
        print(f"{drive}: PSNR {np.mean(values):.2f} dB")


if __name__ == "__main__":
    main()
