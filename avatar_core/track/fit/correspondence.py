"""Which body-model keypoint each MediaPipe landmark corresponds to.

The fitter's keypoint layout is fixed: face (68, iBUG order), left hand (21, MediaPipe hand
order), right hand (21), pose (33, BlazePose order). A pose landmark with no SMPL-X counterpart
gets weight 0.
"""

from __future__ import annotations

import numpy as np

# iBUG 68 -> MediaPipe face-mesh indices (averaged where two are given). The widely used
# correspondence (e.g. PeizhiYan/Mediapipe_2_Dlib_Landmarks); "right" is the person's right.
FACE_MP_TO_IBUG68: tuple[tuple[int, ...], ...] = (
    # jaw contour 0-16 (the person's right ear -> chin -> left ear)
    (127,), (234,), (93,), (132, 58), (58, 172), (136,), (150,), (176,), (152,), (400,),
    (379,), (365,), (397, 288), (361,), (323,), (454,), (356,),
    # brows 17-21 (right), 22-26 (left)
    (70,), (63,), (105,), (66,), (107,), (336,), (296,), (334,), (293,), (300,),
    # nose bridge 27-30, nostrils 31-35
    (168, 6), (197, 195), (5,), (4,), (75,), (97,), (2,), (326,), (305,),
    # eyes 36-41 (right), 42-47 (left)
    (33,), (160,), (158,), (133,), (153,), (144,), (362,), (385,), (387,), (263,), (373,),
    (380,),
    # outer lips 48-59, inner lips 60-67
    (61,), (39,), (37,), (0,), (267,), (269,), (291,), (405,), (314,), (17,), (84,), (181,),
    (78,), (82,), (13,), (312,), (308,), (317,), (14,), (87,),
)  # fmt: skip
NUM_FACE = 68
IBUG_CONTOUR = tuple(range(17))  # the model's dynamic (yaw-dependent) contour landmarks

# MediaPipe hand 21 -> SMPL-X joint name suffix, or a fingertip vertex ("tip:<finger>").
HAND_MP_TO_SMPLX: tuple[str, ...] = (
    "wrist",
    "thumb1", "thumb2", "thumb3", "tip:thumb",
    "index1", "index2", "index3", "tip:index",
    "middle1", "middle2", "middle3", "tip:middle",
    "ring1", "ring2", "ring3", "tip:ring",
    "pinky1", "pinky2", "pinky3", "tip:pinky",
)  # fmt: skip
NUM_HAND = 21

# BlazePose 33 -> SMPL-X joint ("joint:<name>") or semantic vertex ("vertex:<name>"); None:
# no counterpart (eye corners, mouth, legs).
POSE_MP_TO_SMPLX: tuple[str | None, ...] = (
    "vertex:nose", None, "vertex:leye", None, None, "vertex:reye", None,
    "vertex:lear", "vertex:rear", None, None,
    "joint:left_shoulder", "joint:right_shoulder", "joint:left_elbow", "joint:right_elbow",
    "joint:left_wrist", "joint:right_wrist",
    # pinky, index, thumb: nearest to the finger's first joint on studio renders
    # (bench/webcam_pose_hand_points.py); used only for a hand whose own landmarks are not seen.
    "joint:left_pinky1", "joint:right_pinky1", "joint:left_index1", "joint:right_index1",
    "joint:left_thumb1", "joint:right_thumb1",
    "joint:left_hip", "joint:right_hip", None, None, None, None, None, None, None, None,
)  # fmt: skip
NUM_POSE = 33

# `smplx.vertex_ids['smplx']`: SMPL-X vertex index of each semantic point.
SMPLX_SEMANTIC_VERTEX_IDS = {
    "nose": 9120, "reye": 9929, "leye": 9448, "rear": 616, "lear": 6,
    "rthumb": 8079, "rindex": 7669, "rmiddle": 7794, "rring": 7905, "rpinky": 8022,
    "lthumb": 5361, "lindex": 4933, "lmiddle": 5058, "lring": 5169, "lpinky": 5286,
}  # fmt: skip

# Offsets of each group in the fitter's keypoint layout.
FACE_SLICE = slice(0, NUM_FACE)
LEFT_HAND_SLICE = slice(NUM_FACE, NUM_FACE + NUM_HAND)
RIGHT_HAND_SLICE = slice(NUM_FACE + NUM_HAND, NUM_FACE + 2 * NUM_HAND)
POSE_SLICE = slice(NUM_FACE + 2 * NUM_HAND, NUM_FACE + 2 * NUM_HAND + NUM_POSE)
NUM_KEYPOINTS = POSE_SLICE.stop
GROUP_SLICES = {"face": FACE_SLICE, "left_hand": LEFT_HAND_SLICE,
                "right_hand": RIGHT_HAND_SLICE, "pose": POSE_SLICE}


def face_468_to_ibug68(points: np.ndarray) -> np.ndarray:
    """[468, C] MediaPipe face mesh -> [68, C] iBUG layout (pairs averaged)."""
    pts = np.asarray(points, dtype=np.float64)
    return np.stack([pts[list(ids)].mean(axis=0) for ids in FACE_MP_TO_IBUG68])
