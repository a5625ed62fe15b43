"""Kinematic trees and part names of the SMPL-X, FLAME and MANO families.

Joint order and parents follow the official model files (and the `smplx` package).
"""

from __future__ import annotations

SMPLX_JOINT_NAMES: tuple[str, ...] = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar",
    "right_collar", "head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
    "left_wrist", "right_wrist", "jaw", "left_eye_smplhf", "right_eye_smplhf",
    "left_index1", "left_index2", "left_index3", "left_middle1", "left_middle2", "left_middle3",
    "left_pinky1", "left_pinky2", "left_pinky3", "left_ring1", "left_ring2", "left_ring3",
    "left_thumb1", "left_thumb2", "left_thumb3",
    "right_index1", "right_index2", "right_index3", "right_middle1", "right_middle2",
    "right_middle3", "right_pinky1", "right_pinky2", "right_pinky3", "right_ring1",
    "right_ring2", "right_ring3", "right_thumb1", "right_thumb2", "right_thumb3",
)  # fmt: skip

SMPLX_PARENTS: tuple[int, ...] = (
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 15, 15, 15,
    20, 25, 26, 20, 28, 29, 20, 31, 32, 20, 34, 35, 20, 37, 38,
    21, 40, 41, 21, 43, 44, 21, 46, 47, 21, 49, 50, 21, 52, 53,
)  # fmt: skip

SMPLX_NUM_JOINTS = 55
SMPLX_NUM_BODY_JOINTS = 21  # joints 1..21: `body_pose[21, 3]`
SMPLX_NUM_HAND_JOINTS = 15

JOINT = {name: i for i, name in enumerate(SMPLX_JOINT_NAMES)}
LEFT_HAND_JOINTS = tuple(range(25, 40))
RIGHT_HAND_JOINTS = tuple(range(40, 55))

# FLAME: root (global rotation), neck, jaw, left eye, right eye.
FLAME_JOINT_NAMES = ("root", "neck", "jaw", "left_eye", "right_eye")
FLAME_PARENTS = (-1, 0, 1, 1, 1)
# SMPL-X joint that plays the role of each FLAME joint (fusion and the synthetic sibling).
FLAME_TO_SMPLX_JOINT = (JOINT["neck"], JOINT["head"], JOINT["jaw"],
                        JOINT["left_eye_smplhf"], JOINT["right_eye_smplhf"])  # fmt: skip

# MANO: wrist then index, middle, pinky, ring, thumb (three joints each), as SMPL-X's hands.
MANO_PARENTS = (-1, 0, 1, 2, 0, 4, 5, 0, 7, 8, 0, 10, 11, 0, 13, 14)
MANO_TO_SMPLX_JOINT = {
    "left": (JOINT["left_wrist"], *LEFT_HAND_JOINTS),
    "right": (JOINT["right_wrist"], *RIGHT_HAND_JOINTS),
}

# Part names of the widely used SMPL-X vertex segmentation (`smplx_vert_segmentation.json`).
SMPLX_PART_NAMES = (
    "hips", "leftUpLeg", "rightUpLeg", "spine", "leftLeg", "rightLeg", "spine1", "leftFoot",
    "rightFoot", "spine2", "leftToeBase", "rightToeBase", "neck", "leftShoulder",
    "rightShoulder", "head", "leftArm", "rightArm", "leftForeArm", "rightForeArm", "leftHand",
    "rightHand", "leftHandIndex1", "rightHandIndex1", "leftEye", "rightEye", "eyeballs",
)  # fmt: skip
UPPER_BODY_PARTS = (
    "spine", "spine1", "spine2", "neck", "leftShoulder", "rightShoulder", "head", "leftArm",
    "rightArm", "leftForeArm", "rightForeArm", "leftHand", "rightHand", "leftHandIndex1",
    "rightHandIndex1", "leftEye", "rightEye", "eyeballs",
)  # fmt: skip
LOWER_BODY_PARTS = tuple(p for p in SMPLX_PART_NAMES if p not in UPPER_BODY_PARTS)


def swap_left_right(name: str) -> str:
    """Name of the mirrored joint or part ('left_wrist' <-> 'right_wrist', 'leftArm' <-> ...)."""
    for a, b in (("left", "right"), ("Left", "Right")):
        if a in name:
            return name.replace(a, b)
        if b in name:
            return name.replace(b, a)
    return name


def mirrored_joint_index() -> tuple[int, ...]:
    """For each SMPL-X joint, the index of its left/right mirror (itself on the midline)."""
    return tuple(JOINT[swap_left_right(n)] for n in SMPLX_JOINT_NAMES)
