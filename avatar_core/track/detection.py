"""A MediaPipe SSD detector on ONNX Runtime: letterboxed input -> decoded, suppressed
detections in image pixels."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .anchors import AnchorSpec, ssd_anchors
from .nms import Detection, decode_boxes, weighted_nms
from .onnx_model import ModelSource, OnnxModel
from .roi import crop_rgb, detection_to_px, letterbox_rect, to_tensor


class Detector:
    """Runs one detector on the whole frame (keep aspect ratio, zero padding), as
    TensorsToDetections + WEIGHTED NonMaxSuppression configure it in MediaPipe's graphs.
    Returns `Detection`s with `box` [4] and `keypoints` [K, 2] in image px, best first."""

    def __init__(self, name: str, anchors: AnchorSpec, num_keypoints: int,
                 input_range: tuple[float, float], models: ModelSource = None,
                 providers: Sequence | None = None, threads: int | None = None,
                 min_score: float = 0.5, iou_threshold: float = 0.3,
                 max_detections: int | None = None):
        self.model = OnnxModel(name, models, providers, threads)
        self.spec = anchors
        self.anchors = ssd_anchors(anchors)  # [N, 2]
        self.num_keypoints = num_keypoints
        self.input_range = input_range
        self.min_score = min_score
        self.iou_threshold = iou_threshold
        self.max_detections = max_detections

    @property
    def calls(self) -> int:
        return self.model.calls

    def __call__(self, frame_bgr: np.ndarray) -> list[Detection]:
        h, w = frame_bgr.shape[:2]
        box = letterbox_rect(w, h)
        size = self.spec.input_size
        # face_detection.pbtxt, palm_detection_cpu.pbtxt, pose_detection_cpu.pbtxt:
        # ImageToTensorCalculator keep_aspect_ratio: true, border_mode: BORDER_ZERO.
        x = to_tensor(crop_rgb(frame_bgr, box, size, size, zero_border=True),
                      *self.input_range)  # [1, S, S, 3]
        raw_boxes, raw_scores = self.model(x)[:2]  # [1, N, 4 + 2K], [1, N, 1]
        found = decode_boxes(raw_boxes[0], raw_scores[0], self.anchors, size,
                             self.num_keypoints, self.min_score)
        found = weighted_nms(found, self.iou_threshold, self.max_detections)
        out = []
        for d in found:
            box_px, kps_px = detection_to_px(d.box, d.keypoints, box)
            out.append(Detection(box_px, kps_px, d.score))
        return out
