"""Rotated regions of interest: from detections and landmarks, affine crops, projection back.

All in image pixels (x right, y down). MediaPipe does the same steps in normalised
coordinates (DetectionsToRects, RectTransformation, ImageToTensor, LandmarkProjection); with
the square regions used here the two agree.
"""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np

from .types import RotatedRect


def normalize_radians(angle: float) -> float:
    return angle - 2 * math.pi * math.floor((angle + math.pi) / (2 * math.pi))


def rotation_between(start: np.ndarray, end: np.ndarray, target_degrees: float) -> float:
    """The rotation that turns the start -> end vector (px) to `target_degrees` (counter-
    clockwise from +x as seen on screen). Positive = clockwise in the image."""
    angle = math.atan2(-(float(end[1]) - float(start[1])), float(end[0]) - float(start[0]))
    return normalize_radians(math.radians(target_degrees) - angle)


def transform_rect(rect: RotatedRect, scale_x: float = 1.0, scale_y: float = 1.0,
                   shift_x: float = 0.0, shift_y: float = 0.0,
                   square_long: bool = True) -> RotatedRect:
    """RectTransformationCalculator: shift along the rect's own axes (in units of its size),
    make it square on its long side, then scale."""
    c, s = math.cos(rect.rotation), math.sin(rect.rotation)
    dx, dy = rect.width * shift_x, rect.height * shift_y
    cx = rect.cx + c * dx - s * dy
    cy = rect.cy + s * dx + c * dy
    w, h = rect.width, rect.height
    if square_long:
        w = h = max(w, h)
    return RotatedRect(cx, cy, w * scale_x, h * scale_y, rect.rotation)


def letterbox_rect(width: int, height: int) -> RotatedRect:
    """The square covering the whole frame, centred (keep-aspect-ratio input with padding)."""
    side = float(max(width, height))
    return RotatedRect(width / 2, height / 2, side, side, 0.0)


def crop_matrix(rect: RotatedRect, out_w: int, out_h: int) -> np.ndarray:
    """[2, 3] affine map from image px to crop px: the rect's corners go to the crop's."""
    tl, tr, _br, bl = rect.corners()
    src = np.float32([tl, tr, bl])
    dst = np.float32([[0, 0], [out_w, 0], [0, out_h]])
    return cv2.getAffineTransform(src, dst)


# OpenCV's fixed-point bilinear resampling (the one MediaPipe's bundled OpenCV 4.x uses):
# source coordinates are rounded to 1/32 px and the weights are exact multiples of 1/1024.
_INTER_BITS = 5
_INTER_TAB = 1 << _INTER_BITS
# Fixed-point coordinates inside this range need no saturation (whole px fit an int16).
_SAFE = (-32000.0 * _INTER_TAB, 32000.0 * _INTER_TAB)


# A settled ROI repeats frame after frame (a still subject): its maps are kept.
CROP_MAP_CACHE_SIZE = 16


