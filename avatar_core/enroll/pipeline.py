"""Enrollment end to end: frames -> selection -> tracking -> refusals -> shape fit -> dataset
-> training -> avatar package. ``prepare`` does everything before anything is written (so a
refused take stores nothing); ``train_prepared`` writes and trains; ``enroll`` is both."""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .checks import check_length, check_people, check_turn
from .config import EnrollConfig
from .errors import EnrollmentRefused
from .result import EnrollResult, FrameCounts
from .selection import select_frames
from .shape_fit import fit_shape
from .tracking import TakeTracker, load_body, track_take, yaw_deg
from .video import read_video

Progress = Callable[[str, float], None]
DEFAULT_FOV_X_DEG = 60.0   # the focal prior without metadata: a typical webcam / phone


@dataclass
class PreparedTake:
    frames: list[np.ndarray]                 # the used frames, RGB at the video's size
    indices: list[int]                       # their index in the video
    masks: list[np.ndarray] | None           # person probability per used frame
    params: list[dict[str, np.ndarray]]      # per used frame, after the shape fit
    betas: np.ndarray
    fps: float
    focal_px: float                          # at the video's size
    focal_source: str
    counts: FrameCounts
    yaw_range_deg: float
    files: Any                               # BodyModelFiles
    num_expression: int
    timings: dict[str, float] = field(default_factory=dict)
    fit_px: tuple[float, float] = (0.0, 0.0)  # mean reprojection before / after the shape fit


def _check_frames(frames: Sequence[np.ndarray]) -> None:
    if not len(frames):
        raise EnrollmentRefused("too_short", "The video has no frames.",
                                "Record 20-60 s of yourself turning slowly.")
    shape = frames[0].shape
    for f in frames:
        if not (isinstance(f, np.ndarray) and f.dtype == np.uint8 and f.ndim == 3
                and f.shape[2] == 3 and f.shape == shape):
            raise ValueError("frames must be uint8 [H, W, 3] RGB arrays of one size")


def _even(items: Sequence[int], n: int) -> list[int]:
    if len(items) <= n:
        return list(items)
    return [items[i] for i in np.linspace(0, len(items) - 1, n).round().astype(int)]


def prepare(frames: Sequence[np.ndarray], fps: float, *, config: EnrollConfig,
            focal_px: float | None = None, progress: Progress | None = None,
            body_models: str | Path | None = None, models=None) -> PreparedTake:
    """Everything before anything is written; raises EnrollmentRefused for a bad take."""
    say = progress or (lambda _stage, _f: None)
    _check_frames(frames)
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be > 0, got {fps}")
    if focal_px is not None and not (math.isfinite(focal_px) and focal_px > 0):
        raise ValueError(f"focal_px must be > 0, got {focal_px}")
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    counts = FrameCounts(total=len(frames))
    check_length(len(frames), len(frames), config)
    kept, dropped, _ = select_frames(frames, config)
    counts.blurred, counts.duplicate = dropped["blurred"], dropped["duplicate"]
    check_length(len(kept), len(frames), config)
    # at most max_frames are tracked (evenly spread): tracking costs ~1 s a frame on 2 cores
    tracked = _even(kept, config.max_frames)
    counts.subsampled = len(kept) - len(tracked)
    kept = tracked
    say("select", 1.0)
    h, w = frames[0].shape[:2]
    source = "metadata" if focal_px is not None else "prior+fit"
    focal = focal_px or 0.5 * w / math.tan(math.radians(DEFAULT_FOV_X_DEG) / 2)
    files, model = load_body(body_models)
    timings["select_s"] = time.perf_counter() - t0

    tt = TakeTracker(models)
    try:
        t0 = time.perf_counter()
        if config.preflight_frames:
            sample = _even(kept, config.preflight_frames)
            pre = track_take(frames, sample, fps, model, focal, config.track_size, False, tt,
                             progress=lambda f: say("preflight", f))
            check_people(len(pre.frames), len(sample), pre.faces)
        timings["preflight_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        take = track_take(frames, kept, fps, model, focal, config.track_size, config.masks,
                          tt, progress=lambda f: say("track", f))
        timings["track_s"] = time.perf_counter() - t0
    finally:
        tt.close()
    counts.failed_track = len(take.failed)
    check_people(len(take.frames), len(kept), take.faces)
    check_length(len(take.frames), len(frames), config)
    use = list(range(len(take.frames)))
    counts.used = len(use)
    yaw_range = check_turn(
        [yaw_deg(take.params[j]["global_orient"]) for j in use], config)

    t0 = time.perf_counter()
    fitted = fit_shape(model, [take.params[j] for j in use],
                       [take.observations[j] for j in use], take.size, focal * take.scale,
                       fit_focal=focal_px is None, iterations=config.fit_iterations,
                       progress=lambda f: say("fit", f))
    timings["fit_s"] = time.perf_counter() - t0
    return PreparedTake(
        frames=[frames[take.frames[j]] for j in use], indices=[take.frames[j] for j in use],
        masks=[take.masks[j] for j in use] if config.masks else None,
        params=fitted.params, betas=fitted.betas, fps=fps,
        focal_px=fitted.focal_px / take.scale, focal_source=source, counts=counts,
        yaw_range_deg=yaw_range, files=files, num_expression=model.num_expression,
        timings=timings, fit_px=(fitted.reprojection_px_before, fitted.reprojection_px))


