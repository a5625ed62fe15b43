"""Keyframed SMPL-X parameter tracks: poses described by joint names, eased interpolation.

A `Pose` names only what differs from neutral: joint rotations by SMPL-X joint name, expression
coefficients by name, a finger gesture per hand. `Clip.sample(t)` turns the keyframes into a
complete SMPL-X parameter set, interpolating each coefficient with smoothstep easing.

Anything with a `name`, a `duration` and `sample(t, rig)` is a `Track`: clips, `blend`s of two
tracks and `chain`s of several. `check_joint_limits` reports rotations beyond what a human
joint does (`JOINT_LIMITS_DEG`, body/joint_limits.py) and expression coefficients outside
[-1.5, 1.5].
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from ..body.joint_limits import EXPRESSION_LIMIT, JOINT_LIMITS_DEG, RELAXED_ARMS
from ..body.skeleton import (
    JOINT,
    LEFT_HAND_JOINTS,
    RIGHT_HAND_JOINTS,
    SMPLX_JOINT_NAMES,
    SMPLX_NUM_BODY_JOINTS,
)

_FACE_JOINTS = {"jaw": "jaw_pose", "left_eye_smplhf": "leye_pose", "right_eye_smplhf": "reye_pose"}


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


@runtime_checkable
class Track(Protocol):
    """A motion: complete SMPL-X parameters at any time t (clamped to [0, duration])."""

    @property
    def name(self) -> str: ...

    @property
    def duration(self) -> float: ...

    def sample(self, t: float, rig: Rig) -> dict[str, np.ndarray]: ...


def _sample_clamped(track: Track, t: float, rig: Rig) -> dict[str, np.ndarray]:
    return track.sample(min(max(t, 0.0), track.duration), rig)


def _mix(a: Mapping[str, np.ndarray], b: Mapping[str, np.ndarray],
         w: float) -> dict[str, np.ndarray]:
    """(1 - w) a + w b, parameter by parameter (axis-angles too: fine for nearby poses)."""
    if a.keys() != b.keys():
        raise KeyError(f"tracks give different parameters: {sorted(a)} vs {sorted(b)}")
    return {k: (1.0 - w) * np.asarray(a[k]) + w * np.asarray(b[k]) for k in a}


@dataclass(frozen=True)
class Blend:
    """Two tracks played together, mixed with `weight` (0: only `a`, 1: only `b`)."""

    name: str
    a: Track
    b: Track
    weight: float | Callable[[float], float]  # constant, or a function of time in seconds

    def __post_init__(self) -> None:
        if not callable(self.weight) and not 0.0 <= self.weight <= 1.0:
            raise ValueError(f"blend '{self.name}': weight must lie in [0, 1], got {self.weight}")

    @property
    def duration(self) -> float:
        return max(self.a.duration, self.b.duration)

    def sample(self, t: float, rig: Rig) -> dict[str, np.ndarray]:
        t = min(max(t, 0.0), self.duration)
        w = float(self.weight(t)) if callable(self.weight) else float(self.weight)
        if not 0.0 <= w <= 1.0:  # also catches NaN
            raise ValueError(f"blend '{self.name}': weight({t:.3f}) = {w} is outside [0, 1]")
        # The shorter track holds its last pose.
        return _mix(_sample_clamped(self.a, t, rig), _sample_clamped(self.b, t, rig), w)


def blend(name: str, a: Track, b: Track, weight: float | Callable[[float], float]) -> Blend:
    """A track mixing the parameters of `a` and `b`; `weight` is a constant in [0, 1] or a
    function of time (seconds) into [0, 1]. Lasts as long as the longer of the two."""
    return Blend(name, a, b, weight)


@dataclass(frozen=True)
class Chain:
    """Tracks one after another, each joined to the next by a `crossfade`-second transition in
    which the previous track's last pose eases into the next track's first."""

    name: str
    tracks: tuple[Track, ...]
    crossfade: float = 0.4

    def __post_init__(self) -> None:
        if not self.tracks:
            raise ValueError(f"chain '{self.name}': needs at least one track")
        if self.crossfade < 0.0:
            raise ValueError(f"chain '{self.name}': crossfade must be >= 0")

    @property
    def duration(self) -> float:
        return sum(tr.duration for tr in self.tracks) + self.crossfade * (len(self.tracks) - 1)

    def sample(self, t: float, rig: Rig) -> dict[str, np.ndarray]:
        start = 0.0
        for i, track in enumerate(self.tracks):  # bounded by the number of tracks
            end = start + track.duration
            if t <= end or i == len(self.tracks) - 1:
                return _sample_clamped(track, t - start, rig)
            if t < end + self.crossfade:
                # Smoothstep: both ends are reached with zero slope, so a track that comes to
                # rest leaves and enters the transition without a kink.
                w = _smoothstep((t - end) / self.crossfade)
                return _mix(track.sample(track.duration, rig),
                            self.tracks[i + 1].sample(0.0, rig), w)
            start = end + self.crossfade
        raise AssertionError("unreachable: the last track answers every later time")


def chain(name: str, clips: Sequence[Track], crossfade: float = 0.4) -> Chain:
    """Play tracks one after another; see `Chain`. Continuous for any tracks when
    crossfade > 0 (with 0, a jump where a track does not end where the next begins)."""
    return Chain(name, tuple(clips), crossfade)


def check_joint_limits(params: Mapping[str, np.ndarray], rig: Rig | None = None) -> list[str]:
    """A description of every rotation beyond `JOINT_LIMITS_DEG`, every expression coefficient
    outside [-EXPRESSION_LIMIT, EXPRESSION_LIMIT] and every non-finite value in one unbatched
    parameter set; empty when all is plausible. With a `rig`, finger poses are checked with
    the model's mean hand added (the rotation the fingers really make) and expressions by name.
    """
    out = []
    for key, value in params.items():
        if not np.isfinite(np.asarray(value, dtype=np.float64)).all():
            out.append(f"{key}: not finite")
    angles = _joint_angles_deg(params, rig)
    for name, angle in angles.items():
        limit = JOINT_LIMITS_DEG.get(name)
        if limit is not None and angle > limit:
            out.append(f"{name}: {angle:.1f} deg exceeds the limit of {limit:.0f} deg")
    expression = np.asarray(params.get("expression", np.zeros(0)), dtype=np.float64).ravel()
    names = rig.expression_names if rig else ()
    for i, value in enumerate(expression):
        if abs(value) > EXPRESSION_LIMIT:
            label = names[i] if i < len(names) else f"expression[{i}]"
            out.append(f"{label}: {value:.2f} outside [-{EXPRESSION_LIMIT}, {EXPRESSION_LIMIT}]")
    return out


def _joint_angles_deg(params: Mapping[str, np.ndarray], rig: Rig | None) -> dict[str, float]:
    """Rotation angle (degrees) of every joint the parameters pose, by SMPL-X joint name."""
    rows: dict[str, np.ndarray] = {}
    if "body_pose" in params:
        body = np.asarray(params["body_pose"], dtype=np.float64).reshape(-1, 3)  # [21, 3]
        rows.update(zip(SMPLX_JOINT_NAMES[1:1 + len(body)], body, strict=True))
    for joint, key in _FACE_JOINTS.items():
        if key in params:
            rows[joint] = np.asarray(params[key], dtype=np.float64).reshape(3)
    for side, joints in (("left", LEFT_HAND_JOINTS), ("right", RIGHT_HAND_JOINTS)):
        hand = np.asarray(params.get(f"{side}_hand_pose", np.zeros(0)), dtype=np.float64)
        if hand.size != 45:
            continue  # absent, or PCA coefficients: no per-joint rotation to check
        hand = hand.reshape(15, 3) + (rig.hand_mean[side] if rig else 0.0)  # [15, 3]
        rows.update(zip((SMPLX_JOINT_NAMES[j] for j in joints), hand, strict=True))
    return {name: float(np.degrees(np.linalg.norm(aa))) for name, aa in rows.items()}
