"""A stream of frames -> a stream of SMPL-X parameters: warm starts, One Euro smoothing, and
the lost-track policy.

Each part of the body belongs to one landmark group (face, left hand, right hand, pose), each
wrist to its own (seen with its hand, or with the pose model's points of that hand), and with
`hold_arms` each arm (shoulder, elbow) to its own, seen while anything below the shoulder is
(an arm out of view has nothing to fit, and the fit's free arm drifts). While a
group is seen its parameters come from the fit; when it is lost they hold their last fitted
value for `hold_s`, then ease to the neutral stance over `relax_s`: fingers lost while the
pose still places the hand keep their last confident state, then ease to the relaxed hand,
while the wrist follows the pose. A group never seen stays neutral. With nothing seen for
longer than `hold_s` the next detection starts cold (placement solved again) instead of warm
from a stale pose.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from ...body.models import SMPLXModel
from ...body.skeleton import JOINT
from .camera import WebcamCamera
from .fitter import FitConfig, FitResult, FrameFitter
from .gaze import gaze_solver
from .observations import (
    Observations,
    arm_seen,
    pose_hand_seen,
    without_edge_arm_points,
    without_pose_hands,
)
from .one_euro import OneEuroFilter, ParamSmoother
from .palm import rotation_angle_deg
from .world_correction import WorldCorrection, correct_world
from .world_cues import ARM_BONES, SHOULDER_LINE

# Parameter -> owning group; body_pose rows listed separately (rows = joint index - 1).
GROUP_OF_PARAM = {"expression": "face", "jaw_pose": "face", "leye_pose": "face",
                  "reye_pose": "face", "left_hand_pose": "left_hand",
                  "right_hand_pose": "right_hand", "global_orient": "pose", "transl": "pose"}
GROUP_OF_BODY_JOINT = {"neck": "face", "head": "face", "left_wrist": "left_wrist",
                       "right_wrist": "right_wrist", "left_shoulder": "left_arm",
                       "left_elbow": "left_arm", "right_shoulder": "right_arm",
                       "right_elbow": "right_arm"}  # other body joints: "pose"
GROUPS = ("face", "left_hand", "right_hand", "pose")  # the landmark groups
# What is held and relaxed on its own: the landmark groups, and each wrist, which is seen
# while its hand is, or while the pose model's points of that hand are (`POSE_HAND_POINTS`:
# the hand landmark model declines many hands that BlazePose still places).
# Each arm (shoulder, elbow) is seen while anything below its shoulder is (`arm_seen`): an
# arm out of view has nothing to fit, and the fit's free arm drifts (docs/tracking.md).
HOLD_GROUPS = ("face", "left_hand", "right_hand", "left_wrist", "right_wrist", "left_arm",
               "right_arm", "pose")


@dataclass
class SequenceFitConfig:
    fov_x_deg: float = 60.0
    hold_s: float = 0.5      # lost: keep the last fitted value this long
    relax_s: float = 1.0     # ... then ease to neutral over this long
    smoothing: bool = True
    gaze: bool = True        # turn the eyes onto the iris centres, when the tracker reads them
    # One Euro: Hz at rest. 3 Hz: today's jitter or less at 2/3 of 1.5 Hz's lag on the studio
    # webcam protocol (docs/tracking.md, "One Euro: jitter against lag").
    min_cutoff: float = 3.0
    beta: float = 0.3        # cutoff gain per unit/s of speed
    # A hand's palm rotation (`palm.py`) is trusted for the fitter's palm retry only when it
    # is within this (deg) of the same hand's in the previous frame, at most `palm_gap_s`
    # before: a single frame's palm flips (a hand entering or leaving the view) are not.
    palm_stable_deg: float = 30.0
    palm_gap_s: float = 0.1
    # A hand the hand landmark model declines is placed by the pose model's points of it
    # (`from_track_result(..., pose_hands=True)`): its wrist follows them while the fingers
    # hold, then relax. False: those points are dropped and the wrist holds and relaxes. Off:
    # on the studio protocol it made the wrists worse (docs/tracking.md, "Hands the landmark
    # model declines").
    pose_hands: bool = False
    # Arm points this close to the image's border (fraction of its longer side) are unused
    # (`without_edge_arm_points`); 0: off.
    edge_margin: float = 0.0
    # Each arm held, then eased to rest, while nothing below its shoulder is observed
    # (`arm_seen`); False: the arms belong to the pose group and follow the fit.
    hold_arms: bool = False
    # One Euro on BlazePose's world landmarks before the fit, Hz at rest (0: off): they are
    # read afresh each frame, and their jitter passes into the world terms.
    world_min_cutoff: float = 0.0
    # A learned correction of BlazePose's world arm bones (`world_correction`), applied to
    # each frame's world landmarks before the fit; None: BlazePose's as they come.
    world_correction: WorldCorrection | None = None
    fit: FitConfig = field(default_factory=FitConfig)


@dataclass
class FrameParams:
    params: dict[str, np.ndarray]     # smplx names, per frame; what to drive with
    seen: dict[str, bool]             # group -> seen in this frame
    fit: FitResult | None             # None: nothing seen, params held / relaxing
    t: float


def _smoothstep(u: float) -> float:
    u = min(max(u, 0.0), 1.0)
    return u * u * (3 - 2 * u)


def _body_rows(group: str) -> list[int]:
    named = {JOINT[n] - 1: g for n, g in GROUP_OF_BODY_JOINT.items()}
    return [r for r in range(21) if named.get(r, "pose") == group]


class SequenceFit:
    """Feed observations in time order: `step(obs, t) -> FrameParams`."""

    def __init__(self, model: SMPLXModel, betas: np.ndarray | None = None,
                 config: SequenceFitConfig | None = None) -> None:
        self.config = config or SequenceFitConfig()
        if not 0.0 <= self.config.edge_margin < 0.5:
            raise ValueError(f"edge_margin is a fraction of the image's longer side in "
                             f"[0, 0.5), got {self.config.edge_margin}")
        if not (np.isfinite(self.config.world_min_cutoff) and self.config.world_min_cutoff >= 0):
            raise ValueError(f"world_min_cutoff must be a finite frequency >= 0 (0: off), got "
                             f"{self.config.world_min_cutoff}")
        self.fitter = FrameFitter(model, betas, self.config.fit)
        self.gaze = gaze_solver(model) if self.config.gaze else None
        self.neutral = self.fitter.neutral
        self.smoother = ParamSmoother(self.config.min_cutoff, self.config.beta)
        self.world_smoother = OneEuroFilter(self.config.world_min_cutoff, self.config.beta) \
            if self.config.world_min_cutoff > 0 else None
        self._rows = {g: _body_rows(g) for g in HOLD_GROUPS}
        self.reset()

    def reset(self) -> None:
        self.current: dict[str, np.ndarray] | None = None  # last output before smoothing
        self.held: dict[str, dict[str, np.ndarray]] = {}  # group -> its last fitted values
        self.last_seen: dict[str, float] = {}
        self.smoother.reset()
        if self.world_smoother is not None:
            self.world_smoother.reset()
        self._world_rows: np.ndarray | None = None  # [33] the finite rows last filtered
        self.palm_previous: dict[str, tuple[np.ndarray, float]] = {}  # side -> (rotation, t)

    def _group_values(self, params: dict[str, np.ndarray], group: str) -> dict[str, np.ndarray]:
        out = {k: np.array(v) for k, v in params.items() if GROUP_OF_PARAM.get(k) == group}
        out["body_rows"] = np.asarray(params["body_pose"])[self._rows[group]].copy()
        return out

    def _compose(self, fitted: dict[str, np.ndarray] | None, seen: dict[str, bool],
                 t: float) -> dict[str, np.ndarray]:
        out = {k: np.array(v, dtype=np.float64) for k, v in self.neutral.items()}
        if self.current is not None:
            out["transl"] = self.current["transl"].copy()  # placement is held, never relaxed
        for group in HOLD_GROUPS:
            if seen.get(group) and fitted is not None:
                values = self._group_values(fitted, group)
                self.held[group], self.last_seen[group] = dict(values), t
            elif group in self.held:
                lost = t - self.last_seen[group] - self.config.hold_s
                keep = 1.0 - _smoothstep(lost / max(self.config.relax_s, 1e-6))
                neutral = self._group_values(self.neutral, group)
                values = {k: neutral[k] + keep * (v - neutral[k]) if k != "transl" else v
                          for k, v in self.held[group].items()}
            else:
                continue
            rows = values.pop("body_rows")
            out["body_pose"][self._rows[group]] = rows
            out.update(values)
        if fitted is not None:  # the placement is shared by every group
            out["transl"] = np.array(fitted["transl"], dtype=np.float64)
        return out

    def _stable_palms(self, obs: Observations, camera: WebcamCamera, t: float
                      ) -> dict[str, np.ndarray]:
        """This frame's palm rotations that agree with the previous frame's (side -> [3, 3])."""
        cfg = self.config
        if cfg.fit.palm_retry_deg >= 180.0:
            return {}
        now = self.fitter.palm_targets(obs, camera)
        stable = {}
        for side, rot in now.items():
            prev = self.palm_previous.get(side)
            if prev is not None and 0 < t - prev[1] <= cfg.palm_gap_s + 1e-9 and \
                    rotation_angle_deg(prev[0], rot) <= cfg.palm_stable_deg:
                stable[side] = rot
            self.palm_previous[side] = (rot, t)
        return stable

    def _smoothed_world(self, obs: Observations, t: float) -> Observations:
        """`obs` with its world landmarks through the One Euro filter, row by row; a change in
        which rows are finite (a landmark lost or found) restarts the filter."""
        if self.world_smoother is None:
            return obs
        if obs.world is None:
            self.world_smoother.reset()
            return obs
        rows = np.isfinite(obs.world).all(axis=1)
        if self._world_rows is None or not np.array_equal(rows, self._world_rows):
            self.world_smoother.reset()
        self._world_rows = rows
        world = np.full_like(obs.world, np.nan)
        world[rows] = self.world_smoother(obs.world[rows], t)
        return dataclasses.replace(obs, world=world)

    def step(self, obs: Observations, t: float) -> FrameParams:
        camera = WebcamCamera(*obs.image_size, fov_x_deg=self.config.fov_x_deg)
        seen = {g: bool(obs.seen.get(g)) for g in GROUPS}
        if not self.config.pose_hands:
            obs = without_pose_hands(obs)
        obs = without_edge_arm_points(obs, self.config.edge_margin * max(obs.image_size))
        obs = self._smoothed_world(obs, t)
        if self.config.world_correction is not None and obs.world is not None:
            obs = dataclasses.replace(obs, world=correct_world(obs, self.config.world_correction))
        fit = None
        if any(seen.values()):
            stale = not self.last_seen or t - max(self.last_seen.values()) > self.config.hold_s
            start = None if self.current is None or stale else self.current
            fit = self.fitter.fit(obs, camera, start, self._stable_palms(obs, camera, t))
            if self.gaze is not None and obs.iris is not None and seen["face"]:
                eyes = self.gaze.fit(fit.params, obs.iris, camera, self.fitter.betas[0].numpy())
                fit.params.update(eyes.params)
                fit.stats["gaze_px"] = eyes.residual_px
        held = dict(seen)
        for side in ("left", "right"):
            held[f"{side}_wrist"] = seen[f"{side}_hand"] or (
                seen["pose"] and pose_hand_seen(obs, side))
            held[f"{side}_arm"] = seen["pose"] and (
                arm_seen(obs, side) or not self.config.hold_arms)
        params = self._compose(None if fit is None else fit.params, held, t)
        self.current = params
        if self.config.smoothing:
            params = self.smoother(params, t)
        return FrameParams(params, seen, fit, t)


# The arm cues as set on identity 1 of the studio webcam protocol and checked on identity 0
# (docs/tracking.md, "BlazePose's world bones and the elbow hinge"): BlazePose's world bone
# directions (arms and the shoulders' line), the elbows held to their hinge, and a firmer
# temporal prior on the body (placement and rotations) against the jitter the world
# landmarks bring. And the torso's axis while both hips are in view (set on identity 1's
# hips-in-view recording, checked on identity 0's and on a trained avatar's take:
# docs/results.md "The root's lean and BlazePose's torso axis"). And the shoulders' line's
# turn doubled: BlazePose's turns about 0.6 of the body's (docs/results.md "The shoulders'
# line turns too little").
ARM_CUES = {"world_direction_weight": 100.0,
            "world_direction_bones": (*ARM_BONES, *SHOULDER_LINE),
            "elbow_hinge_weight": 10.0, "elbow_extension_deg": 5.0, "body_temporal_weight": 10.0,
            "torso_axis_weight": 2.0, "shoulder_line_yaw_gain": 2.0}


def with_arm_cues(config: SequenceFitConfig) -> SequenceFitConfig:
    """`config` with `ARM_CUES` in its fit."""
    return dataclasses.replace(config, fit=dataclasses.replace(config.fit, **ARM_CUES))


def live_config(**fields) -> SequenceFitConfig:
    """The live path's configuration (the server's webcam tracking, `telesplat eval --protocol
    webcam`, `telesplat track video`): `SequenceFitConfig(**fields)` with the arm cues. On
    the studio webcam protocol's held-out identity they gain +1.3 dB, root 21 -> 7 deg,
    elbows 83 -> 29, at the same jitter and fit time (docs/tracking.md)."""
    return with_arm_cues(SequenceFitConfig(**fields))


def drive_params(params: dict[str, np.ndarray], with_transl: bool = False
                 ) -> dict[str, np.ndarray]:
    """The SMPL-X fields to drive an avatar with. `transl` is the subject's place in front of
    the webcam, which would move the avatar out of its own view: left out by default."""
    return {k: np.asarray(v, dtype=np.float64) for k, v in params.items()
            if with_transl or k != "transl"}
