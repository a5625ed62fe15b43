"""Gaze on renders with known eye rotations: the textured synthetic actor looks in known
directions; `Tracker(iris=True)`, the body fit and `fit_gaze` recover them.

    OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python bench/track_gaze.py [--frames 10] [--scale 2]

The scene is `synth.tracking_eval`'s (identity 0, 640x480 webcam with a 60 deg field of view, the
subject 1.09 m away, noisy background, 2/255 sensor noise); the body holds the first pose of
the "smile" clip while the eyes turn through `LOOKS`, one frame each, in order through one
`Tracker` and one `SequenceFit`. Reported, in degrees (geodesic): the eye rotations fitted on
the true body (the gaze solver and the iris model alone) for a shared gaze and per eye, with
the iris centre at `IRIS_DEPTH` and, for comparison, on the eyeball's front pole; and, on the
fitted body (the whole path), the eye rotations and the gaze direction in the world (the
head's fitted rotation error then moves into the eye rotations). Also the tracked iris
centre's distance (px) from the model's. `--scale 2` renders at 1280x960 (same field of view
and placement: the eyes twice as many pixels wide).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from avatar_core.synth.tracking_eval import (  # noqa: E402
    FOV_X_DEG,
    HEIGHT,
    WIDTH,
    aa_to_matrix,
    background,
    clip_params,
    geodesic_deg,
    make_scene,
    render_frame,
    webcam_camera,
)

# (pitch, yaw) deg: +yaw looks to the person's left, +pitch down.
LOOKS = ((0, 0), (0, 15), (0, -15), (-10, 0), (10, 0), (-10, 15), (10, -15), (-5, 25),
         (5, -25), (0, 0))


def eye_world_rotations(model, params: dict, betas: np.ndarray) -> np.ndarray:
    """[2, 3, 3] world rotation of the right and left eye joints (a float64 `model`)."""
    from avatar_core.body import lbs
    from avatar_core.track.fit import gaze

    p = {k: torch.as_tensor(np.asarray(v, dtype=np.float64))[None] for k, v in params.items()
         if k not in ("betas", "vertex_offsets")}
    p["betas"] = torch.as_tensor(np.asarray(betas, dtype=np.float64))[None]
    with torch.no_grad():
        pose = model(p).full_pose
        world = lbs.global_rotations(lbs.rodrigues(pose), model.parents)[0].numpy()
    return world[[gaze.EYE_JOINT[e] for e in gaze.EYES]]


def main() -> None:
    from avatar_core.gaussians.animate import synthetic_package
    from avatar_core.track.fit import gaze
    from avatar_core.track.fit.camera import WebcamCamera
    from avatar_core.track.fit.observations import from_track_result
    from avatar_core.track.fit.sequence import SequenceFit, SequenceFitConfig
    from avatar_core.track.tracker import Tracker

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=len(LOOKS))
    parser.add_argument("--scale", type=int, default=1, help="render resolution multiplier")
    args = parser.parse_args()
    torch.set_num_threads(1)
    scene = make_scene()
    if args.scale != 1:
        size = (WIDTH * args.scale, HEIGHT * args.scale)
        scene = dataclasses.replace(scene, camera=webcam_camera(*size), bg=background(*size))
    package, model = synthetic_package(scene.model_dir, 0)
    betas = np.asarray(package.body.betas)
    tracker = Tracker(threads=1, hands=False, iris=True)
    sequence_fit = SequenceFit(model, betas,
                               SequenceFitConfig(fov_x_deg=FOV_X_DEG, smoothing=False))
    camera = WebcamCamera(scene.camera.width, scene.camera.height, FOV_X_DEG)
    model64 = synthetic_package(scene.model_dir, 0)[1].double()
    solvers = {"iris plane": gaze.GazeSolver(model), "front pole": gaze.GazeSolver(model, 1.0)}
    base = clip_params(scene, "smile", 30.0, max_frames=1)[0]
    rng = np.random.default_rng(3)
    rows, iris_ms, gaze_ms = [], [], []
    for i, (pitch, yaw) in enumerate(LOOKS[:args.frames]):
        look = np.radians([pitch, yaw, 0.0])
        truth = dict(base, leye_pose=look, reye_pose=look)
        frame = render_frame(scene.actor, truth, scene.camera, scene.bg, 2 / 255, rng)
        result = tracker.track(frame)
        fitted = sequence_fit.step(from_track_result(result), i / 30.0).params
        face = result.face
        if face is None or face.iris is None:
            print(f"({pitch}, {yaw}): no iris", file=sys.stderr)
            continue
        iris_ms.append(result.timings_ms["iris"])
        px = face.iris[:, 0, :2]
        eyes = solvers["iris plane"].eyes(truth, betas)
        model_px = camera.project(torch.as_tensor(np.stack(
            [eyes[e].iris(look[:2]) for e in gaze.EYES]))).numpy()
        row = {"look": (pitch, yaw), "iris_px": np.linalg.norm(px - model_px, axis=1).mean()}
        for name, solver in solvers.items():
            for shared in (True, False):
                fit = solver.fit(truth, px, camera, betas, shared=shared)
                row[name, shared] = np.mean([geodesic_deg(aa_to_matrix(fit.params[k]),
                                                          aa_to_matrix(look))
                                             for k in ("reye_pose", "leye_pose")])
        t0 = time.perf_counter()
        fit = solvers["iris plane"].fit(fitted, px, camera, betas)
        gaze_ms.append((time.perf_counter() - t0) * 1e3)
        row["fitted body, eyes"] = np.mean([geodesic_deg(aa_to_matrix(fit.params[k]),
                                                         aa_to_matrix(look))
                                            for k in ("reye_pose", "leye_pose")])
        world_fit = eye_world_rotations(model64, {**fitted, **fit.params}, betas)[..., 2]
        world_true = eye_world_rotations(model64, truth, betas)[..., 2]  # the gaze axes (+z)
        cos = np.clip(np.sum(world_fit * world_true, axis=1), -1.0, 1.0)
        row["fitted body, world gaze"] = float(np.degrees(np.arccos(cos)).mean())
        rows.append(row)
        print(f"({pitch}, {yaw}): " + ", ".join(f"{k}: {v:.2f}" for k, v in row.items()
                                                if k != "look"), file=sys.stderr, flush=True)
    keys = [k for k in rows[0] if k != "look"]
    names = {("iris plane", True): "shared", ("iris plane", False): "per eye",
             ("front pole", True): "shared, front pole",
             ("front pole", False): "per eye, front pole"}
    print("| look (pitch, yaw) | " + " | ".join(names.get(k, k) for k in keys) + " |")
    print("|---|" + "---:|" * len(keys))
    for r in rows + [{"look": "**mean**", **{k: np.mean([r[k] for r in rows]) for k in keys}}]:
        print(f"| {r['look']} | " + " | ".join(f"{r[k]:.1f}" for k in keys) + " |")
    print(f"\niris stage {np.median(iris_ms):.1f} ms (median), fit_gaze "
          f"{np.median(gaze_ms):.1f} ms; IRIS_DEPTH {gaze.IRIS_DEPTH:.3f}; "
          f"eye limit {gaze.EYE_LIMIT_DEG:.0f} deg")


if __name__ == "__main__":
    main()
