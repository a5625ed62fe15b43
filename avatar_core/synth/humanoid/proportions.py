"""The seeded individual: nominal joints and anatomical numbers (`_Body`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .primitives import _unit


@dataclass(frozen=True)
class _Body:
    """Anatomical numbers of one (seeded) individual, left side and midline."""

    j: dict  # joint name -> [3] nominal rest position
    height: float  # vertical scale of trunk and legs
    girth: float
    shoulders: float
    hips: float
    head_o: np.ndarray  # [3] origin of the head-local frame (eye level, midline)
    head_s: float  # head-local -> world scale
    hand_s: float
    floor: float
    fingers: tuple  # per finger (j1, j2, j3, tip, radius, direction), SMPL-X order


_TEMPLATE = {  # nominal joints (metres) before the seeded proportions
    "pelvis": (0.0, 0.0, 0.0), "left_hip": (0.072, -0.085, 0.0),
    "left_knee": (0.092, -0.49, 0.008), "left_ankle": (0.085, -0.875, -0.012),
    "spine1": (0.0, 0.105, -0.012), "spine2": (0.0, 0.235, -0.008), "spine3": (0.0, 0.29, 0.0),
    "neck": (0.0, 0.49, -0.016), "left_collar": (0.07, 0.42, -0.015),
    "left_shoulder": (0.172, 0.425, -0.02), "left_elbow": (0.43, 0.425, -0.03),
    "left_wrist": (0.68, 0.425, -0.025),
}  # fmt: skip
_HEAD_EYE_Y = 0.645  # head-local origin height
_HEAD_LOCAL_JOINTS = {"head": (0.0, -0.060, -0.008), "jaw": (0.0, -0.043, 0.008),
                      "left_eye_smplhf": (0.0325, 0.0, 0.0705)}


_EYE_R = 0.0118
# name, MCP offset from the wrist (left hand), direction, segment lengths, radius
_FINGERS = (
    ("index", (0.094, 0.001, 0.026), (1.0, 0.0, 0.05), (0.039, 0.023, 0.021), 0.0088),
    ("middle", (0.097, 0.001, 0.006), (1.0, 0.0, 0.0), (0.043, 0.026, 0.022), 0.0092),
    ("pinky", (0.085, -0.001, -0.032), (1.0, 0.0, -0.09), (0.032, 0.020, 0.020), 0.0075),
    ("ring", (0.092, 0.0, -0.013), (1.0, 0.0, -0.04), (0.040, 0.025, 0.021), 0.0086),
    ("thumb", (0.020, -0.008, 0.012), (1.0, -0.15, 0.62), (0.046, 0.034, 0.028), 0.0105),
)


def _body(seed: int) -> _Body:
    """Seeded proportions (a few % each) applied to the template skeleton."""
    rng = np.random.default_rng(seed)
    height, shoulders, hips, girth, head, arms, legs, hands = 1.0 + 0.03 * rng.uniform(-1, 1, 8)
    legs *= height
    t = {k: np.array(v, dtype=np.float64) for k, v in _TEMPLATE.items()}
    j = {}
    for name in ("pelvis", "spine1", "spine2", "spine3", "neck"):
        j[name] = t[name] * [1.0, height, 1.0]
    j["left_hip"] = t["left_hip"] * [hips, height, 1.0]
    for name in ("left_knee", "left_ankle"):
        j[name] = j["left_hip"] + (t[name] - t["left_hip"]) * [hips, legs, 1.0]
    j["left_collar"] = t["left_collar"] * [shoulders, height, 1.0]
    j["left_shoulder"] = t["left_shoulder"] * [shoulders, height, 1.0]
    for name in ("left_elbow", "left_wrist"):
        j[name] = j["left_shoulder"] + (t[name] - t["left_shoulder"]) * arms * height
    head_o = np.array([0.0, _HEAD_EYE_Y * height, 0.0])
    head_s = head * (0.5 + 0.5 * height)
    for name, p in _HEAD_LOCAL_JOINTS.items():
        j[name] = head_o + head_s * np.array(p)
    hand_s = hands * height
    fingers = []
    for _, off, d, lengths, r in _FINGERS:
        d = _unit(np.array(d))
        p1 = j["left_wrist"] + hand_s * np.array(off)
        p2 = p1 + hand_s * lengths[0] * d
        p3 = p2 + hand_s * lengths[1] * d
        tip = p3 + hand_s * lengths[2] * d
        fingers.append((p1, p2, p3, tip, hand_s * r, d))
    floor = float(j["left_ankle"][1] - 0.075 * legs)
    return _Body(j, float(height), float(girth), float(shoulders), float(hips), head_o,
                 float(head_s), float(hand_s), floor, tuple(fingers))
