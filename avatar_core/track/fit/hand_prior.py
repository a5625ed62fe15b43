"""The fingers' hinge prior: a finger's middle and end joints bend about one axis, and no
finger turns about its own bone.

The axes come from the hand model's rest geometry alone: a finger joint flexes about
bone x palm normal (the bone from the joint to its child, the palm's normal from the wrist,
index1 and pinky1 joints). The middle and end joints of all five fingers (PIP / DIP, and the
thumb's MCP / IP) are hinges: their rotation off that axis is penalized; the four finger
bases (MCP) may also spread sideways, so only their twist about the bone is. The thumb's base
(CMC) is left free. The fingers' end joints have no child joint: their bone runs from the
parent. On the synthetic rig every gesture of the motion library bends the fingers about
these axes to within ~6 deg (off-axis at most ~10% of the bend), so the prior takes 24 of the
45 finger degrees of freedom, the ones monocular landmarks pin worst, nearly out
(docs/tracking.md).

`hinge_rows(rest_joints, parents, side)` gives, per hand joint, the directions [R, 3] whose
components of the joint's full axis-angle (mean hand included) the prior drives to 0.
"""

from __future__ import annotations

import numpy as np

from ...body.skeleton import JOINT

HINGES = ("index2", "index3", "middle2", "middle3", "ring2", "ring3", "pinky2", "pinky3",
          "thumb2", "thumb3")
BASES = ("index1", "middle1", "ring1", "pinky1")


def unit_or_none(v: np.ndarray) -> np.ndarray | None:
    """v / |v|, or None for a zero-length or non-finite v."""
    n = float(np.linalg.norm(v))
    return v / n if np.isfinite(n) and n > 1e-9 else None


def hinge_rows(rest_joints: np.ndarray, parents: np.ndarray, side: str
               ) -> dict[int, np.ndarray]:
    """Joint index -> the unit directions [R, 3] (rest frame) a finger joint must not turn
    about: two per hinge (everything but the flexion axis), one per finger base (the bone,
    its twist). A joint whose bone or palm is degenerate in the model gets no rows."""
    j = np.asarray(rest_joints, dtype=np.float64)
    parents = np.asarray(parents)
    wrist = j[JOINT[f"{side}_wrist"]]
    normal = unit_or_none(np.cross(j[JOINT[f"{side}_index1"]] - wrist,
                                   j[JOINT[f"{side}_pinky1"]] - wrist))
    if normal is None:
        return {}
    out: dict[int, np.ndarray] = {}
    for names, hinge in ((HINGES, True), (BASES, False)):
        for name in names:
            k = JOINT[f"{side}_{name}"]
            children = np.flatnonzero(parents == k)
            bone = unit_or_none(j[children[0]] - j[k] if len(children) else j[k] - j[parents[k]])
            if bone is None:
                continue
            if not hinge:
                out[k] = bone[None]
                continue
            axis = unit_or_none(np.cross(bone, normal))
            if axis is None:
                continue
            other = np.cross(axis, bone)  # bone, other: an orthonormal basis of axis's complement
            out[k] = np.stack([bone, other])
    return out


def hinge_matrix(rows: dict[int, np.ndarray], joint_columns: dict[int, np.ndarray],
                 size: int) -> np.ndarray:
    """[R, size] the linear map from the free-variable vector to the off-axis components:
    `rows` (joint -> directions [r, 3]) placed on each joint's three columns
    (`joint_columns`: joint -> [3] column indices)."""
    blocks = []
    for k, dirs in rows.items():
        block = np.zeros((len(dirs), size))
        block[:, joint_columns[k]] = dirs
        blocks.append(block)
    return np.concatenate(blocks) if blocks else np.zeros((0, size))
