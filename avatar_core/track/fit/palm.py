"""The palm's orientation from one frame's hand landmarks, by the hand model's own geometry.

The wrist and the four finger bases (MediaPipe 0, 5, 9, 13, 17) are rigid on the hand: the
model's wrist, index1, middle1, ring1 and pinky1 joints, whose offsets from the wrist turn
with the wrist's world rotation alone. Their landmarks in image pixels with MediaPipe's
relative depth (z x `HAND_Z_SCALE`: f (d_k - d_wrist) / d_wrist in px) are lifted back through
the camera (x = (u - cx)(1 + w / f): exact for that depth, so a hand off the optical axis is
not seen turned) and matched to the model's rest offsets by Kabsch / Procrustes, which gives
the wrist's world rotation directly, whatever the fingers do.

That rotation is a second opinion for the fitter (`FrameFitter`): where its wrist ends far
from it (a palm fitted as the back of the hand, or a cold start that settled on the wrong
side), the fit is tried again from it and the lower cost wins. It is not a fit term: on the
renders it is less accurate than the fit where the fit is right (docs/tracking.md).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

# MediaPipe hand landmarks on the rigid palm, and the model joints they correspond to.
PALM_LANDMARKS = (0, 5, 9, 13, 17)
PALM_JOINTS = ("wrist", "index1", "middle1", "ring1", "pinky1")
# The points' spread must be at least this share of their extent in the second direction:
# collinear or coincident points do not fix a rotation.
MIN_PLANARITY = 0.05


def kabsch(source: np.ndarray, target: np.ndarray) -> np.ndarray | None:
    """The rotation R [3, 3] minimizing sum_k |R (a_k - mean a) - s (b_k - mean b)|^2 over
    rotations (any positive scale s: the shape, not its size) for points a = `source`
    [N, 3], b = `target` [N, 3]; None when the points cannot fix a rotation (fewer than 3,
    non-finite, collinear or coincident)."""
    a = np.asarray(source, dtype=np.float64)
    b = np.asarray(target, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 2 or a.shape[1] != 3 or a.shape[0] < 3:
        return None
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        return None
    a0, b0 = a - a.mean(0), b - b.mean(0)
    for pts in (a0, b0):
        sv = np.linalg.svd(pts, compute_uv=False)
        if sv[0] <= 0 or sv[1] < MIN_PLANARITY * sv[0]:
            return None
    u, _, vt = np.linalg.svd(a0.T @ b0)             # H = A^T B = U S V^T
    d = 1.0 if np.linalg.det(vt.T @ u.T) >= 0 else -1.0  # a proper rotation, never a mirror
    return vt.T @ np.diag([1.0, 1.0, d]) @ u.T


def palm_points(hand: np.ndarray, z_scale: float, focal: float,
                center: tuple[float, float]) -> np.ndarray:
    """MediaPipe hand landmarks [21, 3] (px, z relative to the wrist, smaller nearer) -> the
    palm points in model axes [5, 3] (x right, y up, z toward the camera), in px at the
    wrist's distance: the pixel rays scaled to each point's depth (1 + w / f, w = z_scale z
    relative to the wrist)."""
    h = np.asarray(hand, dtype=np.float64)[list(PALM_LANDMARKS)]
    w = z_scale * (h[:, 2] - h[0, 2])
    grow = 1.0 + w / focal
    return np.stack([(h[:, 0] - center[0]) * grow, -(h[:, 1] - center[1]) * grow, -w], axis=1)


def palm_rotation(hand: np.ndarray, rest_offsets: np.ndarray, z_scale: float, focal: float,
                  center: tuple[float, float]) -> np.ndarray | None:
    """The wrist's world rotation [3, 3] that turns the model's rest palm (`rest_offsets`
    [5, 3]: the `PALM_JOINTS` at rest) onto the landmarks `hand` [21, 3] seen by a pinhole
    (`focal` px, principal point `center`); None when the landmarks cannot tell (missing,
    NaN, collapsed)."""
    hand = np.asarray(hand, dtype=np.float64)
    if hand.shape != (21, 3) or not focal > 0:
        return None
    return kabsch(rest_offsets, palm_points(hand, z_scale, focal, center))


def rotation_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Geodesic angle (deg) between two rotations [3, 3]."""
    cos = (np.trace(a.T @ b) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def axis_angle(rot: np.ndarray) -> np.ndarray:
    """Rotation [3, 3] -> axis-angle [3] (angle in [0, pi])."""
    return Rotation.from_matrix(np.asarray(rot, dtype=np.float64)).as_rotvec()
