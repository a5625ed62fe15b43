"""Re-summarise saved runs of the studio webcam protocol (`telesplat synth webcam-eval
--keep-frames` writes runs.pkl), e.g. conditions run as separate processes, with today's
metrics; and the hands a tracker declines: wrist errors over the frames where a hand is wholly
in view and its own landmarks are not seen.

    PYTHONPATH=. python bench/webcam_protocol_summary.py /tmp/a/runs.pkl /tmp/b/runs.pkl \
        --out /tmp/merged
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from avatar_core.body.skeleton import JOINT


def _score_camera(condition, size: tuple[int, int]):
    from avatar_core.synth.actor import Actor
    from avatar_core.synth.model_writer import ensure_models
    from avatar_core.synth.tracking_eval.protocol import (
        framed_transl,
        score_camera,
        webcam_camera,
    )

    actor = Actor.load(ensure_models(), condition.identity)
    transl = framed_transl(actor, webcam_camera(), condition.framing)
    return actor, score_camera(transl, actor, *size)


def declined_hands(actor, res, score_cam) -> dict[str, dict[str, float]]:
    """Per drive: mean world-rotation error (deg) of the hands (wrist joints) over the frames
    where a hand is wholly in view and not seen by the hand model, and the frame count."""
    from avatar_core.synth.tracking_eval.metrics import evaluate_params, geodesic_deg

    truth = evaluate_params(actor, res.truth, score_cam)
    out = {}
    for d in res.smooth:
        pred = evaluate_params(actor, res.smooth[d], score_cam)
        errs = []
        for side in ("left", "right"):
            use = res.in_view[f"{side}_hand"] & ~res.seen[f"{side}_hand"]
            j = JOINT[f"{side}_wrist"]
            if use.any():
                errs.append(geodesic_deg(pred.rotations[use, j], truth.rotations[use, j]))
        e = np.concatenate(errs) if errs else np.zeros(0)
        out[d] = {"hand_world_deg": float(e.mean()) if len(e) else float("nan"),
                  "frames": int(len(e))}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="runs.pkl files (our own output)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--score-size", type=int, default=320, help="as the runs used (4:3)")
    ap.add_argument("--recompute", action="store_true",
                    help="recompute every metric and the One Euro curve with today's code "
                         "(else the runs' own), and the declined hands' errors")
    args = ap.parse_args()

    from avatar_core.synth.tracking_eval.protocol import run_metrics, temporal_curve
    from avatar_core.synth.tracking_eval.protocol_report import (
        load_runs,
        summarise,
        write_protocol,
    )

    runs = load_runs(args.runs)
    size = (args.score_size, args.score_size * 3 // 4)
    declined = []
    for res in runs if args.recompute else ():
        actor, cam = _score_camera(res.condition, size)
        res.metrics = run_metrics(actor, res, cam)
        if "live" in res.raw:
            res.curve = temporal_curve(actor, res, cam, res.start_frame)
        declined.append({"identity": res.condition.identity, "framing": res.condition.framing,
                         **{d: v for d, v in declined_hands(actor, res, cam).items()}})
    summary = summarise(runs)
    summary["declined_hands"] = declined
    js, md = write_protocol(summary, args.out)
    lines = ["", "Hands the hand model declines (in view, not seen): world rotation error "
             "of the hand (deg), frames:", ""]
    drives = [d for d in declined[0] if isinstance(declined[0][d], dict)] if declined else []
    for d in drives:
        n = sum(r[d]["frames"] for r in declined)
        mean = sum(r[d]["hand_world_deg"] * r[d]["frames"] for r in declined
                   if r[d]["frames"]) / max(n, 1)
        lines.append(f"- all conditions, {d}: {mean:.1f} deg over {n} hand-frames")
    for row in declined:
        lines.append(f"- identity {row['identity']} {row['framing']}: " + "; ".join(
            f"{d} {v['hand_world_deg']:.1f} ({v['frames']})" for d, v in row.items()
            if isinstance(v, dict)))
    with open(md, "a") as f:
        f.write("\n".join(lines) + "\n")
    print(md.read_text())
    print(f"wrote {js}, {md}")


if __name__ == "__main__":
    main()