@functools.lru_cache(maxsize=CROP_MAP_CACHE_SIZE)
def crop_map(rect: RotatedRect, out_w: int, out_h: int) -> tuple[np.ndarray, np.ndarray]:
    """The fixed-point source map of a crop, as MediaPipe's ImageToTensor builds it:
    cv::boxPoints of the float rect (degrees) -> getPerspectiveTransform onto the crop's
    corners -> warpPerspective's inverse map with coordinates rounded to 1/32 px.
    Returns (map1 [out_h, out_w, 2] int16 whole px, map2 [out_h, out_w] uint16 fraction
    index) for cv2.remap."""
    box = ((np.float32(rect.cx), np.float32(rect.cy)),
           (np.float32(rect.width), np.float32(rect.height)),
           float(np.float32(np.float32(rect.rotation) * np.float32(180.0) / math.pi)))
    src = cv2.boxPoints(box)  # bottom-left, top-left, top-right, bottom-right
    dst = np.float32([[0, out_h], [0, 0], [out_w, 0], [out_w, out_h]])
    inv = cv2.invert(cv2.getPerspectiveTransform(src, dst), flags=cv2.DECOMP_LU)[1]
    # A rect maps affinely: the last row is [0, 0, 1] up to rounding, so warpPerspective's
    # division by W is left out (it and OpenCV's per-block sums move a sample position by
    # ~1e-12 px, which flips the 1/32 px rounding of a rare pixel). The scaling by 32 is
    # exact: this is round((M[0] x + (M[1] y + M[2])) * 32).
    x = np.arange(out_w, dtype=np.float64)
    y = np.arange(out_h, dtype=np.float64)
    map1 = np.empty((out_h, out_w, 2), np.int16)
    frac = []
    for k, row in enumerate(inv[:2]):
        v = np.add.outer((row[1] * y + row[2]) * _INTER_TAB, (row[0] * _INTER_TAB) * x)
        np.rint(v, out=v)
        # Saturated as OpenCV does (int, then short for the whole pixels), which a crop
        # within 32000 px of the image never needs.
        inside = _SAFE[0] < v.min() and v.max() < _SAFE[1]
        if not inside:  # NaN (a degenerate rect) saturates to INT_MIN, as cvRound gives
            np.nan_to_num(v, copy=False, nan=np.iinfo(np.int32).min)
            np.clip(v, np.iinfo(np.int32).min, np.iinfo(np.int32).max, out=v)
        fixed = v.astype(np.int32)
        whole = fixed >> _INTER_BITS
        if not inside:
            whole = np.clip(whole, np.iinfo(np.int16).min, np.iinfo(np.int16).max)
        map1[..., k] = whole
        frac.append(fixed & (_INTER_TAB - 1))
    map2 = (frac[1] << _INTER_BITS | frac[0]).astype(np.uint16)
    map1.flags.writeable = map2.flags.writeable = False  # shared through the cache
    return map1, map2


def crop_rgb(frame_bgr: np.ndarray, rect: RotatedRect, out_w: int, out_h: int,
             zero_border: bool = False) -> np.ndarray:
    """[out_h, out_w, 3] uint8 RGB crop of the rotated rect, resampled as MediaPipe's
    ImageToTensorCalculator does on the CPU (bilinear, fixed point; see `crop_map`).
    `zero_border` fills outside the frame with black (border_mode BORDER_ZERO), else the
    edge pixels are replicated (BORDER_REPLICATE, also what an unset border_mode means)."""
    border = cv2.BORDER_CONSTANT if zero_border else cv2.BORDER_REPLICATE
    map1, map2 = crop_map(rect, out_w, out_h)
    crop = cv2.remap(frame_bgr, map1, map2, cv2.INTER_LINEAR, borderMode=border,
                     borderValue=0)
    return cv2.cvtColor(crop, cv2.COLOR_BGR2RGB)


