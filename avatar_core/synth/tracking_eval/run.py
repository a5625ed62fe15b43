"""Rendering, tracking and fitting one clip in order."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .metrics import GROUPS, LH, NUM_FACE_HANDS, RH, TJE_SKIP_S, clip_metrics, evaluate_params
from .scene import FOV_X_DEG, Scene, clip_params, render_frame


@dataclass
class ClipResult:
    name: str
    frames: int
    seen: dict[str, np.ndarray]        # group -> [T] bool
    in_view: dict[str, np.ndarray]     # hand -> [T] bool (all true keypoints in the image)
    ms: list[float]                    # tracking + fitting per frame
    track_ms: list[float]
    metrics: dict[str, float] = field(default_factory=dict)
    frames_bgr: list[np.ndarray] = field(default_factory=list)
    fitted_px: list[np.ndarray] = field(default_factory=list)  # fitter layout [K, 2]
    # Per frame, fitter layout [K, 2]: tracked landmark - the true model keypoint (NaN unused)
    offsets: list[np.ndarray] = field(default_factory=list)
    swapped: dict[str, np.ndarray] = field(default_factory=dict)  # hand -> [T] wrong side


# Landmarks that `--ignore` can take out of the fit (fitter-layout rows), for ablations.
IGNORABLE = {"contour": list(range(17)),
             "ears": [NUM_FACE_HANDS + 7, NUM_FACE_HANDS + 8],
             "hips": [NUM_FACE_HANDS + 23, NUM_FACE_HANDS + 24]}


def run_clip(scene: Scene, name: str, tracker, sequence_fit, fps: float,
             max_frames: int | None = None, start: float = 0.0, sensor_noise: float = 2 / 255,
             keep_frames: bool = False, ignore: tuple[str, ...] = (), log=None) -> ClipResult:
    """Render, track and fit one clip in order; `ignore`: landmark classes (`IGNORABLE`)
    given weight 0 in the fit."""
    from avatar_core.track.fit.camera import WebcamCamera
    from avatar_core.track.fit.observations import from_track_result
    from avatar_core.track.fit.synthetic import project_params

    gt = clip_params(scene, name, fps, start, max_frames)
    tracker.reset()
    sequence_fit.reset()
    rng = np.random.default_rng([11, *name.encode()])
    wcam = WebcamCamera(scene.camera.width, scene.camera.height, FOV_X_DEG)
    seen = {g: np.zeros(len(gt), bool) for g in GROUPS}
    raw_params, smooth_params, ms, track_ms = [], [], [], []
    res = ClipResult(name, len(gt), seen, {}, ms, track_ms)
    res.swapped = {g: np.zeros(len(gt), bool) for g in ("left_hand", "right_hand")}
    render_s = 0.0
    for i, params in enumerate(gt):
        r0 = time.perf_counter()
        frame = render_frame(scene.actor, params, scene.camera, scene.bg, sensor_noise, rng)
        render_s += time.perf_counter() - r0
        t0 = time.perf_counter()
        result = tracker.track(frame)
        t1 = time.perf_counter()
        obs = from_track_result(result)
        for cls in ignore:
            obs.weights[IGNORABLE[cls]] = 0.0
        out = sequence_fit.step(obs, i / fps)
        ms.append((time.perf_counter() - t0) * 1e3)
        track_ms.append((t1 - t0) * 1e3)
        for g in GROUPS:
            seen[g][i] = bool(out.seen.get(g))
        raw_params.append({k: np.array(v) for k, v in sequence_fit.current.items()})
        true_px = project_params(sequence_fit.fitter, {k: v for k, v in params.items()
                                                       if k != "betas"}, wcam)
        offset = np.where((obs.weights > 0)[:, None], obs.pixels - true_px, np.nan)
        for side, own, other in (("left_hand", LH, RH), ("right_hand", RH, LH)):
            if seen[side][i]:  # labelled on the wrong side: its wrist is nearer the other's
                wrist = obs.pixels[own]
                res.swapped[side][i] = (np.linalg.norm(wrist - true_px[other])
                                        < np.linalg.norm(wrist - true_px[own]))
                if res.swapped[side][i]:  # the offset table is about landmark definitions
                    offset[own:own + 21] = np.nan
        res.offsets.append(offset)
        smooth_params.append({k: np.array(v) for k, v in out.params.items()})
        if keep_frames:
            res.frames_bgr.append(frame)
            res.fitted_px.append(project_params(sequence_fit.fitter, raw_params[-1], wcam))
    cam = scene.camera
    truth = evaluate_params(scene.actor, gt, cam)
    raw = evaluate_params(scene.actor, raw_params, cam)
    smooth = evaluate_params(scene.actor, smooth_params, cam)
    neutral = evaluate_params(scene.actor, [
        {**p, "expression": np.zeros_like(p["expression"]), "jaw_pose": np.zeros(3)}
        for p in gt], cam)
    res.in_view = {g: truth.visible[g].all(-1) for g in ("left_hand", "right_hand")}
    res.metrics = clip_metrics(truth, raw, smooth, gt, seen, res.in_view, neutral, res.swapped,
                               skip=int(round(TJE_SKIP_S * fps)))
    res.metrics["ms"] = float(np.mean(ms))
    res.metrics["ms_median"] = float(np.median(ms))
    res.metrics["track_ms"] = float(np.mean(track_ms))
    res.metrics["render_s"] = render_s / max(len(gt), 1)
    if log:
        log(f"{name}: {len(gt)} frames, render {res.metrics['render_s']:.2f} s/frame, "
            f"track+fit {res.metrics['ms']:.0f} ms/frame")
    return res


def make_tracker_and_fit(scene: Scene, smoothing: bool = True):
    from avatar_core.gaussians.animate import synthetic_package
    from avatar_core.track.fit.sequence import SequenceFit, SequenceFitConfig
    from avatar_core.track.tracker import Tracker

    tracker = Tracker(threads=1, iris=True)
    package, model = synthetic_package(scene.model_dir, 0)
    sequence_fit = SequenceFit(model, np.asarray(package.body.betas),
                               SequenceFitConfig(fov_x_deg=FOV_X_DEG, smoothing=smoothing))
    return tracker, sequence_fit
