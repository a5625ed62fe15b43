"""Eyes: MediaPipe's iris pipeline on the tracked face mesh (iris_landmark_left_and_right_cpu).

Per eye (IrisLandmarkLandmarksToRoi + IrisLandmarkCpu): the two face-mesh corners of the eye
give a rect (their bounding box, rotated so that the start -> end corner vector is level),
squared on its long side and scaled 2.3x; a 64x64 crop of it (border replicated) in [0, 1]
goes to iris_landmark, which answers 71 eye-contour points and 5 iris points (centre first)
in crop pixels. The model knows one eye side only: MediaPipe flips the crop of its "right eye"
(face-mesh 362 -> 263, the person's left eye) horizontally and flips the points' x back.

Output order here is the person's right eye (face-mesh 33 -> 133, on the image's left for an
unmirrored frame), then the person's left eye.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from .onnx_model import ModelSource, OnnxModel
from .roi import crop_rgb, project, rect_from_box, rotation_between, to_tensor, transform_rect
from .types import FaceLandmarks, RotatedRect

# (start, end) face-mesh corners per eye, person's right eye then left eye: MediaPipe's
# "left eye" boundary (33, 133) and "right eye" boundary (362, 263).
EYE_CORNERS = ((33, 133), (362, 263))
# Which of the two crops is mirrored before the model (MediaPipe's IS_RIGHT_EYE: 362 -> 263).
FLIP = (False, True)
ROI_SCALE = 2.3
NUM_CONTOUR, NUM_IRIS = 71, 5
# The first 16 contour points are the eyelid margin (MediaPipe's UpdateFaceLandmarks table):
# 0..8 the lower lid from the outer corner to the inner one, 9..15 the upper lid from outer to
# inner without the corners; the rest are rings around the eye and the brow. EYELID walks the
# margin as a closed polygon.
EYELID = (*range(9), *range(15, 8, -1))
# An eye whose corners lie closer than this (px) is too small to read: no iris for it.
MIN_EYE_WIDTH_PX = 4.0


def eye_roi(start_px: np.ndarray, end_px: np.ndarray) -> RotatedRect:
    """IrisLandmarkLandmarksToRoi: the corners' box, start -> end level, square, 2.3x."""
    pts = np.stack([start_px[:2], end_px[:2]]).astype(np.float64)  # [2, 2]
    box = np.concatenate([pts.min(axis=0), pts.max(axis=0)])
    rect = rect_from_box(box, rotation_between(start_px, end_px, 0.0))
    return transform_rect(rect, ROI_SCALE, ROI_SCALE)


class IrisPipeline:
    """`(frame, face) -> face` with `iris` [2, 5, 3] and `eye_contour` [2, 71, 3] filled in
    (frame px; z in px scale like the face mesh). An eye that cannot be read (too small, its
    ROI centre off the frame, non-finite corners or output) is NaN; both: fields stay None."""

    def __init__(self, models: ModelSource = None, providers: Sequence | None = None,
                 threads: int | None = None):
        self.model = OnnxModel("iris_landmark", models, providers, threads)

    def eye(self, frame_bgr: np.ndarray, roi: RotatedRect, flip: bool
            ) -> tuple[np.ndarray, np.ndarray]:
        """One eye's contour [71, 3] and iris [5, 3] in frame px."""
        w, h = self.model.input_size
        # iris_landmark_cpu.pbtxt: ImageCroppingCalculator border_mode: BORDER_REPLICATE. (It
        # crops nearest-neighbour on whole pixels, then resizes to 64x64; here one bilinear
        # warp: docs/tracking.md, parity with MediaPipe.)
        crop = crop_rgb(frame_bgr, roi, w, h)  # [64, 64, 3]
        if flip:
            crop = crop[:, ::-1]
        contour, iris = self.model(to_tensor(np.ascontiguousarray(crop), 0.0, 1.0))
        points = np.concatenate([contour.reshape(NUM_CONTOUR, 3), iris.reshape(NUM_IRIS, 3)])
        if flip:  # TensorsToLandmarks' flip_horizontally: x only, z kept
            points[:, 0] = w - points[:, 0]
        out = project(points / np.float32(w), roi)  # [76, 3]
        return out[:NUM_CONTOUR], out[NUM_CONTOUR:]

    def read(self, frame_bgr: np.ndarray, start: np.ndarray, end: np.ndarray, flip: bool
             ) -> tuple[np.ndarray, np.ndarray] | None:
        """An eye from its two corners, or None when it cannot be read: corners not finite or
        closer than MIN_EYE_WIDTH_PX, the ROI's centre off the frame, non-finite output."""
        if not (np.isfinite(start[:2]).all() and np.isfinite(end[:2]).all()):
            return None
        if float(np.hypot(*(end[:2] - start[:2]))) < MIN_EYE_WIDTH_PX:
            return None
        roi = eye_roi(start, end)
        h, w = frame_bgr.shape[:2]
        if not (0 <= roi.cx < w and 0 <= roi.cy < h):
            return None
        contour, iris = self.eye(frame_bgr, roi, flip)
        return (contour, iris) if np.isfinite(contour).all() and np.isfinite(iris).all() else None

    def __call__(self, frame_bgr: np.ndarray, face: FaceLandmarks) -> FaceLandmarks:
        contours = np.full((2, NUM_CONTOUR, 3), np.nan, np.float32)
        irises = np.full((2, NUM_IRIS, 3), np.nan, np.float32)
        for k, ((a, b), flip) in enumerate(zip(EYE_CORNERS, FLIP, strict=True)):
            found = self.read(frame_bgr, face.points[a], face.points[b], flip)
            if found is not None:
                contours[k], irises[k] = found
        if np.isnan(irises[:, 0, 0]).all():
            return face
        return replace(face, iris=irises, eye_contour=contours)