def to_tensor(crop_rgb_uint8: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """[1, H, W, 3] float32 in [lo, hi] (the models' NHWC input)."""
    x = crop_rgb_uint8.astype(np.float32) * ((hi - lo) / 255.0)
    if lo:
        x += lo
    return x[None]


def project(points: np.ndarray, rect: RotatedRect) -> np.ndarray:
    """Normalised crop coordinates [N, 2 or 3] (0..1 over the crop; z in the same unit as x)
    -> image px [N, 2 or 3] (z scaled by the rect's width)."""
    c, s = math.cos(rect.rotation), math.sin(rect.rotation)
    u = (points[:, 0] - 0.5) * rect.width
    v = (points[:, 1] - 0.5) * rect.height
    out = np.empty_like(points, dtype=np.float32)
    out[:, 0] = rect.cx + c * u - s * v
    out[:, 1] = rect.cy + s * u + c * v
    if points.shape[1] > 2:
        out[:, 2] = points[:, 2] * rect.width
    return out


def unproject(points_px: np.ndarray, rect: RotatedRect) -> np.ndarray:
    """Inverse of `project` for x, y: image px [N, 2] -> normalised crop coordinates."""
    c, s = math.cos(rect.rotation), math.sin(rect.rotation)
    dx = points_px[:, 0] - rect.cx
    dy = points_px[:, 1] - rect.cy
    u = c * dx + s * dy
    v = -s * dx + c * dy
    return np.stack([u / rect.width + 0.5, v / rect.height + 0.5], axis=1).astype(np.float32)


def rect_from_box(box_px: np.ndarray, rotation: float) -> RotatedRect:
    """An axis-aligned box [xmin, ymin, xmax, ymax] px with a rotation (about its centre)."""
    x0, y0, x1, y1 = (float(v) for v in box_px)
    return RotatedRect((x0 + x1) / 2, (y0 + y1) / 2, x1 - x0, y1 - y0, rotation)


def rect_from_points_rotated(points_px: np.ndarray, rotation: float) -> RotatedRect:
    """The tightest rect with the given rotation around the points (HandLandmarksToRect)."""
    c, s = math.cos(rotation), math.sin(rotation)
    # Into the rect's frame (rotate by -rotation), box there, centre back.
    u = c * points_px[:, 0] + s * points_px[:, 1]
    v = -s * points_px[:, 0] + c * points_px[:, 1]
    cu, cv = (u.min() + u.max()) / 2, (v.min() + v.max()) / 2
    return RotatedRect(float(c * cu - s * cv), float(s * cu + c * cv),
                       float(u.max() - u.min()), float(v.max() - v.min()), rotation)


def rect_from_alignment_points(centre: np.ndarray, scale_point: np.ndarray,
                               target_degrees: float) -> RotatedRect:
    """AlignmentPointsRects: centred on `centre`, side twice the distance to `scale_point`,
    rotated so that centre -> scale_point points to `target_degrees`."""
    side = 2.0 * float(np.hypot(*(scale_point[:2] - centre[:2])))
    return RotatedRect(float(centre[0]), float(centre[1]), side, side,
                       rotation_between(centre, scale_point, target_degrees))


def detection_to_px(box: np.ndarray, keypoints: np.ndarray,
                    letterbox: RotatedRect) -> tuple[np.ndarray, np.ndarray]:
    """A detection normalised over the (unrotated) letterboxed input -> image px."""
    x0 = letterbox.cx - letterbox.width / 2
    y0 = letterbox.cy - letterbox.height / 2
    scale = np.float32([letterbox.width, letterbox.height])
    corners = box.reshape(2, 2) * scale + [x0, y0]
    return corners.reshape(4).astype(np.float32), (keypoints * scale + [x0, y0]).astype(
        np.float32)


def settle_rect(prev: RotatedRect | None, new: RotatedRect, tolerance: float = 0.05
                ) -> RotatedRect:
    """Low-pass a tracked ROI: small changes (relative to the ROI's size; rotation in
    radians) are mostly ignored, large ones pass through. The landmark models see the same
    crop while the subject is still, so a still subject gives still landmarks (MediaPipe
    smooths its ROI landmarks with a one-euro filter for the same reason)."""
    if prev is None:
        return new
    size = max(prev.width, 1e-6)
    change = max(math.hypot(new.cx - prev.cx, new.cy - prev.cy) / size,
                 abs(new.width - prev.width) / size,
                 abs(normalize_radians(new.rotation - prev.rotation)))
    alpha = min(1.0, (change / tolerance) ** 2)
    rot = prev.rotation + alpha * normalize_radians(new.rotation - prev.rotation)
    return RotatedRect(prev.cx + alpha * (new.cx - prev.cx),
                       prev.cy + alpha * (new.cy - prev.cy),
                       prev.width + alpha * (new.width - prev.width),
                       prev.height + alpha * (new.height - prev.height),
                       normalize_radians(rot))
