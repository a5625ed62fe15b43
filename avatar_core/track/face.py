"""Face: short-range detection -> rotated ROI -> 468 landmarks, tracked frame to frame.

MediaPipe's face_landmark_front graph: the detector runs only while no face is tracked; the
ROI for the next frame comes from this frame's landmarks; a face-presence score under the
threshold drops the track (here the detector then runs again in the same frame).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.special import expit

from .anchors import FACE_SHORT_RANGE
from .detection import Detector
from .onnx_model import ModelSource, OnnxModel
from .roi import (
    crop_rgb,
    project,
    rect_from_box,
    rotation_between,
    to_tensor,
    transform_rect,
)
from .single import SingleTargetPipeline
from .types import FaceLandmarks, RotatedRect

# Face detection keypoints: right eye, left eye, nose tip, mouth, right ear, left ear.
# Landmark indices (face mesh): outer corners of the right and left eye.
RIGHT_EYE_CORNER, LEFT_EYE_CORNER = 33, 263


def roi_from_face_landmarks(points_px: np.ndarray) -> RotatedRect:
    """Next frame's ROI: landmarks' bounding box, rotated to level the eyes, 1.5x, square."""
    lo, hi = points_px[:, :2].min(axis=0), points_px[:, :2].max(axis=0)
    rotation = rotation_between(points_px[RIGHT_EYE_CORNER], points_px[LEFT_EYE_CORNER], 0.0)
    return transform_rect(rect_from_box(np.concatenate([lo, hi]), rotation), 1.5, 1.5)


class FacePipeline(SingleTargetPipeline):
    def __init__(self, models: ModelSource = None, providers: Sequence | None = None,
                 threads: int | None = None, min_detection: float = 0.5,
                 min_presence: float = 0.5):
        self.detector = Detector("face_detection_short_range", FACE_SHORT_RANGE, 6,
                                 (-1.0, 1.0), models, providers, threads,
                                 min_score=min_detection, max_detections=1)
        self.landmarker = OnnxModel("face_landmark", models, providers, threads)
        self.min_presence = min_presence

    def detect_roi(self, frame_bgr: np.ndarray) -> RotatedRect | None:
        found = self.detector(frame_bgr)
        if not found:
            return None
        det = found[0]
        rotation = rotation_between(det.keypoints[0], det.keypoints[1], 0.0)
        return transform_rect(rect_from_box(det.box, rotation), 1.5, 1.5)

    def landmarks(self, frame_bgr: np.ndarray, roi: RotatedRect
                  ) -> tuple[FaceLandmarks, RotatedRect] | None:
        w, h = self.landmarker.input_size
        # face_landmark_cpu.pbtxt: ImageToTensorCalculator border_mode unset -> BORDER_REPLICATE.
        x = to_tensor(crop_rgb(frame_bgr, roi, w, h), 0.0, 1.0)  # [1, 192, 192, 3]
        raw, flag = self.landmarker(x)  # [1, 1, 1, 1404], [1, 1, 1, 1]
        score = float(expit(flag.reshape(-1)[0]))  # a logit
        if score < self.min_presence:
            return None
        points = raw.reshape(468, 3) / np.float32(w)  # normalised over the crop
        face = FaceLandmarks(project(points, roi), score, roi)
        return face, roi_from_face_landmarks(face.points)
