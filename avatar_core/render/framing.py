"""The default view of a scene at rest: an orbit that shows every upper body whole (head to the
cut, both hands), and the face that zooming in goes toward without cutting the head.

Pure geometry on boxes (``lo``, ``hi`` corners [3] in world metres): the caller poses the bodies
at rest and places them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["FRAME_MARGIN", "SceneFraming", "fit_distance", "frame_scene", "head_box"]

FRAME_MARGIN = 0.08  # of the box's half size, left free on each side of the frame
HEAD_MARGIN = 0.25   # of the head's half size: the closest zoom still shows hair and chin


@dataclass(frozen=True)
class SceneFraming:
    target: np.ndarray  # [3] the centre of every body's box
    distance: float     # orbit distance at which the boxes fit a square frame at fov_y_deg
    fov_y_deg: float
    face: np.ndarray    # [3] the centre of the head's box
    min_distance: float  # the closest orbit around `face` that still shows the whole head


def fit_distance(half: np.ndarray, fov_y_deg: float, margin: float) -> float:
    """Orbit distance from a box's centre, seen from the front (+z), at which the box of half
    sizes ``half`` [3] fits a square frame with ``margin`` free: its front face, nearest the
    camera and so the largest on screen, must fit."""
    tan = math.tan(math.radians(fov_y_deg) / 2)
    return float(max(half[0], half[1]) * (1 + margin) / tan + half[2])


def head_box(vertices: np.ndarray, neck: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The box of the vertices [V, 3] above the neck joint [3] (the head and the hair)."""
    head = vertices[vertices[:, 1] > neck[1]]
    if not len(head):
        raise ValueError("no vertex lies above the neck joint")
    return head.min(0), head.max(0)


def frame_scene(boxes: list[tuple[np.ndarray, np.ndarray]], head: tuple[np.ndarray, np.ndarray],
                fov_y_deg: float = 30.0) -> SceneFraming:
    """The framing of bodies whose rest boxes are ``boxes`` and whose face is ``head``'s box."""
    if not boxes:
        raise ValueError("no box to frame")
    lo = np.min([b[0] for b in boxes], axis=0).astype(np.float64)
    hi = np.max([b[1] for b in boxes], axis=0).astype(np.float64)
    head_lo, head_hi = (np.asarray(v, dtype=np.float64) for v in head)
    return SceneFraming(
        target=(lo + hi) / 2, distance=fit_distance((hi - lo) / 2, fov_y_deg, FRAME_MARGIN),
        fov_y_deg=fov_y_deg, face=(head_lo + head_hi) / 2,
        min_distance=fit_distance((head_hi - head_lo) / 2, fov_y_deg, HEAD_MARGIN))
