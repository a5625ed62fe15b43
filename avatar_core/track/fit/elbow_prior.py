"""The elbows' hinge prior: an elbow flexes the forearm toward the front of the body and turns
it about its own bone (pronation, which SMPL-X shares between elbow and wrist); it does not
bend sideways, and it does not bend backward past straight.

Monocular landmarks pin the shoulder, elbow and wrist points, not the upper arm's twist: with
a free 3-DoF elbow the fit can twist the upper arm and bend the elbow sideways to reach the
same points. Held to its hinge, the elbow's bend plane fixes that twist.

The axes come from the model's rest geometry alone (the rest stance faces +z):
bone = elbow -> wrist, flexion axis = bone x forward (the forearm then moves toward +z),
and the sideways row = forward made orthogonal to the bone.
"""

from __future__ import annotations

import numpy as np

from ...body.skeleton import JOINT
from .hand_prior import unit_or_none

FORWARD = np.array([0.0, 0.0, 1.0])  # the rest stance's facing direction


def elbow_axes(rest_joints: np.ndarray) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Elbow joint -> (flexion axis [3], sideways row [3]), unit vectors in the rest frame
    (an SMPL-X joint's axis-angle is expressed there). A side whose forearm is degenerate
    (zero length, or pointing forward) gets no entry."""
    j = np.asarray(rest_joints, dtype=np.float64)
    out = {}
    for side in ("left", "right"):
        elbow = JOINT[f"{side}_elbow"]
        bone = unit_or_none(j[JOINT[f"{side}_wrist"]] - j[elbow])
        if bone is None:
            continue
        axis = unit_or_none(np.cross(bone, FORWARD))
        if axis is None:
            continue
        out[elbow] = (axis, np.cross(axis, bone))
    return out