def train_prepared(prep: PreparedTake, out_dir: str | Path, *, config: EnrollConfig,
                   progress: Progress | None = None,
                   body_models: str | Path | None = None) -> EnrollResult:
    """Write the one-camera dataset under ``out_dir/dataset`` and train into ``out_dir``
    (the avatar package: ``out_dir/avatar``; the summary: ``out_dir/enroll.json``)."""
    from .dataset import write_take
    from .training import enroll_train_config, train_take

    say = progress or (lambda _stage, _f: None)
    out = Path(out_dir)
    if (out / "avatar").exists() or (out / "dataset").exists():
        raise ValueError(f"{out} already holds an enrollment: give another --out folder")
    out.mkdir(parents=True, exist_ok=True)
    timings = dict(prep.timings)
    t0 = time.perf_counter()
    dataset = write_take(out / "dataset", prep.frames, prep.masks, prep.params, prep.betas,
                         prep.fps, prep.focal_px, config.resolution, prep.files,
                         prep.num_expression)
    timings["dataset_s"] = time.perf_counter() - t0
    say("dataset", 1.0)
    train_config = enroll_train_config(config, len(prep.frames))
    total = train_config.iterations

    def on_event(event: dict[str, Any]) -> None:
        say("train", min(1.0, event.get("iteration", 0) / total))

    t0 = time.perf_counter()
    package, stats = train_take(dataset, out, train_config, body_models, on_event)
    timings["train_s"] = time.perf_counter() - t0
    result = EnrollResult(
        package=Path(package), frames=prep.counts, betas=[float(b) for b in prep.betas],
        focal_px=float(prep.focal_px), focal_source=prep.focal_source,
        yaw_range_deg=round(prep.yaw_range_deg, 2), train=stats,
        timings={k: round(v, 3) for k, v in timings.items()})
    doc = result.to_dict()
    doc["fit_reprojection_px"] = {"before": prep.fit_px[0], "after": prep.fit_px[1]}
    (out / "enroll.json").write_text(json.dumps(doc, indent=1) + "\n")
    say("done", 1.0)
    return result


def enroll(frames: Sequence[np.ndarray], fps: float, out_dir: str | Path, *,
           config: EnrollConfig, focal_px: float | None = None,
           progress: Progress | None = None, body_models: str | Path | None = None,
           models=None) -> EnrollResult:
    """One video's frames (uint8 [H, W, 3] RGB) -> an avatar package in ``out_dir``."""
    prep = prepare(frames, fps, config=config, focal_px=focal_px, progress=progress,
                   body_models=body_models, models=models)
    return train_prepared(prep, out_dir, config=config, progress=progress,
                          body_models=body_models)


def _decode(path: str | Path, config: EnrollConfig, focal_px: float | None, limits
            ) -> tuple[list[np.ndarray], float, float | None]:
    """Frames, fps and focal (px at the frames' size), through the probe with its limits
    (``enroll.video``: refused before any decoding when outside them)."""
    decoded = read_video(path, limits, long_side=max(config.resolution, config.track_size))
    if focal_px is not None:  # given at the video's size
        focal_px = focal_px * decoded.size[0] / decoded.info.width
    return list(decoded.frames), decoded.fps, focal_px or decoded.focal_px


def enroll_video(path: str | Path, out_dir: str | Path, *, config: EnrollConfig,
                 progress: Progress | None = None, body_models: str | Path | None = None,
                 focal_px: float | None = None, models=None, limits=None) -> EnrollResult:
    """A video file -> an avatar package. ``focal_px``: at the video's size (else from its
    metadata, else the prior); ``limits``: the probe's ``VideoLimits`` (None: defaults)."""
    frames, fps, focal = _decode(path, config, focal_px, limits)
    if progress:
        progress("decode", 1.0)
    return enroll(frames, fps, out_dir, config=config, focal_px=focal, progress=progress,
                  body_models=body_models, models=models)
