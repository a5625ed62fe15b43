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

FORWARD = np.array([0.0, 0.0, 1.0])  # the rest stance's facing direction


def _unit(v: np.ndarray) -> np.ndarray | None:
    n = float(np.linalg.norm(v))
    return v / n if np.isfinite(n) and n > 1e-9 else None


def elbow_axes(rest_joints: np.ndarray) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Elbow joint -> (flexion axis [3], sideways row [3]), unit vectors in the rest frame
    (an SMPL-X joint's axis-angle is expressed there). A side whose forearm is degenerate
    (zero length, or pointing forward) gets no entry."""
    j = np.asarray(rest_joints, dtype=np.float64)
    out = {}
    for side in ("left", "right"):
        elbow = JOINT[f"{side}_elbow"]
        bone = _unit(j[JOINT[f"{side}_wrist"]] - j[elbow])
        if bone is None:
            continue
        axis = _unit(np.cross(bone, FORWARD))
        if axis is None:
            continue
        out[elbow] = (axis, np.cross(axis, bone))
    return out


def sideways_matrix(axes: dict[int, tuple[np.ndarray, np.ndarray]],
                    joint_columns: dict[int, np.ndarray], size: int) -> np.ndarray:
    """[E, size] the linear map from the free-variable vector to each elbow's sideways bend."""
    rows = np.zeros((len(axes), size))
    for r, (k, (_, sideways)) in enumerate(axes.items()):
        rows[r, joint_columns[k]] = sideways
    return rows


def flexion_matrix(axes: dict[int, tuple[np.ndarray, np.ndarray]],
                   joint_columns: dict[int, np.ndarray], size: int) -> np.ndarray:
    """[E, size] the linear map from the free-variable vector to each elbow's flexion (rad,
    positive toward the front; negative is bending backward)."""
    rows = np.zeros((len(axes), size))
    for r, (k, (axis, _)) in enumerate(axes.items()):
        rows[r, joint_columns[k]] = axis
    return rows
