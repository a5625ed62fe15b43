"""Box decoding (TensorsToDetectionsCalculator) and weighted non-maximum suppression."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import expit


@dataclass(frozen=True)
class Detection:
    """A detection in normalised model-input coordinates (0..1 over the detector's input)."""

    box: np.ndarray  # [4] float32: xmin, ymin, xmax, ymax
    keypoints: np.ndarray  # [K, 2] float32: x, y
    score: float


def decode_boxes(raw_boxes: np.ndarray, raw_scores: np.ndarray, anchors: np.ndarray,
                 input_size: int, num_keypoints: int, min_score: float = 0.5,
                 score_clip: float = 100.0) -> list[Detection]:
    """SSD regressors -> detections above `min_score`.

    raw_boxes [N, 4 + 2K] (x, y, w, h, then keypoint x, y: offsets in input pixels from the
    anchor centre, MediaPipe's ``reverse_output_order``), raw_scores [N] or [N, 1] logits,
    anchors [N, 2] normalised centres (fixed size 1).
    """
    logits = np.clip(raw_scores.reshape(-1).astype(np.float64), -score_clip, score_clip)
    scores = expit(logits)
    keep = np.flatnonzero(scores >= min_score)
    if keep.size == 0:
        return []
    raw = raw_boxes.reshape(raw_boxes.shape[0], -1)[keep] / input_size  # [M, 4 + 2K]
    anchor = anchors[keep]  # [M, 2]
    centre = raw[:, 0:2] + anchor
    half = raw[:, 2:4] / 2
    boxes = np.concatenate([centre - half, centre + half], axis=1)  # [M, 4]
    kps = raw[:, 4:4 + 2 * num_keypoints].reshape(-1, num_keypoints, 2) + anchor[:, None]
    return [Detection(boxes[i].astype(np.float32), kps[i].astype(np.float32),
                      float(scores[keep[i]])) for i in range(keep.size)]


def iou(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Intersection over union of one [4] box with [M, 4] boxes (xmin, ymin, xmax, ymax)."""
    lo = np.maximum(box[:2], boxes[:, :2])
    hi = np.minimum(box[2:], boxes[:, 2:])
    inter = np.prod(np.clip(hi - lo, 0, None), axis=1)
    area = np.prod(np.clip(box[2:] - box[:2], 0, None))
    areas = np.prod(np.clip(boxes[:, 2:] - boxes[:, :2], 0, None), axis=1)
    union = area + areas - inter
    return np.where(union > 0, inter / np.maximum(union, 1e-12), 0.0)


def weighted_nms(detections: list[Detection], iou_threshold: float = 0.3,
                 max_detections: int | None = None) -> list[Detection]:
    """MediaPipe's WEIGHTED suppression: take the best-scoring detection, gather every
    remaining one overlapping it by more than `iou_threshold` (itself included) and replace
    its box and keypoints by their score-weighted mean; it keeps the best score."""
    order = sorted(range(len(detections)), key=lambda i: -detections[i].score)
    remaining = [detections[i] for i in order]
    out: list[Detection] = []
    while remaining and (max_detections is None or len(out) < max_detections):
        best = remaining[0]
        boxes = np.stack([d.box for d in remaining])
        overlap = iou(best.box, boxes) > iou_threshold
        overlap[0] = True
        group = [d for d, o in zip(remaining, overlap, strict=True) if o]
        weights = np.array([d.score for d in group], np.float32)
        weights /= weights.sum()
        box = np.tensordot(weights, np.stack([d.box for d in group]), axes=1)
        kps = np.tensordot(weights, np.stack([d.keypoints for d in group]), axes=1)
        out.append(Detection(box.astype(np.float32), kps.astype(np.float32), best.score))
        remaining = [d for d, o in zip(remaining, overlap, strict=True) if not o]
    return out
