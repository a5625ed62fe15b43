"""Hands: palm detection -> rotated ROI -> 21 landmarks + handedness, up to two hands,
tracked frame to frame.

As in MediaPipe's hand_landmark_tracking graph, the palm detector runs while fewer than
`max_hands` hands are tracked (here every `palm_interval`-th frame, 1 = every frame as
MediaPipe does, also while no hand is tracked); new palms overlapping a tracked hand's ROI
(IoU > 0.5) are dropped.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .anchors import PALM_192
from .detection import Detector
from .onnx_model import ModelSource, OnnxModel
from .roi import (
    crop_rgb,
    project,
    rect_from_box,
    rect_from_points_rotated,
    rotation_between,
    settle_rect,
    to_tensor,
    transform_rect,
)
from .types import HandLandmarks, RotatedRect

# Palm keypoints: 0 wrist centre, 2 middle-finger MCP (the rotation is wrist -> middle, up).
# The landmarks the next ROI is fitted to: wrist, thumb CMC..IP, and the MCP + PIP of each
# finger (MediaPipe's hand_landmark_landmarks_to_roi).
ROI_LANDMARKS = [0, 1, 2, 3, 5, 6, 9, 10, 13, 14, 17, 18]
WRIST, INDEX_MCP, MIDDLE_MCP, RING_MCP = 0, 5, 9, 13


def roi_from_palm(box_px: np.ndarray, keypoints_px: np.ndarray) -> RotatedRect:
    rotation = rotation_between(keypoints_px[0], keypoints_px[2], 90.0)
    return transform_rect(rect_from_box(box_px, rotation), 2.6, 2.6, shift_y=-0.5)


def roi_from_hand_landmarks(points_px: np.ndarray) -> RotatedRect:
    """Next frame's ROI: rotated so wrist -> middle of the MCPs points up, fitted to the palm
    and finger-base landmarks, 2x, shifted towards the fingers."""
    p = points_px[:, :2]
    knuckles = ((p[INDEX_MCP] + p[RING_MCP]) / 2 + p[MIDDLE_MCP]) / 2
    rotation = rotation_between(p[WRIST], knuckles, 90.0)
    rect = rect_from_points_rotated(p[ROI_LANDMARKS], rotation)
    return transform_rect(rect, 2.0, 2.0, shift_y=-0.1)


def rect_iou(a: RotatedRect, b: RotatedRect) -> float:
    """IoU of the rects' unrotated boxes (as MediaPipe's AssociationNormRectCalculator)."""
    ax0, ay0, ax1, ay1 = a.cx - a.width / 2, a.cy - a.height / 2, a.cx + a.width / 2, \
        a.cy + a.height / 2
    bx0, by0, bx1, by1 = b.cx - b.width / 2, b.cy - b.height / 2, b.cx + b.width / 2, \
        b.cy + b.height / 2
    iw = max(0.0, min(ax1, bx1) - max(ax0, bx0))
    ih = max(0.0, min(ay1, by1) - max(ay0, by0))
    inter = iw * ih
    union = a.width * a.height + b.width * b.height - inter
    return inter / union if union > 0 else 0.0


class HandPipeline:
    def __init__(self, models: ModelSource = None, providers: Sequence | None = None,
                 threads: int | None = None, max_hands: int = 2, variant: str = "full",
                 palm_interval: int = 1, min_detection: float = 0.5,
                 min_presence: float = 0.5):
        if variant not in ("full", "lite"):
            raise ValueError(f"hand model variant must be 'full' or 'lite', not {variant!r}")
        self.detector = Detector(f"palm_detection_{variant}", PALM_192, 7, (0.0, 1.0), models,
                                 providers, threads, min_score=min_detection,
                                 max_detections=max_hands)
        self.landmarker = OnnxModel(f"hand_landmark_{variant}", models, providers, threads)
        self.max_hands = max_hands
        self.palm_interval = max(1, palm_interval)
        self.min_presence = min_presence
        self.rois: list[RotatedRect] = []
        self._frames_since_palm = self.palm_interval  # look on the first frame

    def reset(self) -> None:
        self.rois = []
        self._frames_since_palm = self.palm_interval

    def detect_rois(self, frame_bgr: np.ndarray, tracked: list[RotatedRect]
                    ) -> list[RotatedRect]:
        new = []
        for det in self.detector(frame_bgr):
            roi = roi_from_palm(det.box, det.keypoints)
            if all(rect_iou(roi, t) <= 0.5 for t in tracked + new):
                new.append(roi)
        return new

    def landmarks(self, frame_bgr: np.ndarray, roi: RotatedRect) -> HandLandmarks | None:
        w, h = self.landmarker.input_size
        # hand_landmark_cpu.pbtxt: ImageToTensorCalculator border_mode unset -> BORDER_REPLICATE.
        x = to_tensor(crop_rgb(frame_bgr, roi, w, h), 0.0, 1.0)  # [1, 224, 224, 3]
        raw, presence, handedness = self.landmarker(x)[:3]  # [1, 63], [1, 1], [1, 1]
        score = float(presence.reshape(-1)[0])
        if score < self.min_presence:
            return None
        points = project(raw.reshape(21, 3) / np.float32(w), roi)
        # The model's score is for "Left" in a mirrored (selfie) image, i.e. the person's
        # right hand in the unmirrored camera frame.
        p_right = float(handedness.reshape(-1)[0])
        side = "right" if p_right >= 0.5 else "left"
        return HandLandmarks(points, side, score, roi)

    def __call__(self, frame_bgr: np.ndarray) -> tuple[HandLandmarks, ...]:
        rois = list(self.rois)
        if len(rois) < self.max_hands and self._frames_since_palm >= self.palm_interval:
            self._frames_since_palm = 0
            rois += self.detect_rois(frame_bgr, rois)
        self._frames_since_palm += 1
        hands: list[HandLandmarks] = []
        next_rois: list[RotatedRect] = []
        for i, roi in enumerate(rois[:self.max_hands]):
            hand = self.landmarks(frame_bgr, roi)
            if hand is None:
                continue
            tracked = roi if i < len(self.rois) else None
            nxt = settle_rect(tracked, roi_from_hand_landmarks(hand.points))
            if any(rect_iou(nxt, r) > 0.5 for r in next_rois):  # two tracks, one hand
                continue
            hands.append(hand)
            next_rois.append(nxt)
        self.rois = next_rois
        return tuple(hands)
