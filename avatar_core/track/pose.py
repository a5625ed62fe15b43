"""Body: pose detection -> rotated ROI -> 33 landmarks with visibility, tracked.

MediaPipe's pose_landmark graph (full model): the detector's hips centre and full-body scale
point give the ROI; the landmark model's two auxiliary points (33, 34) give the next frame's;
each landmark is refined from its heatmap (7x7 window) when that is confident.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.special import expit

from .anchors import POSE_224
from .detection import Detector
from .onnx_model import ModelSource, OnnxModel
from .roi import (
    crop_rgb,
    project,
    rect_from_alignment_points,
    to_tensor,
    transform_rect,
)
from .single import SingleTargetPipeline
from .types import PoseLandmarks, RotatedRect

NUM_LANDMARKS = 33  # BlazePose topology; the model outputs 39: + 2 ROI points + 4 unused


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return expit(x.astype(np.float64)).astype(np.float32)


def roi_from_alignment(centre_px: np.ndarray, scale_px: np.ndarray) -> RotatedRect:
    """Hips centre + full-body scale point -> square ROI, upright body, 1.25x."""
    return transform_rect(rect_from_alignment_points(centre_px, scale_px, 90.0), 1.25, 1.25)


def refine_from_heatmap(points: np.ndarray, heatmap: np.ndarray, kernel: int = 7,
                        min_confidence: float = 0.5) -> np.ndarray:
    """points [N, >=2] normalised over the crop; heatmap [h, w, N] logits. Each point inside
    the map moves to the sigmoid-weighted mean cell of its kernel window (as MediaPipe's
    RefineLandmarksFromHeatmap: cell index / size, no half-cell offset) if that window's
    peak confidence reaches `min_confidence`."""
    hm_h, hm_w, _ = heatmap.shape
    out = points.copy()
    r = (kernel - 1) // 2
    for i in range(points.shape[0]):
        col, row = int(points[i, 0] * hm_w), int(points[i, 1] * hm_h)  # truncated, as in C++
        # refine_landmarks_from_heatmap_calculator.cc tests `col >= hm_height` where it means
        # the row, so a point up to `r` cells below the map still refines from its clipped
        # window (a square map; kept for parity).
        if not (0 <= col < hm_w and 0 <= row and col < hm_h):
            continue
        r0, r1, c0, c1 = max(0, row - r), min(hm_h, row + r + 1), max(0, col - r), min(
            hm_w, col + r + 1)
        conf = _sigmoid(heatmap[r0:r1, c0:c1, i])
        total = float(conf.sum())
        if conf.size and conf.max() >= min_confidence and total > 0:
            rows, cols = np.mgrid[r0:r1, c0:c1]
            out[i, 0] = float((cols * conf).sum()) / hm_w / total
            out[i, 1] = float((rows * conf).sum()) / hm_h / total
    return out


def world_from_output(world: np.ndarray, rotation: float) -> np.ndarray:
    """The model's world output [1, 117] -> [33, 3] metres, turned by the ROI's rotation about
    the camera axis (MediaPipe's WorldLandmarkProjectionCalculator)."""
    w = np.asarray(world, dtype=np.float32).reshape(39, 3)[:NUM_LANDMARKS].copy()
    c, s = np.float32(np.cos(rotation)), np.float32(np.sin(rotation))
    x, y = w[:, 0].copy(), w[:, 1].copy()
    w[:, 0], w[:, 1] = c * x - s * y, s * x + c * y
    return w


class PosePipeline(SingleTargetPipeline):
    def __init__(self, models: ModelSource = None, providers: Sequence | None = None,
                 threads: int | None = None, min_detection: float = 0.5,
                 min_presence: float = 0.5, refine: bool = True):
        self.detector = Detector("pose_detection", POSE_224, 4, (-1.0, 1.0), models,
                                 providers, threads, min_score=min_detection,
                                 max_detections=1)
        self.landmarker = OnnxModel("pose_landmark_full", models, providers, threads)
        self.min_presence = min_presence
        self.refine = refine

    def detect_roi(self, frame_bgr: np.ndarray) -> RotatedRect | None:
        found = self.detector(frame_bgr)
        if not found:
            return None
        kps = found[0].keypoints  # [4, 2]: hips centre, body scale, shoulders centre, scale
        return roi_from_alignment(kps[0], kps[1])

    def input_tensor(self, frame_bgr: np.ndarray, roi: RotatedRect) -> np.ndarray:
        """The landmark model's input: [1, 256, 256, 3] in [0, 1]."""
        w, h = self.landmarker.input_size
        # pose_landmark_by_roi_cpu.pbtxt: ImageToTensorCalculator border_mode unset ->
        # BORDER_REPLICATE. The body ROI of a portrait is 2-4x the photo, so the fill matters.
        return to_tensor(crop_rgb(frame_bgr, roi, w, h), 0.0, 1.0)

    def landmarks(self, frame_bgr: np.ndarray, roi: RotatedRect
                  ) -> tuple[PoseLandmarks, RotatedRect] | None:
        w, _h = self.landmarker.input_size
        x = self.input_tensor(frame_bgr, roi)
        raw, flag, _seg, heatmap, world = self.landmarker(x)[:5]  # [1,195] [1,1] _ hm [1,117]
        score = float(flag.reshape(-1)[0])  # the model ends in a sigmoid
        if score < self.min_presence:
            return None
        values = raw.reshape(39, 5)  # x, y, z (crop px), visibility, presence logits
        points = values[:, :3] / np.float32(w)
        if self.refine:
            points = refine_from_heatmap(points, heatmap[0])
        px = project(points, roi)  # [39, 3]
        pose = PoseLandmarks(px[:NUM_LANDMARKS], _sigmoid(values[:NUM_LANDMARKS, 3]), score, roi,
                             world_from_output(world, roi.rotation))
        return pose, roi_from_alignment(px[33], px[34])
