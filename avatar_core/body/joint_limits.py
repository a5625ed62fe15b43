"""Plausible ranges of SMPL-X parameters and the neutral stance, shared by the tracker's fitter
(its priors and initial pose), the motion library (its checks) and the studio's actors."""

from __future__ import annotations

from .skeleton import LEFT_HAND_JOINTS, RIGHT_HAND_JOINTS, SMPLX_JOINT_NAMES

# Arms hang down and forward a little instead of the T-pose: the neutral stance of the clips.
RELAXED_ARMS = {
    "left_shoulder": (0.0, 0.0, -1.15), "right_shoulder": (0.0, 0.0, 1.15),
    "left_elbow": (0.0, -0.35, 0.0), "right_elbow": (0.0, 0.35, 0.0),
}  # fmt: skip
# Largest rotation angle (degrees) a joint plausibly reaches from the rest pose, whatever the
# axis: generous bounds that catch a wrong sign or a swapped axis, not an anatomy model.
JOINT_LIMITS_DEG = {
    "left_hip": 120.0, "right_hip": 120.0, "left_knee": 150.0, "right_knee": 150.0,
    "left_ankle": 50.0, "right_ankle": 50.0, "left_foot": 40.0, "right_foot": 40.0,
    "spine1": 30.0, "spine2": 30.0, "spine3": 30.0, "neck": 50.0, "head": 50.0,
    "left_collar": 20.0, "right_collar": 20.0, "left_shoulder": 150.0, "right_shoulder": 150.0,
    "left_elbow": 150.0, "right_elbow": 150.0, "left_wrist": 80.0, "right_wrist": 80.0,
    "jaw": 30.0, "left_eye_smplhf": 30.0, "right_eye_smplhf": 30.0,
    **{SMPLX_JOINT_NAMES[j]: 110.0 for j in (*LEFT_HAND_JOINTS, *RIGHT_HAND_JOINTS)},
}  # fmt: skip
EXPRESSION_LIMIT = 1.5  # |coefficient| of a plausible expression
