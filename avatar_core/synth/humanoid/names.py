"""Public name tables of the humanoid (materials, shape and expression coefficients,
semantic vertices) and the index maps the builders share."""

from __future__ import annotations

import numpy as np

from avatar_core.body.skeleton import SMPLX_NUM_JOINTS, SMPLX_PART_NAMES

MATERIALS: tuple[str, ...] = ("skin", "hair", "eyebrow", "lips", "eye_white", "iris", "pupil",
                              "mouth_interior", "teeth", "shirt", "trousers", "shoes")


SHAPE_NAMES: tuple[str, ...] = ("height", "weight", "shoulder_width", "head_size", "arm_length",
                                "neck_length", "chest_depth", "hip_width", "hand_size",
                                "face_width")


EXPRESSION_NAMES: tuple[str, ...] = ("smile", "grin", "lips_part", "pucker", "cheek_puff",
                                     "blink_left", "blink_right", "brows_raise", "brows_lower",
                                     "frown")


SEMANTIC_NAMES: tuple[str, ...] = (
    "nose", "reye", "leye", "rear", "lear", "rthumb", "rindex", "rmiddle", "rring", "rpinky",
    "lthumb", "lindex", "lmiddle", "lring", "lpinky", "LBigToe", "LSmallToe", "LHeel",
    "RBigToe", "RSmallToe", "RHeel",
)  # fmt: skip
_MAT = {name: i for i, name in enumerate(MATERIALS)}
_PART = {name: i for i, name in enumerate(SMPLX_PART_NAMES)}
_NJ = SMPLX_NUM_JOINTS
# SMPL-X hand joint order: index, middle, pinky, ring, thumb (three joints each).
_FINGER_NAMES = ("index", "middle", "pinky", "ring", "thumb")
# iBUG-68 left/right flip; landmarks are iBUG 17..67, the contour iBUG 0..16.
_IBUG_FLIP = np.array(
    [16, 15, 14, 13, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0,
     26, 25, 24, 23, 22, 21, 20, 19, 18, 17, 27, 28, 29, 30, 35, 34, 33, 32, 31,
     45, 44, 43, 42, 47, 46, 39, 38, 37, 36, 41, 40,
     54, 53, 52, 51, 50, 49, 48, 59, 58, 57, 56, 55, 64, 63, 62, 61, 60, 67, 66, 65])  # fmt: skip
