"""Hand presence on the studio webcam protocol's frames: ours (the live `Tracker`, tracking
mode, a palm search every `LIVE_PALM_INTERVAL` frames) against MediaPipe's own hand tracking
graph (each frame a fresh start, `bench/track_parity.py`; needs the `mediapipe-parity`
extra).

The frames are `telesplat synth webcam-eval`'s (avatar_core/synth/tracking_eval/protocol.py):
the take `TAKE` per identity and framing, 640x480, JPEG quality 90. A hand counts as present
in a frame when a detected hand's wrist is nearer its true wrist than the other hand's;
rates are over the frames in which all 21 of the hand's true keypoints are inside the image.

    OMP_NUM_THREADS=1 python bench/webcam_hand_presence.py --fps 10    # docs/results.md
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

SIDES = ("left_hand", "right_hand")


def _sides(wrists_px: list[np.ndarray], true_wrists: dict[str, np.ndarray]) -> set[str]:
    found = set()
    for w in wrists_px:
        found.add(min(SIDES, key=lambda s: float(np.linalg.norm(w - true_wrists[s]))))
    return found


def run(identity: int, framing: str, fps: float, max_frames: int | None) -> dict:
    from avatar_core.motion.rig import model_rig
    from avatar_core.synth.actor import Actor
    from avatar_core.synth.model_writer import ensure_models
    from avatar_core.synth.tracking_eval import protocol as wp
    from avatar_core.synth.tracking_eval.metrics import evaluate_params
    from avatar_core.track.fit.observations import from_track_result
    from avatar_core.track.image import decode_image
    from avatar_core.track.tracker import LIVE_PALM_INTERVAL, Tracker

    reference = None
    try:
        from track_parity import reference_available, reference_hands

        if reference_available() is None:
            reference = reference_hands
    except ImportError:
        pass
    files = ensure_models()
    actor = Actor.load(files, identity)
    cam = wp.webcam_camera()
    transl = wp.framed_transl(actor, cam, framing)
    truth = wp.take_params(actor, model_rig(files, actor.model), transl, fps, max_frames)
    posed = evaluate_params(actor, truth, cam)
    in_view = {s: posed.visible[s].all(-1) for s in SIDES}
    bg = wp.background(cam.width, cam.height)
    rng = np.random.default_rng([23, identity, len(framing)])
    tracker = Tracker(threads=1, palm_interval=LIVE_PALM_INTERVAL, iris=True)
    ours = {s: np.zeros(len(truth), bool) for s in SIDES}
    theirs = {s: np.zeros(len(truth), bool) for s in SIDES}
    try:
        for i, params in enumerate(truth):
            frame = wp.render_frame(actor, params, cam, bg, wp.SENSOR_NOISE, rng)
            jpeg = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, wp.JPEG_QUALITY])[1]
            image = decode_image(jpeg.tobytes())
            obs = from_track_result(tracker.track(image))
            for s in SIDES:
                ours[s][i] = bool(obs.seen.get(s))
            if reference is not None:
                true_wrists = {s: posed.uv[s][i, 0] for s in SIDES}
                found = _sides([h["points"][0] for h in reference(image[..., ::-1].copy())],
                               true_wrists)
                for s in found:
                    theirs[s][i] = True
    finally:
        tracker.close()

    def rate(seen):
        return {s: float(seen[s][in_view[s]].mean()) if in_view[s].any() else float("nan")
                for s in SIDES}
    return {"identity": identity, "framing": framing, "frames": len(truth),
            "in_view": {s: float(in_view[s].mean()) for s in SIDES}, "ours": rate(ours),
            "mediapipe": rate(theirs) if reference is not None else None}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--identities", default="0,1")
    ap.add_argument("--framings", default="head_shoulders,waist_up")
    ap.add_argument("--fps", type=float, default=10.0)
    ap.add_argument("--max-frames", type=int, default=None)
    args = ap.parse_args(argv)
    rows = [run(int(i), f, args.fps, args.max_frames) for i in args.identities.split(",")
            for f in args.framings.split(",")]
    pct = lambda x: "-" if x is None or not np.isfinite(x) else f"{100 * x:.0f}%"  # noqa: E731
    print("| identity | framing | frames | left hand in view | ours | MediaPipe | "
          "right hand in view | ours | MediaPipe |")
    print("|---:|---|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        mp = r["mediapipe"] or {}
        print(f"| {r['identity']} | {r['framing']} | {r['frames']} | "
              + " | ".join(f"{pct(r['in_view'][s])} | {pct(r['ours'][s])} | {pct(mp.get(s))}"
                           for s in SIDES) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
