"""Joint-angle errors of the webcam fit with and without the learned landmark embedding and
the 3D cues, on studio frames of identities and clips the embedding never saw.

Input: the samples `telesplat track build-embedding --samples S.npz` writes (each held-out
frame's tracked landmarks, BlazePose world landmarks and true parameters). Each frame is
fitted cold and refined once warm (a still subject's second frame), per configuration, side
by side in one run. The weights of the 3D cues are chosen on one held-out identity (`--tune`)
and reported on the others.

    PYTHONPATH=. python bench/webcam_embedding.py --samples S.npz \
        --embedding avatar_core/track/fit/assets/landmark_embedding.npz
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from avatar_core.body.skeleton import JOINT
from avatar_core.gaussians.animate import synthetic_package
from avatar_core.track.fit import correspondence as cor
from avatar_core.track.fit.camera import WebcamCamera
from avatar_core.track.fit.embedding import load_embedding
from avatar_core.track.fit.fitter import FitConfig, FrameFitter
from avatar_core.track.fit.observations import MIN_POINTS, MISMATCHED_ROWS, Observations

CAMERA = WebcamCamera(640, 480, 60.0)
PARTS = {"root": ("pelvis",), "shoulders": ("left_shoulder", "right_shoulder"),
         "elbows": ("left_elbow", "right_elbow"), "neck/head": ("head",)}


def observations(arrays: dict, i: int) -> Observations:
    w = np.array(arrays["held_weights"][i], dtype=np.float64)
    w[MISMATCHED_ROWS] = 0.0  # as the live path (`from_track_result`)
    seen = {g: int((w[sl] > 0).sum()) >= MIN_POINTS[g] for g, sl in cor.GROUP_SLICES.items()}
    world = arrays["held_world"][i]
    return Observations(np.array(arrays["held_pixels"][i]), w, (CAMERA.width, CAMERA.height),
                        seen, np.array(arrays["held_image_z"][i]),
                        world=None if not np.isfinite(world).any() else np.array(world))


def angle_errors(fitter: FrameFitter, x_fit: np.ndarray, x_true: np.ndarray) -> dict:
    a = fitter.kinematics.world_rotations(fitter.full_pose(x_fit))
    b = fitter.kinematics.world_rotations(fitter.full_pose(x_true))
    out = {}
    for part, joints in PARTS.items():
        errs = []
        for j in joints:
            r = a[JOINT[j]].T @ b[JOINT[j]]
            errs.append(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))))
        out[part] = float(np.mean(errs))
    return out


def run(arrays: dict, family: str, configs: dict, frames: np.ndarray) -> dict:
    identity = np.array([int(str(lab).split(":")[0]) for lab in arrays["held_label"]])
    rows = {name: {"angles": [], "ms": []} for name in configs}
    for ident in sorted(set(identity[frames])):
        package, model = synthetic_package(family, int(ident))
        betas = np.asarray(package.body.betas)
        fitters = {name: FrameFitter(model, betas, cfg) for name, cfg in configs.items()}
        for i in frames[identity[frames] == ident]:
            obs = observations(arrays, i)
            for name, fitter in fitters.items():
                x_true = arrays["held_params"][i]
                t0 = time.perf_counter()
                cold = fitter.fit(obs, CAMERA)
                fit = fitter.fit(obs, CAMERA, start=cold.params)
                rows[name]["ms"].append((time.perf_counter() - t0) * 1e3 / 2)
                rows[name]["angles"].append(angle_errors(fitter, fitter.pack(fit.params),
                                                         x_true))
    out = {}
    for name, r in rows.items():
        out[name] = {p: float(np.mean([a[p] for a in r["angles"]])) for p in PARTS}
        out[name]["fit_ms_median"] = float(np.median(r["ms"]))
        out[name]["frames"] = len(r["ms"])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--samples", required=True)
    ap.add_argument("--embedding", required=True)
    ap.add_argument("--tune", type=int, default=1, help="held-out identity to set weights on")
    ap.add_argument("--weights", type=float, nargs="+", default=[0.1, 0.3, 1.0, 3.0])
    ap.add_argument("--out", default=None, help="JSON of the results")
    ap.add_argument("--fixed-world", type=float, nargs="+", default=None,
                    help="no sweep: these world weights, with --image-z-weight, on --tune's "
                         "complement (or on --tune itself with --on-tune)")
    ap.add_argument("--image-z-weight", type=float, default=0.0)
    ap.add_argument("--on-tune", action="store_true")
    ap.add_argument("--stride", type=int, default=1, help="every K-th held-out frame")
    args = ap.parse_args()
    with np.load(args.samples) as raw:
        arrays = {k: raw[k] for k in raw.files}
    family = str(arrays["family"])
    emb = load_embedding(args.embedding)
    identity = np.array([int(str(lab).split(":")[0]) for lab in arrays["held_label"]])
    tune, report = np.flatnonzero(identity == args.tune), np.flatnonzero(identity != args.tune)
    tune, report = tune[::args.stride], report[::args.stride]
    if args.fixed_world is not None:
        zw = args.image_z_weight
        final = {f"embedding+world {w:g}+image_z {zw:g}": FitConfig(
            embedding=emb, world_weight=w, image_z_weight=zw) for w in args.fixed_world}
        report_table(run(arrays, family, final, tune if args.on_tune else report), args.out,
                     {"world_weights": args.fixed_world, "stride": args.stride})
        return
    sweep = {"today": FitConfig(), "embedding": FitConfig(embedding=emb)}
    for w in args.weights:
        sweep[f"embedding+world {w:g}"] = FitConfig(embedding=emb, world_weight=w)
        sweep[f"embedding+image_z {w:g}"] = FitConfig(embedding=emb, image_z_weight=w)
    tuned = run(arrays, family, sweep, tune)

    def score(r: dict) -> float:
        return r["root"] + r["shoulders"] + r["elbows"] + r["neck/head"]

    best_world = min(args.weights, key=lambda w: score(tuned[f"embedding+world {w:g}"]))
    best_z = min(args.weights, key=lambda w: score(tuned[f"embedding+image_z {w:g}"]))
    final = {"today": FitConfig(), "embedding": FitConfig(embedding=emb),
             "embedding+world": FitConfig(embedding=emb, world_weight=best_world),
             "embedding+world+image_z": FitConfig(embedding=emb, world_weight=best_world,
                                                  image_z_weight=best_z),
             "world only": FitConfig(world_weight=best_world)}
    print(f"weights set on identity {args.tune}: world {best_world:g}, image z {best_z:g}")
    report_table(run(arrays, family, final, report), args.out, {
        "tune_identity": args.tune, "tuned": tuned, "world_weight": best_world,
        "image_z_weight": best_z})


def report_table(reported: dict, out: str | None, extra: dict) -> None:
    print("| fit | root deg | shoulders deg | elbows deg | neck/head deg | fit ms/frame |")
    print("|---|---:|---:|---:|---:|---:|")
    for name, r in reported.items():
        print(f"| {name} | {r['root']:.1f} | {r['shoulders']:.1f} | {r['elbows']:.1f} | "
              f"{r['neck/head']:.1f} | {r['fit_ms_median']:.1f} |")
    if out:
        with open(out, "w") as fh:
            json.dump({**extra, "reported": reported}, fh, indent=1)


if __name__ == "__main__":
    main()
