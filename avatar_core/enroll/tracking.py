"""Every kept frame through the live tracker and the per-frame fit (``track.fit``), on the
video's own camera; people counted by the face detector; the person's mask from the selfie
segmentation model. Body shape stays the mean here: ``shape_fit`` fits it across frames."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..track.anchors import FACE_SHORT_RANGE
from ..track.detection import Detector
from ..track.fit.observations import Observations, from_track_result
from ..track.fit.sequence import SequenceFit, SequenceFitConfig
from ..track.tracker import Tracker

FACE_DETECTION_SCORE = 0.6   # a second face counts only at this confidence


@dataclass
class TrackedTake:
    frames: list[int]                        # video frame index of each tracked frame
    observations: list[Observations]         # at the tracking size
    params: list[dict[str, np.ndarray]]      # per-frame fit (mean shape)
    masks: list[np.ndarray | None]           # [h, w] float32 at the tracking size, or None
    failed: list[int] = field(default_factory=list)  # video frames with nobody tracked
    faces: list[int] = field(default_factory=list)   # faces detected, per kept frame
    size: tuple[int, int] = (0, 0)           # (w, h) tracked at
    scale: float = 1.0                       # tracking size / video size


def tracking_scale(width: int, height: int, track_size: int) -> float:
    return min(1.0, track_size / max(width, height))


def fov_x_deg(focal_px: float, width: int) -> float:
    return math.degrees(2 * math.atan(0.5 * width / focal_px))


def load_body(body_models: str | Path | None):
    from ..body.model_paths import resolve_body_models
    from ..body.upper_body import UpperBodyModel

    files = resolve_body_models(body_models)
    files.require()
    return files, UpperBodyModel.load(files.smplx_npz, files.segmentation)


class TakeTracker:
    """The tracker (with the selfie mask) and a face detector that counts people: loaded once
    per enrollment (loading the ONNX sessions costs seconds)."""

    def __init__(self, models=None) -> None:
        self.tracker = Tracker(models, mask=True)
        self.faces = Detector("face_detection_short_range", FACE_SHORT_RANGE, 6, (-1.0, 1.0),
                              models, min_score=FACE_DETECTION_SCORE, max_detections=4)

    def close(self) -> None:
        self.tracker.close()


def track_take(frames: Sequence[np.ndarray], kept: Sequence[int], fps: float, model,
               focal_px: float, track_size: int, masks: bool, take_tracker: TakeTracker,
               progress: Callable[[float], None] | None = None) -> TrackedTake:
    """Track and fit ``frames[kept]`` (RGB) in order; ``focal_px`` at the video's size."""
    h0, w0 = frames[0].shape[:2]
    s = tracking_scale(w0, h0, track_size)
    size = (max(1, round(w0 * s)), max(1, round(h0 * s)))
    tracker, faces = take_tracker.tracker, take_tracker.faces
    tracker.reset()
    fit = SequenceFit(model, None, SequenceFitConfig(
        fov_x_deg=fov_x_deg(focal_px * s, size[0]), smoothing=False, gaze=False))
    take = TrackedTake([], [], [], [], size=size, scale=s)
    mask_stage = tracker.mask
    if not masks:
        tracker.mask = None  # the segmentation is skipped, not computed and dropped
    try:
        for n, i in enumerate(kept):
            bgr = np.ascontiguousarray(frames[i][..., ::-1])
            if s < 1:
                bgr = cv2.resize(bgr, size, interpolation=cv2.INTER_AREA)
            result = tracker.track(bgr)
            take.faces.append(len(faces(bgr)))
            obs = from_track_result(result)
            if not (obs.seen.get("face") or obs.seen.get("pose")):
                take.failed.append(i)
                tracker.reset()
            else:
                out = fit.step(obs, i / fps)
                take.frames.append(i)
                take.observations.append(obs)
                take.params.append({k: np.asarray(v, np.float64) for k, v in out.params.items()})
                take.masks.append(result.mask)
            if progress:
                progress((n + 1) / len(kept))
    finally:
        tracker.mask = mask_stage
    return take


def yaw_deg(global_orient: np.ndarray) -> float:
    """The body's turn about the vertical (deg; 0 facing the camera) from its root rotation."""
    from scipy.spatial.transform import Rotation

    forward = Rotation.from_rotvec(global_orient).apply([0.0, 0.0, 1.0])
    return math.degrees(math.atan2(forward[0], forward[2]))
