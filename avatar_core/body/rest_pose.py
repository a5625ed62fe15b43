"""The rest pose of a live avatar: what a new session, ``drive {reset: true}``, a room seat
whose performer left and ``telesplat render --motion rest`` show.

Not the model's zero pose (a T-pose, hands outside any upper-body framing) but a relaxed
stance: arms down and slightly forward, elbows bent about 60 degrees, hands in front of the
hips and belly. The angles were fitted by least squares on the synthetic body (left wrist at
(0.17, 0.10, 0.20) m, left elbow at (0.27, 0.21, 0.00) m in the model frame); the right arm is
the mirror image. Hands and face stay at zero (the model's mean hand, a neutral face).
"""

from __future__ import annotations

from types import MappingProxyType

import numpy as np

from .skeleton import JOINT, SMPLX_NUM_BODY_JOINTS

__all__ = ["REST_ARMS", "rest_body_pose"]

REST_ARMS = MappingProxyType({
    "left_shoulder": (0.126, -0.28, -1.259), "right_shoulder": (0.126, 0.28, 1.259),
    "left_elbow": (0.116, -1.063, -0.315), "right_elbow": (0.116, 1.063, 0.315),
})  # fmt: skip


def rest_body_pose() -> np.ndarray:
    """``body_pose`` [21, 3] float32 of the rest pose (a new array each call)."""
    pose = np.zeros((SMPLX_NUM_BODY_JOINTS, 3), dtype=np.float32)
    for name, axis_angle in REST_ARMS.items():
        pose[JOINT[name] - 1] = axis_angle
    return pose
