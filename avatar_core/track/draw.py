"""Landmark overlays for eyeballing (the `telesplat track landmarks` command and the docs)."""

from __future__ import annotations

import cv2
import numpy as np

from .types import RotatedRect, TrackResult

HAND_EDGES = [(0, 1), (1, 2), (2, 3), (3, 4), (0, 5), (5, 6), (6, 7), (7, 8), (5, 9), (9, 10),
              (10, 11), (11, 12), (9, 13), (13, 14), (14, 15), (15, 16), (13, 17), (0, 17),
              (17, 18), (18, 19), (19, 20)]
POSE_EDGES = [(0, 1), (1, 2), (2, 3), (3, 7), (0, 4), (4, 5), (5, 6), (6, 8), (9, 10),
              (11, 12), (11, 13), (13, 15), (15, 17), (15, 19), (15, 21), (17, 19), (12, 14),
              (14, 16), (16, 18), (16, 20), (16, 22), (18, 20), (11, 23), (12, 24), (23, 24),
              (23, 25), (24, 26), (25, 27), (26, 28), (27, 29), (28, 30), (29, 31), (30, 32),
              (27, 31), (28, 32)]


def _pt(p) -> tuple[int, int]:
    return int(round(float(p[0]))), int(round(float(p[1])))


def _rect(img: np.ndarray, rect: RotatedRect | None, colour) -> None:
    if rect is not None:
        cv2.polylines(img, [np.round(rect.corners()).astype(np.int32)], True, colour, 1,
                      cv2.LINE_AA)


def draw_result(frame_bgr: np.ndarray, result: TrackResult, rois: bool = True) -> np.ndarray:
    """A copy of the frame with the mask tinted, the ROIs, pose skeleton (visible joints),
    face mesh points and hand skeletons drawn."""
    img = frame_bgr.copy()
    if result.mask is not None:
        tint = np.zeros_like(img)
        tint[..., 1] = 255
        alpha = (0.35 * result.mask)[..., None]
        img = (img * (1 - alpha) + tint * alpha).astype(np.uint8)
    if result.pose is not None:
        p, vis = result.pose.points, result.pose.visibility
        for a, b in POSE_EDGES:
            if vis[a] > 0.5 and vis[b] > 0.5:
                cv2.line(img, _pt(p[a]), _pt(p[b]), (255, 160, 0), 2, cv2.LINE_AA)
        for i in range(len(p)):
            if vis[i] > 0.5:
                cv2.circle(img, _pt(p[i]), 3, (255, 80, 0), -1, cv2.LINE_AA)
        if rois:
            _rect(img, result.pose.roi, (255, 160, 0))
    if result.face is not None:
        for q in result.face.points:
            cv2.circle(img, _pt(q), 1, (0, 255, 255), -1)
        if result.face.iris is not None:  # centre and radius of each iris that was read
            for eye in result.face.iris:
                if np.isfinite(eye).all():
                    radius = float(np.linalg.norm(eye[1:, :2] - eye[0, :2], axis=1).mean())
                    cv2.circle(img, _pt(eye[0]), max(1, round(radius)), (0, 0, 255), 1,
                               cv2.LINE_AA)
        if rois:
            _rect(img, result.face.roi, (0, 200, 255))
    for hand in result.hands:
        colour = (0, 0, 255) if hand.handedness == "right" else (255, 0, 255)
        for a, b in HAND_EDGES:
            cv2.line(img, _pt(hand.points[a]), _pt(hand.points[b]), colour, 2, cv2.LINE_AA)
        cv2.putText(img, hand.handedness, _pt(hand.points[0]), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                    colour, 1, cv2.LINE_AA)
        if rois:
            _rect(img, hand.roi, colour)
    return img
