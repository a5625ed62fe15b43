"""Keyframed SMPL-X parameter tracks: poses described by joint names, eased interpolation.

A `Pose` names only what differs from neutral: joint rotations by SMPL-X joint name, expression
coefficients by name, a finger gesture per hand. `Clip.sample(t)` turns the keyframes into a
complete SMPL-X parameter set, interpolating each coefficient with smoothstep easing.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..body.skeleton import JOINT, SMPLX_NUM_BODY_JOINTS

_FACE_JOINTS = {"jaw": "jaw_pose", "left_eye_smplhf": "leye_pose", "right_eye_smplhf": "reye_pose"}
# Arms hang down and forward a little instead of the T-pose: the neutral stance of the clips.
RELAXED_ARMS = {
    "left_shoulder": (0.0, 0.0, -1.15), "right_shoulder": (0.0, 0.0, 1.15),
    "left_elbow": (0.0, -0.35, 0.0), "right_elbow": (0.0, 0.35, 0.0),
}  # fmt: skip


@dataclass(frozen=True)
class Pose:
    joints: Mapping[str, Sequence[float]] = field(default_factory=dict)  # name -> axis-angle
    expression: Mapping[str, float] = field(default_factory=dict)       # name -> coefficient
    left_hand: str | np.ndarray = "relaxed"   # gesture name or [15, 3] absolute pose
    right_hand: str | np.ndarray = "relaxed"
    global_orient: Sequence[float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Rig:
    """What a pose description needs to become parameters: names and gestures of the model."""

    expression_names: tuple[str, ...]
    gestures: Mapping[str, np.ndarray]   # right-hand gesture name -> [15, 3] absolute pose
    hand_mean: Mapping[str, np.ndarray]  # side -> [15, 3] the model's mean hand (0 if flat)
    num_betas: int = 10


def _mirror(pose: np.ndarray) -> np.ndarray:
    return pose * np.array([1.0, -1.0, -1.0])


def pose_to_params(pose: Pose, rig: Rig) -> dict[str, np.ndarray]:
    """A complete (unbatched) SMPL-X parameter dict for a pose description."""
    body = np.zeros((SMPLX_NUM_BODY_JOINTS, 3))
    out = {k: np.zeros(3) for k in _FACE_JOINTS.values()}
    for name, aa in {**RELAXED_ARMS, **pose.joints}.items():
        if name not in JOINT:
            raise KeyError(f"unknown joint '{name}'")
        if name in _FACE_JOINTS:
            out[_FACE_JOINTS[name]] = np.asarray(aa, dtype=np.float64)
        elif 1 <= JOINT[name] <= SMPLX_NUM_BODY_JOINTS:
            body[JOINT[name] - 1] = aa
        else:
            raise KeyError(f"joint '{name}' is posed through a hand gesture, not by name")
    expression = np.zeros(len(rig.expression_names))
    for name, value in pose.expression.items():
        if name not in rig.expression_names:
            raise KeyError(f"unknown expression '{name}'; known: {rig.expression_names}")
        expression[rig.expression_names.index(name)] = value
    for side, gesture in (("left", pose.left_hand), ("right", pose.right_hand)):
        if isinstance(gesture, str):
            if gesture not in rig.gestures:
                raise KeyError(f"unknown gesture '{gesture}'; known: {sorted(rig.gestures)}")
            absolute = np.asarray(rig.gestures[gesture], dtype=np.float64).reshape(15, 3)
            absolute = _mirror(absolute) if side == "left" else absolute
        else:
            absolute = np.asarray(gesture, dtype=np.float64).reshape(15, 3)
        out[f"{side}_hand_pose"] = absolute - rig.hand_mean[side]
    out.update(betas=np.zeros(rig.num_betas), expression=expression, body_pose=body,
               global_orient=np.asarray(pose.global_orient, dtype=np.float64), transl=np.zeros(3))
    return out


def _smoothstep(x: float) -> float:
    x = min(max(x, 0.0), 1.0)
    return x * x * (3.0 - 2.0 * x)


@dataclass(frozen=True)
class Clip:
    name: str
    keyframes: tuple[tuple[float, Pose], ...]  # (time in seconds, pose), times increasing

    def __post_init__(self) -> None:
        times = [t for t, _ in self.keyframes]
        if not times or any(b <= a for a, b in zip(times, times[1:], strict=False)) or times[0]:
            raise ValueError(f"clip '{self.name}': keyframe times must start at 0 and increase")

    @property
    def duration(self) -> float:
        return self.keyframes[-1][0]

    def sample(self, t: float, rig: Rig) -> dict[str, np.ndarray]:
        """Parameters at time t (clamped to the clip), eased between neighbouring keyframes."""
        times = [k for k, _ in self.keyframes]
        i = int(np.searchsorted(times, t, side="right")) - 1
        i = min(max(i, 0), len(times) - 1)
        a = pose_to_params(self.keyframes[i][1], rig)
        if i == len(times) - 1:
            return a
        b = pose_to_params(self.keyframes[i + 1][1], rig)
        w = _smoothstep((t - times[i]) / (times[i + 1] - times[i]))
        return {k: (1.0 - w) * a[k] + w * b[k] for k in a}


def chain(name: str, clips: Sequence[Clip]) -> Clip:
    """Play clips one after another (each clip's last pose leads into the next's first)."""
    keys, offset = [], 0.0
    for clip in clips:
        for t, pose in clip.keyframes:
            if keys and t == 0.0:
                offset += 0.4  # ease from the previous clip's end into this one
            keys.append((offset + t, pose))
        offset += clip.duration
    return Clip(name, tuple(keys))
