"""Hand tracking quality on renders with known parameters, with the landmarks recorded once.

The landmark models' output does not depend on the fit, so the renders are tracked once
(`--record`) and the fit is replayed on the recorded observations (`--replay`) for each
fitter variant; same frames, same landmarks, side by side:

    OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python bench/track_hands.py --record obs.npz
    OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python bench/track_hands.py --replay obs.npz \
        [--variants base,orient] [--json out.json]

The metrics are `avatar_core.synth.tracking_eval`'s (bench/track_eval.py); the default clips
are the five with hands in view. `fit ms` is `SequenceFit.step` alone per frame (median).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from avatar_core.synth.tracking_eval import (  # noqa: E402
    FOV_X_DEG,
    GROUPS,
    LH,
    RH,
    TJE_SKIP_S,
    clip_metrics,
    clip_params,
    evaluate_params,
    make_scene,
    render_frame,
)
from avatar_core.track.fit.observations import Observations  # noqa: E402

HAND_CLIPS = ("thumbs_up", "peace", "heart", "clapping", "talk_animated")
OBS_FIELDS = ("pixels", "weights", "depth")


def record(path: Path, clips: list[str], fps: float, log) -> None:
    from avatar_core.track.fit.observations import from_track_result
    from avatar_core.track.tracker import Tracker

    scene = make_scene("noise")
    tracker = Tracker(threads=1, iris=True)
    out: dict[str, np.ndarray] = {}
    for name in clips:
        gt = clip_params(scene, name, fps)
        tracker.reset()
        rng = np.random.default_rng([11, *name.encode()])  # run_clip's sensor noise
        rows: dict[str, list] = {k: [] for k in (*OBS_FIELDS, "seen", "iris")}
        for params in gt:
            frame = render_frame(scene.actor, params, scene.camera, scene.bg, 2 / 255, rng)
            obs = from_track_result(tracker.track(frame))
            for k in OBS_FIELDS:
                rows[k].append(getattr(obs, k))
            rows["seen"].append([bool(obs.seen.get(g)) for g in GROUPS])
            rows["iris"].append(np.full((2, 2), np.nan) if obs.iris is None else obs.iris)
        for k, v in rows.items():
            out[f"{name}/{k}"] = np.asarray(v)
        log(f"recorded {name}: {len(gt)} frames")
    out["clips"] = np.asarray(clips)
    out["fps"] = np.asarray(fps)
    np.savez_compressed(path, **out)


def _observations(data, name: str, i: int, size: tuple[int, int]) -> Observations:
    iris = data[f"{name}/iris"][i]
    return Observations(data[f"{name}/pixels"][i].copy(), data[f"{name}/weights"][i].copy(),
                        size, dict(zip(GROUPS, map(bool, data[f"{name}/seen"][i]), strict=True)),
                        data[f"{name}/depth"][i].copy(),
                        None if np.isnan(iris).all() else iris.copy())


def replay_clip(scene, data, name: str, sequence_fit, fps: float) -> dict[str, float]:
    from avatar_core.track.fit.camera import WebcamCamera
    from avatar_core.track.fit.synthetic import project_params

    gt = clip_params(scene, name, fps)
    wcam = WebcamCamera(scene.camera.width, scene.camera.height, FOV_X_DEG)
    size = (scene.camera.width, scene.camera.height)
    sequence_fit.reset()
    seen = {g: np.zeros(len(gt), bool) for g in GROUPS}
    swapped = {g: np.zeros(len(gt), bool) for g in ("left_hand", "right_hand")}
    raw, smooth, ms = [], [], []
    for i, params in enumerate(gt):
        obs = _observations(data, name, i, size)
        t0 = time.perf_counter()
        out = sequence_fit.step(obs, i / fps)
        ms.append((time.perf_counter() - t0) * 1e3)
        for g in GROUPS:
            seen[g][i] = bool(out.seen.get(g))
        true_px = project_params(sequence_fit.fitter, {k: v for k, v in params.items()
                                                       if k != "betas"}, wcam)
        for side, own, other in (("left_hand", LH, RH), ("right_hand", RH, LH)):
            if seen[side][i]:
                wrist = obs.pixels[own]
                swapped[side][i] = (np.linalg.norm(wrist - true_px[other])
                                    < np.linalg.norm(wrist - true_px[own]))
        raw.append({k: np.array(v) for k, v in sequence_fit.current.items()})
        smooth.append({k: np.array(v) for k, v in out.params.items()})
    cam = scene.camera
    truth = evaluate_params(scene.actor, gt, cam)
    neutral = evaluate_params(scene.actor, [
        {**p, "expression": np.zeros_like(p["expression"]), "jaw_pose": np.zeros(3)}
        for p in gt], cam)
    in_view = {g: truth.visible[g].all(-1) for g in ("left_hand", "right_hand")}
    m = clip_metrics(truth, evaluate_params(scene.actor, raw, cam),
                     evaluate_params(scene.actor, smooth, cam), gt, seen, in_view, neutral,
                     swapped, skip=int(round(TJE_SKIP_S * fps)))
    m["fit_ms_median"] = float(np.median(ms))
    m["frames"] = len(gt)
    return m


def timing(scene, data, model, betas, configs, names, clips, fps, rounds, log) -> None:
    """`SequenceFit.step` per frame, the variants interleaved clip by clip for `rounds`
    rounds (the machine's load shifts evenly on all): median and p90 ms, the ratio to the
    first variant, and how many frames ran a palm retry."""
    from avatar_core.track.fit.sequence import SequenceFit

    size = (scene.camera.width, scene.camera.height)
    fits = {v: SequenceFit(model, betas, configs[v]) for v in names}
    times = {v: [] for v in names}
    retried = {v: 0 for v in names}
    for _ in range(rounds):
        for c in clips:
            n = len(data[f"{c}/seen"])
            for v in names:
                fits[v].reset()
                for i in range(n):
                    obs = _observations(data, c, i, size)
                    t0 = time.perf_counter()
                    out = fits[v].step(obs, i / fps)
                    times[v].append((time.perf_counter() - t0) * 1e3)
                    retried[v] += bool(out.fit is not None and out.fit.stats.get("palm_retries"))
    first = statistics.median(times[names[0]])
    print("\n| variant | fit ms / frame (median) | p90 | vs first | frames with a palm retry |")
    print("|---|---:|---:|---:|---:|")
    for v in names:
        med = statistics.median(times[v])
        p90 = float(np.percentile(times[v], 90))
        print(f"| {v} | {med:.1f} | {p90:.1f} | {med / first:.2f}x | "
              f"{100 * retried[v] / len(times[v]):.1f}% |")
    log(f"timing: {rounds} rounds, {len(times[names[0]])} frames per variant")


def _weighted(per_clip: dict[str, dict[str, float]], key: str, weight: str) -> float:
    num = den = 0.0
    for m in per_clip.values():
        v, w = m.get(key, float("nan")), m.get(weight, 0)
        if np.isfinite(v) and w:
            num, den = num + v * w, den + w
    return num / den if den else float("nan")


def summary(per_clip: dict[str, dict[str, float]]) -> dict[str, float]:
    """Frame-weighted over clips: AKD by the frames each hand was detected, angles by
    frames (as `tracking_eval.overall`, approximately: angles there weigh detected hands)."""
    return {"akd_left_hand": _weighted(per_clip, "akd_left_hand", "akd_n_left_hand"),
            "akd_right_hand": _weighted(per_clip, "akd_right_hand", "akd_n_right_hand"),
            "wrist_deg": _weighted(per_clip, "wrist_deg", "frames"),
            "finger_deg": _weighted(per_clip, "finger_deg", "frames"),
            "akd_torso": _weighted(per_clip, "akd_torso", "frames"),
            "tje_raw": _weighted(per_clip, "tje_raw", "frames"),
            "tje_smooth": _weighted(per_clip, "tje_smooth", "frames"),
            "fit_ms_median": _weighted(per_clip, "fit_ms_median", "frames")}


def variant_configs():
    """Named `SequenceFitConfig`s compared by `--replay`."""
    from avatar_core.track.fit.sequence import SequenceFitConfig

    base = SequenceFitConfig(fov_x_deg=FOV_X_DEG)

    def fit(**kw):
        return replace(base, fit=replace(base.fit, **kw))

    # "base": the fit before issue 18 (no palm retry, no hinge prior, hand prior 0.3);
    # "default": today's FitConfig; the rest change one thing against one of them.
    return {"base": fit(palm_retry_deg=180.0, finger_hinge_weight=0.0, hand_prior=0.3),
            "hinge": fit(palm_retry_deg=180.0, hand_prior=0.3),
            "palm": fit(finger_hinge_weight=0.0, hand_prior=0.3),
            "palm+hinge": fit(hand_prior=0.3),
            "default": fit(),
            "default, palm 45": fit(palm_retry_deg=45.0),
            "default, hinge 3": fit(finger_hinge_weight=3.0),
            "default, prior 0.6": fit(hand_prior=0.6),
            "default, depth 0.02": fit(hand_depth_weight=0.02)}, replace


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--record", type=Path)
    parser.add_argument("--replay", type=Path)
    parser.add_argument("--clips", default=",".join(HAND_CLIPS))
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--variants", default=None,
                        help="separated by ; (default: all)")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--timing-rounds", type=int, default=0,
                        help="instead of the metrics: per-frame fit time, variants interleaved")
    args = parser.parse_args()
    torch.set_num_threads(1)
    log = lambda msg: print(msg, file=sys.stderr, flush=True)  # noqa: E731
    clips = [c.strip() for c in args.clips.split(",") if c.strip()]
    if args.record:
        record(args.record, clips, args.fps, log)
        return
    if not args.replay:
        parser.error("give --record PATH or --replay PATH")
    from avatar_core.gaussians.animate import synthetic_package
    from avatar_core.track.fit.sequence import SequenceFit

    data = np.load(args.replay)
    fps = float(data["fps"])
    scene = make_scene("noise")
    package, model = synthetic_package(scene.model_dir, 0)
    configs, _ = variant_configs()
    names = list(configs) if args.variants is None else args.variants.split(";")
    if args.timing_rounds > 0:
        timing(scene, data, model, np.asarray(package.body.betas), configs, names, clips, fps,
               args.timing_rounds, log)
        return
    results = {}
    print("| variant | AKD L / R hand px | wrist deg | fingers deg | AKD torso px | "
          "TJE raw / One Euro px | fit ms (median) |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for v in names:
        fit = SequenceFit(model, np.asarray(package.body.betas), configs[v])
        per_clip = {c: replay_clip(scene, data, c, fit, fps) for c in clips}
        s = summary(per_clip)
        results[v] = {"summary": s, "clips": per_clip}
        print(f"| {v} | {s['akd_left_hand']:.1f} / {s['akd_right_hand']:.1f} | "
              f"{s['wrist_deg']:.1f} | {s['finger_deg']:.1f} | {s['akd_torso']:.1f} | "
              f"{s['tje_raw']:.2f} / {s['tje_smooth']:.2f} | {s['fit_ms_median']:.1f} |",
              flush=True)
        for c, m in per_clip.items():
            log(f"  {v} {c}: AKD {m['akd_left_hand']:.1f} / {m['akd_right_hand']:.1f}, "
                f"wrist {m['wrist_deg']:.1f}, fingers {m['finger_deg']:.1f}")
    log(f"load average after: {os.getloadavg()[0]:.2f}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
