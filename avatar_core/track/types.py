"""What the landmark tracker returns: plain frozen dataclasses, numpy arrays in image pixels.

Coordinates are the input frame's pixels: x right, y down, origin at the top-left corner of the
top-left pixel. ``z`` is MediaPipe's relative depth, scaled to pixels the same way as x (smaller
is nearer the camera; its origin is the face centre / the wrist / the hips midpoint).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np


class TrackingInputError(ValueError):
    """The input frame is unusable: empty, corrupt, the wrong type or too large."""


@dataclass(frozen=True)
class RotatedRect:
    """A region of interest in image pixels: centre, size, rotation (radians, clockwise in
    the image since y points down; 0 = axis aligned)."""

    cx: float
    cy: float
    width: float
    height: float
    rotation: float = 0.0

    def corners(self) -> np.ndarray:
        """[4, 2] px: top-left, top-right, bottom-right, bottom-left of the rotated box."""
        c, s = np.cos(self.rotation), np.sin(self.rotation)
        hw, hh = self.width / 2, self.height / 2
        local = np.array([[-hw, -hh], [hw, -hh], [hw, hh], [-hw, hh]])
        rot = np.array([[c, -s], [s, c]])
        return (local @ rot.T + [self.cx, self.cy]).astype(np.float32)


@dataclass(frozen=True)
class FaceLandmarks:
    points: np.ndarray  # [468, 3] float32: x, y px; z relative depth in px scale
    score: float  # face presence, 0..1
    roi: RotatedRect  # the crop the landmarks were read from
    # Eyes (`Tracker(iris=True)`), the person's right eye then left eye; rows of an eye that
    # could not be read are NaN. iris: centre then 4 points on the iris edge; eye_contour:
    # MediaPipe's 71 points, the first 16 the eyelid margin (`iris.EYELID`).
    iris: np.ndarray | None = None  # [2, 5, 3] float32 px
    eye_contour: np.ndarray | None = None  # [2, 71, 3] float32 px


@dataclass(frozen=True)
class HandLandmarks:
    points: np.ndarray  # [21, 3] float32 px (MediaPipe hand topology; 0 = wrist)
    # The person's own hand. MediaPipe's handedness model assumes a mirrored (selfie) image;
    # on an unmirrored camera frame its "Left" is the person's right hand: we swap it.
    handedness: Literal["left", "right"]
    score: float  # hand presence, 0..1
    roi: RotatedRect | None = None


@dataclass(frozen=True)
class PoseLandmarks:
    points: np.ndarray  # [33, 3] float32 px (BlazePose topology; 0 = nose)
    visibility: np.ndarray  # [33] float32, 0..1
    score: float  # pose presence, 0..1
    roi: RotatedRect | None = None
    # [33, 3] float32 metres: BlazePose's world landmarks (origin between the hips, x right,
    # y down, z away from the camera, turned by the ROI's rotation as MediaPipe does), or None.
    world: np.ndarray | None = None


@dataclass(frozen=True)
class TrackResult:
    face: FaceLandmarks | None
    hands: tuple[HandLandmarks, ...]
    pose: PoseLandmarks | None
    mask: np.ndarray | None  # [H, W] float32 0..1 person probability, or None
    timings_ms: dict[str, float] = field(default_factory=dict)
    image_size: tuple[int, int] = (0, 0)  # (w, h)
