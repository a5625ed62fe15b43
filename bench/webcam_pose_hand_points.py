"""Where BlazePose's hand points (pinky 17/18, index 19/20, thumb 21/22) lie on our hand.

The fitter drives a wrist from these points when the hand landmark model declines a hand
(`observations.POSE_HAND_POINTS`), so each needs a model point. Studio frames of identities
the webcam protocol does not score (the embedding family's 2-5) playing hand clips at three
yaws are tracked by the live tracker; each tracked point is compared with the candidate model
points (each finger's three joints and its tip vertex) projected at the true parameters.
Median px error per candidate, over the frames where BlazePose gives the point visibility
>= 0.5 and the candidate is inside the image; the nearest is the point's meaning. BlazePose's
wrists against the wrist joints are the reference for how far its arm points are off.

    PYTHONPATH=. python bench/webcam_pose_hand_points.py --out bench_hand_points.json
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from avatar_core.body.skeleton import JOINT
from avatar_core.track.fit import correspondence as cor

POINTS = {15: ("left", "wrist"), 16: ("right", "wrist"), 17: ("left", "pinky"),
          18: ("right", "pinky"), 19: ("left", "index"), 20: ("right", "index"),
          21: ("left", "thumb"), 22: ("right", "thumb")}


def candidates(side: str, finger: str) -> list[str]:
    if finger == "wrist":  # the reference: BlazePose's own wrist against the wrist joint
        return [f"joint:{side}_wrist"]
    return [f"joint:{side}_{finger}{i}" for i in (1, 2, 3)] + [f"vertex:{side[0]}{finger}"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--identities", default="2,3,4,5")
    ap.add_argument("--clips", default="thumbs_up,peace,pointing,heart,wave")
    ap.add_argument("--yaws", default="-30,0,30")
    ap.add_argument("--frames", type=int, default=2, help="random instants per clip and yaw")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()

    from avatar_core.motion.library import motion_sequence
    from avatar_core.motion.rig import model_rig
    from avatar_core.synth.actor import Actor
    from avatar_core.synth.embedding_build import _family
    from avatar_core.synth.model_writer import BodyModelFiles
    from avatar_core.synth.tracking_eval.scene import (
        background,
        render_frame,
        subject_transl,
        webcam_camera,
    )
    from avatar_core.track.fit.camera import WebcamCamera
    from avatar_core.track.tracker import Tracker

    identities = [int(x) for x in args.identities.split(",")]
    root = _family(max(identities) + 1, None)
    files = BodyModelFiles(root)
    cam = webcam_camera()
    wcam = WebcamCamera(cam.width, cam.height, 60.0)
    tracker = Tracker(threads=1, iris=False)
    errors: dict[int, dict[str, list[float]]] = {
        k: {c: [] for c in candidates(*v)} for k, v in POINTS.items()}
    frames = 0
    for identity in identities:
        actor = Actor.load(files, identity)
        rig = model_rig(files, actor.model)
        bg = background(cam.width, cam.height, "noise", seed=7 + identity)
        transl = subject_transl(actor, cam)
        for clip in args.clips.split(","):
            track = motion_sequence([clip])
            for yaw in (float(y) for y in args.yaws.split(",")):
                rng = np.random.default_rng([args.seed, identity, *clip.encode(), int(yaw) + 360])
                for _ in range(args.frames):
                    p = track.sample(float(rng.uniform(0.15, 0.85)) * track.duration, rig)
                    turn = Rotation.from_rotvec([0.0, math.radians(yaw), 0.0])
                    p["global_orient"] = (turn * Rotation.from_rotvec(p["global_orient"])
                                          ).as_rotvec()
                    p["transl"] = transl
                    tracker.reset()
                    posed = actor.pose(p)
                    result = tracker.track(render_frame(actor, p, cam, bg, 2 / 255, rng))
                    frames += 1
                    if result.pose is None:
                        continue
                    for k, names in errors.items():
                        if result.pose.visibility[k] < 0.5:
                            continue
                        for name in names:
                            kind, key = name.split(":")
                            point = posed.joints[JOINT[key]] if kind == "joint" else \
                                posed.body_vertices[cor.SMPLX_SEMANTIC_VERTEX_IDS[key]]
                            px = wcam.project(torch.as_tensor(point)).numpy()
                            if not (0 <= px[0] < wcam.width and 0 <= px[1] < wcam.height):
                                continue
                            names[name].append(float(np.linalg.norm(
                                px - result.pose.points[k, :2])))
    tracker.close()
    report = {"frames": frames, "points": {}}
    for k, names in errors.items():
        med = {n: float(np.median(v)) if v else float("nan") for n, v in names.items()}
        best = min(med, key=lambda n: med[n] if np.isfinite(med[n]) else np.inf)
        seen = max(len(v) for v in names.values())
        report["points"][k] = {"seen": seen, "median_px": med, "nearest": best}
        print(k, POINTS[k], seen, "frames;",
              ", ".join(f"{n.split(':')[1]} {v:.1f}" for n, v in med.items()), "->", best)
    if args.out:
        with open(args.out, "w") as f:
            json.dump(report, f, indent=1)


if __name__ == "__main__":
    main()
