"""One frame's fit: SMPL-X parameters whose keypoints reproject onto the observed landmarks.

Minimized by Levenberg-Marquardt (bounded iterations) with the exact Jacobian of the keypoints
(`kinematics.KeypointKinematics`: one numpy pass gives the keypoints and their derivatives):

    sum_k w_k * pseudo_huber(|project(keypoint_k) - landmark_k|) / s^2   (data, s = max(W,H)/100)
  + pose prior (spine, neck, head, collars toward rest; arms and hands weakly toward neutral)
  + joint limits (hinge on each rotation's angle beyond `JOINT_LIMITS_DEG`; an elbow bent
    backward past `elbow_extension_deg`)
  + BlazePose's world bone directions against the model's (`world_cues`, when weighted)
  + the fingers' and the elbows' hinge priors (`hand_prior.py`, `elbow_prior.py`)
  + expression prior and its +-1.5 bound
  + temporal prior toward the previous frame's fit (warm starts only)

(the pseudo-Huber loss by iterative reweighting).

A cold start first solves the subject's placement (`transl`, `global_orient`) alone, from a
scale-and-centroid guess; a warm start begins at the previous frame's parameters.
Eye rotations are not fitted: the face mesh's 468 points carry no iris, so they stay 0.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from ...body.joint_limits import EXPRESSION_LIMIT, JOINT_LIMITS_DEG, RELAXED_ARMS
from ...body.models import SMPLXModel
from ...body.skeleton import JOINT, LEFT_HAND_JOINTS, RIGHT_HAND_JOINTS, SMPLX_JOINT_NAMES
from . import correspondence as cor
from . import elbow_prior, palm_retry, world_cues
from .camera import MIN_DEPTH_M, WebcamCamera, project_points
from .embedding import LandmarkEmbedding
from .hand_prior import hinge_matrix, hinge_rows
from .keypoints import BodyKeypoints
from .kinematics import KeypointKinematics, rodrigues_and_left_jacobian
from .observations import Observations
from .palm import PALM_JOINTS

# Body joints the fit moves (the rest of body_pose, i.e. the legs, stays 0).
FREE_BODY_JOINTS = ("spine1", "spine2", "spine3", "neck", "left_collar", "right_collar", "head",
                    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
                    "left_wrist", "right_wrist")
# Pose prior weight per joint (per rad^2): the torso and neck are stiff, the arms loose.
BODY_PRIOR = {"spine1": 4.0, "spine2": 4.0, "spine3": 4.0, "neck": 0.5, "head": 0.5,
              "left_collar": 4.0, "right_collar": 4.0}
# Cold-start stages: the placement, then the head and torso (before the arms and hands).
PLACEMENT_VARIABLES = ("global_orient", "transl")
CORE_VARIABLES = (*PLACEMENT_VARIABLES, "spine1", "spine2", "spine3", "neck", "head",
                  "jaw_pose", "expression")
CORE_POSE_LANDMARKS = (0, 2, 5, 7, 8, 11, 12, 23, 24)  # nose, eyes, ears, shoulders, hips
ARM_VARIABLES = (*CORE_VARIABLES, "left_collar", "right_collar", "left_shoulder",
                 "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist")
ARM_POSE_LANDMARKS = (*CORE_POSE_LANDMARKS, 13, 14, 15, 16)  # + elbows, wrists
HAND_PALM_LANDMARKS = (0, 1, 5, 9, 13, 17)  # wrist and knuckles: the palm's placement
ARM_PRIOR = 0.02
EXPRESSION_PRIOR = 0.02
GLOBAL_PRIOR = 0.5     # the body mostly faces the camera
LIMIT_WEIGHT = 100.0
# Per keypoint group: a weight on its data term (the contour is loosely defined on any face).
GROUP_WEIGHT = {"face": 1.0, "left_hand": 1.0, "right_hand": 1.0, "pose": 2.0}
CONTOUR_WEIGHT = 0.3
# MediaPipe's hand z is ~2.5x flatter than the true relative depth at the wrist's distance
# (renders with known parameters, docs/tracking.md: correlation 0.90, slope 2.5).
HAND_Z_SCALE = 2.5
# ... and its face z 1.4x deeper than the truth against the nose tip (correlation 0.83).
FACE_Z_SCALE = 0.7
# Relative-depth groups: each hand against its wrist (its first row); the face's static
# landmarks (iBUG 17-67: brows, nose, eyes, mouth) against the nose tip (iBUG 30).
DEPTH_HANDS = (np.arange(cor.LEFT_HAND_SLICE.start, cor.LEFT_HAND_SLICE.stop),
               np.arange(cor.RIGHT_HAND_SLICE.start, cor.RIGHT_HAND_SLICE.stop))
DEPTH_FACE = np.arange(cor.FACE_SLICE.start + 17, cor.FACE_SLICE.stop)
FACE_DEPTH_REF = cor.FACE_SLICE.start + 30
HUBER_PX = 8.0         # pseudo-Huber knee: larger errors grow linearly (outlier landmarks)
MAX_ROTATION_STEP = 0.25  # rad: the most one LM step turns any joint (`_step_scale`)
INITIAL_DAMPING = 1e-3   # Levenberg-Marquardt's, relative to diag(J^T J)
NEUTRAL_DEPTH_M = 0.8  # a webcam subject's distance when nothing tells otherwise


def neutral_params(model: SMPLXModel) -> dict[str, np.ndarray]:
    """The rest stance the fit starts from and lost tracks relax to: arms relaxed down."""
    body = np.zeros((21, 3))
    for name, aa in RELAXED_ARMS.items():
        body[JOINT[name] - 1] = aa
    return {"global_orient": np.zeros(3), "transl": np.array([0.0, 0.0, 0.0]),
            "body_pose": body, "jaw_pose": np.zeros(3), "leye_pose": np.zeros(3),
            "reye_pose": np.zeros(3), "expression": np.zeros(model.num_expression),
            "left_hand_pose": np.zeros((15, 3)), "right_hand_pose": np.zeros((15, 3))}


@dataclass
class FitConfig:
    cold_iterations: int = 20   # Levenberg-Marquardt iterations of a cold start
    warm_iterations: int = 4    # ... of a warm start
    placement_iterations: int = 6
    temporal_weight: float = 0.5  # per rad^2 (and per m^2 x 100 for transl), warm starts only
    # ... for the body alone (its placement and rotations: root, spine, collars, neck, head,
    # arms; None: `temporal_weight`): the world bone directions' frame-to-frame noise moves
    # the body, while the face (jaw, expression) and the fingers keep their own.
    body_temporal_weight: float | None = None
    # A hand point's relative-depth residual against its 2D one (0: off). A trade-off measured
    # on renders (docs/tracking.md): more weight, fewer palm / back flips of the wrist, worse
    # 2D hand keypoints.
    hand_depth_weight: float = 0.05
    # Finger joints toward the mean hand, per rad^2: on renders MediaPipe's finger points sit
    # ~11 px from this model's joints, and a firmer prior keeps the fingers nearer the truth
    # (docs/tracking.md: 0.05 -> 0.3 -> 1.0 with the palm retry and the hinge prior, finger
    # error 36 -> 30 -> 23 deg) at a small cost on exact landmarks.
    hand_prior: float = 1.0
    # The same for the face's static landmarks against the nose tip: it pins the head's
    # pitch, which the 2D landmarks leave loose (docs/tracking.md: head 7.8 -> 4.8 deg).
    face_depth_weight: float = 0.3
    # A fitted wrist farther than this (deg) from the palm's own rotation (`palm.py`: Kabsch
    # of the palm landmarks with their z) is fitted again from that rotation, and the lower
    # cost kept: it undoes palm / back flips the local steps cannot leave (docs/tracking.md).
    # 180 or more: off.
    palm_retry_deg: float = 60.0
    palm_retry_iterations: int = 8  # Levenberg-Marquardt iterations of such a retry
    # Finger joints' rotation off their hinge axis (and the finger bases' twist), per rad^2
    # (`hand_prior.py`; 0: off): the landmarks pin a finger's bend far better than its
    # twist, which the fit otherwise bends to meet MediaPipe's offset finger points.
    finger_hinge_weight: float = 10.0
    # The elbows held to their hinge (`elbow_prior.py`): their sideways bend, per rad^2
    # (0: off), and how far (deg) one may bend backward past straight before a joint-limit
    # hinge stops it (180 or more: off). Free elbows let the fit trade the upper arm's twist
    # for a sideways bend that reaches the same landmarks.
    elbow_hinge_weight: float = 0.0
    elbow_extension_deg: float = 180.0
    # The learned landmark embedding (`embedding.py`: where each landmark lies on the model);
    # None: today's correspondence (joint centres, vertices, the iBUG triangles).
    embedding: LandmarkEmbedding | None = None
    # Shoulders, elbows and wrists toward the rest stance (`RELAXED_ARMS`), per rad^2.
    arm_prior: float = ARM_PRIOR
    # BlazePose's metric world z and its image z, against the model's depth differences
    # (`world_cues.py`; 0: off). Set on held-out renders (docs/tracking.md).
    world_weight: float = 0.0
    image_z_weight: float = 0.0
    # Each bone of `world_direction_bones` ((from, to), each end one BlazePose landmark or
    # two: their midpoint) toward its
    # direction in BlazePose's metric world landmarks (`world_cues.direction_residuals`), per
    # rad^2 (0: off): its world bones are far nearer the truth than a monocular fit's
    # (docs/tracking.md).
    world_direction_weight: float = 0.0
    world_direction_bones: tuple[tuple, ...] = world_cues.ARM_BONES
    # The shoulders' line's turn about the vertical, as BlazePose's world points give it,
    # multiplied by this before it is a target (`world_cues.turned_line`; 1: as given).
    shoulder_line_yaw_gain: float = 1.0
    # The torso's axis (`world_cues.TORSO_AXIS`, while both hips are in view) toward
    # BlazePose's, per rad^2 (0: off; the live cues' 2: docs/results.md "The root's lean and
    # BlazePose's torso axis").
    torso_axis_weight: float = 0.0
    # False: the axis counts whether or not the hips are in view (a lean cue that holds
    # there too; the live cue needs them: BlazePose's off-view hips cost up to 1.8 dB).
    torso_axis_hips_in_view: bool = True
    dtype: torch.dtype = torch.float64


@dataclass
class FitResult:
    params: dict[str, np.ndarray]           # smplx names, per frame (no batch axis)
    reprojection_px: dict[str, float]       # group -> mean px error over used landmarks
    loss: float
    ms: float
    stats: dict = field(default_factory=dict)


def _free_joint_rows() -> list[int]:
    return [JOINT[n] - 1 for n in FREE_BODY_JOINTS]


def _limits_rad(names: list[str]) -> np.ndarray:
    return np.array([math.radians(JOINT_LIMITS_DEG.get(n, 180.0)) for n in names])


# The rotations among the free variables, in the free vector's order, and their joints.
POSED_VARIABLES = ("global_orient", "body", "jaw_pose", "left_hand_pose", "right_hand_pose")
POSE_JOINTS_OF_VARIABLES = [0, *(JOINT[n] for n in FREE_BODY_JOINTS), JOINT["jaw"],
                            *LEFT_HAND_JOINTS, *RIGHT_HAND_JOINTS]
HAND_JOINT_ROWS = [*LEFT_HAND_JOINTS, *RIGHT_HAND_JOINTS]


class FrameFitter:
    """Fits single frames; holds the model keypoints and the camera-independent priors."""

    def __init__(self, model: SMPLXModel, betas: np.ndarray | None = None,
                 config: FitConfig | None = None) -> None:
        self.config = config or FitConfig()
        cfg = self.config
        for name in ("arm_prior", "temporal_weight", "body_temporal_weight",
                     "elbow_hinge_weight", "world_direction_weight", "torso_axis_weight"):
            value = getattr(cfg, name)
            if value is not None and not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite weight >= 0, got {value}")
        if not (math.isfinite(cfg.shoulder_line_yaw_gain) and cfg.shoulder_line_yaw_gain > 0):
            raise ValueError(f"shoulder_line_yaw_gain must be a finite gain > 0, got "
                             f"{cfg.shoulder_line_yaw_gain}")
        if math.isnan(cfg.elbow_extension_deg) or cfg.elbow_extension_deg < 0:
            raise ValueError(f"elbow_extension_deg must be >= 0 (180 or more: off), got "
                             f"{cfg.elbow_extension_deg}")
        if not all(world_cues.valid_bone(b) for b in cfg.world_direction_bones):
            raise ValueError(f"world_direction_bones must be (from, to) pairs, each end one "
                             f"BlazePose landmark in [0, {cor.NUM_POSE}) or two (their "
                             f"midpoint), the ends distinct, got {cfg.world_direction_bones}")
        self.keypoints = BodyKeypoints(model, dtype=self.config.dtype)  # the reference model
        self.num_expression = model.num_expression
        n_betas = self.keypoints.model.num_betas
        b = np.zeros(n_betas) if betas is None else np.asarray(betas, dtype=np.float64)
        b = np.pad(b[:n_betas], (0, max(0, n_betas - b.size)))
        self.betas = torch.as_tensor(b, dtype=self.config.dtype)[None]
        self.kinematics = KeypointKinematics(self.keypoints, b)
        self.embedding = self.config.embedding
        if self.embedding is not None:
            self.kinematics.set_offsets(self.embedding.joint, self.embedding.offset,
                                        self.embedding.pose_basis)
        kp_model = self.keypoints.model
        self.hand_mean = np.concatenate([kp_model.left_hand_mean.double().numpy(),
                                         kp_model.right_hand_mean.double().numpy()])  # [30, 3]
        self.neutral = neutral_params(model)
        self.rows = _free_joint_rows()
        self.layout = self._layout()
        lay = self.layout
        n = lay["right_hand_pose"][0].stop
        self.pose_joints = POSE_JOINTS_OF_VARIABLES
        self.pose_columns = np.concatenate(
            [np.arange(n)[lay[name][0]] for name in POSED_VARIABLES])
        # Quadratic priors as sqrt-weights toward a rest value, per variable.
        prior = np.zeros(n)
        prior[lay["body"][0]] = np.repeat([np.sqrt(BODY_PRIOR.get(j, self.config.arm_prior))
                                           for j in FREE_BODY_JOINTS], 3)
        prior[lay["global_orient"][0]] = math.sqrt(GLOBAL_PRIOR)
        prior[lay["left_hand_pose"][0].start:lay["right_hand_pose"][0].stop] = \
            math.sqrt(self.config.hand_prior)
        prior[lay["expression"][0]] = math.sqrt(EXPRESSION_PRIOR)
        self.prior_sqrt = prior
        self.prior_rest = np.zeros(n)
        self.prior_rest[lay["body"][0]] = self.neutral["body_pose"][self.rows].reshape(-1)
        # Hinges on rotation angles: (columns [R, 3], bound [R] rad).
        columns = np.arange(n)
        hand_names = [SMPLX_JOINT_NAMES[j].removeprefix("left_") for j in LEFT_HAND_JOINTS]
        hand_limits = _limits_rad([f"left_{h}" for h in hand_names])
        self.angle_limits = [
            (columns[lay["body"][0]].reshape(-1, 3), _limits_rad(list(FREE_BODY_JOINTS))),
            (columns[lay["left_hand_pose"][0].start:lay["right_hand_pose"][0].stop]
             .reshape(-1, 3), np.tile(hand_limits, 2)),
            (columns[lay["jaw_pose"][0]].reshape(1, 3), _limits_rad(["jaw"])),
        ]
        weights = np.ones(cor.NUM_KEYPOINTS)
        weights[cor.FACE_SLICE][list(cor.IBUG_CONTOUR)] = CONTOUR_WEIGHT
        for group, sl in cor.GROUP_SLICES.items():
            weights[sl] *= GROUP_WEIGHT[group]
        self.group_weights = weights
        core = np.zeros(cor.NUM_KEYPOINTS)
        core[cor.FACE_SLICE] = 1.0
        arms = core.copy()
        core[cor.POSE_SLICE.start + np.array(CORE_POSE_LANDMARKS)] = 1.0
        arms[cor.POSE_SLICE.start + np.array(ARM_POSE_LANDMARKS)] = 1.0
        for sl in (cor.LEFT_HAND_SLICE, cor.RIGHT_HAND_SLICE):
            arms[sl.start + np.array(HAND_PALM_LANDMARKS)] = 1.0
        self.stage_masks = {"core": core, "arms": arms}
        temporal = np.full(n, self.config.temporal_weight)
        if self.config.body_temporal_weight is not None:
            temporal[self._free_mask(("global_orient", "transl", *FREE_BODY_JOINTS))] = \
                self.config.body_temporal_weight
        temporal[lay["transl"][0]] *= 100.0  # 1 cm weighs as 0.1 rad
        self.temporal_sqrt = np.sqrt(temporal)
        # The hinge prior: sqrt weight x the map to the fingers' off-axis components, and the
        # mean hand's part (the hand variables are relative to it).
        hand_cols = np.arange(n)[lay["left_hand_pose"][0].start:lay["right_hand_pose"][0].stop]
        joint_columns = dict(zip(HAND_JOINT_ROWS, hand_cols.reshape(-1, 3), strict=True))
        rows = {**hinge_rows(self.kinematics.j_shape, self.kinematics.parents, "left"),
                **hinge_rows(self.kinematics.j_shape, self.kinematics.parents, "right")}
        hinge = math.sqrt(max(self.config.finger_hinge_weight, 0.0)) * hinge_matrix(
            rows if self.config.finger_hinge_weight > 0 else {}, joint_columns, n)
        mean = np.zeros(n)
        mean[hand_cols] = self.hand_mean.reshape(-1)
        elbows = elbow_prior.elbow_axes(self.kinematics.j_shape)
        elbow_columns = {k: lay["body"][0].start + 3 * FREE_BODY_JOINTS.index(
            SMPLX_JOINT_NAMES[k]) + np.arange(3) for k in elbows}
        if self.config.elbow_hinge_weight > 0:
            sideways = {k: s[None] for k, (_, s) in elbows.items()}
            hinge = np.concatenate([hinge, math.sqrt(self.config.elbow_hinge_weight)
                                    * hinge_matrix(sideways, elbow_columns, n)])
        self.hinge_jacobian, self.hinge_offset = hinge, hinge @ mean
        # Elbow flexion rows [E, N] and the backward bend they allow (rad), or None.
        self.elbow_flexion = None
        if self.config.elbow_extension_deg < 180.0:
            flexion = {k: axis[None] for k, (axis, _) in elbows.items()}
            self.elbow_flexion = (hinge_matrix(flexion, elbow_columns, n),
                                  math.radians(self.config.elbow_extension_deg))
        # Per hand: (its rows, its wrist's body-variable columns, its hand-pose columns, the
        # wrist's joint, the rest palm [5, 3] for `palm_rotation`).
        self.palm_hands = []
        for side, sl in (("left", cor.LEFT_HAND_SLICE), ("right", cor.RIGHT_HAND_SLICE)):
            wrist_col = lay["body"][0].start + 3 * FREE_BODY_JOINTS.index(f"{side}_wrist")
            rest = self.kinematics.j_shape[[JOINT[f"{side}_{n}"] for n in PALM_JOINTS]]
            self.palm_hands.append((sl, np.arange(wrist_col, wrist_col + 3),
                                    np.arange(n)[lay[f"{side}_hand_pose"][0]],
                                    JOINT[f"{side}_wrist"], rest))

    # -- parameters <-> the free-variable vector ----------------------------------------------

    def _layout(self) -> dict[str, tuple[slice, tuple[int, ...]]]:
        shapes = {"global_orient": (3,), "transl": (3,), "body": (len(self.rows), 3),
                  "jaw_pose": (3,), "expression": (self.num_expression,),
                  "left_hand_pose": (15, 3), "right_hand_pose": (15, 3)}
        out, at = {}, 0
        for name, shape in shapes.items():
            n = math.prod(shape)
            out[name] = (slice(at, at + n), shape)
            at += n
        return out

    def _free_mask(self, names: tuple[str, ...]) -> np.ndarray:
        """[N] bool: the free variables of a cold-start stage (body rows by joint name)."""
        mask = np.zeros(self.layout["right_hand_pose"][0].stop, dtype=bool)
        for name in names:
            if name in self.layout:
                mask[self.layout[name][0]] = True
            else:
                row = FREE_BODY_JOINTS.index(name)
                start = self.layout["body"][0].start + 3 * row
                mask[start:start + 3] = True
        return mask

    def pack(self, params: dict[str, np.ndarray]) -> np.ndarray:
        """SMPL-X parameters -> the free-variable vector [N]."""
        parts = []
        for name, (_, shape) in self.layout.items():
            if name == "body":
                a = np.asarray(params["body_pose"], dtype=np.float64).reshape(21, 3)[self.rows]
            elif name == "expression":
                e = np.asarray(params.get("expression", np.zeros(0)), dtype=np.float64).ravel()
                a = np.pad(e[: shape[0]], (0, max(0, shape[0] - e.size)))
            else:
                a = np.asarray(params[name], dtype=np.float64)
            parts.append(a.reshape(-1))
        return np.concatenate(parts)

    def to_params(self, x: np.ndarray) -> dict[str, np.ndarray]:
        """The free-variable vector [N] -> SMPL-X parameters (no batch axis; eyes 0)."""
        out = {name: np.array(x[sl].reshape(shape)) for name, (sl, shape) in self.layout.items()}
        body = np.zeros((21, 3))
        body[self.rows] = out.pop("body")
        return {**out, "body_pose": body, "leye_pose": np.zeros(3), "reye_pose": np.zeros(3)}

    # -- the objective: a residual vector, cost = sum of squares -------------------------------

    def full_pose(self, x: np.ndarray) -> np.ndarray:
        """Free variables [N] -> the model's full axis-angle pose [55, 3] (hand mean added)."""
        lay = self.layout
        pose = np.zeros((55, 3))
        pose[POSE_JOINTS_OF_VARIABLES] = np.concatenate(
            [x[lay[name][0]].reshape(-1, 3) for name in POSED_VARIABLES])
        pose[HAND_JOINT_ROWS] += self.hand_mean
        return pose

    def _keypoints(self, x: np.ndarray, jacobian: bool
                   ) -> tuple[np.ndarray, np.ndarray | None]:
        """Model-space keypoints [K, 3] and, with `jacobian`, their derivatives [K, 3, N]."""
        lay = self.layout
        points, d_pose, d_expr = self.kinematics.evaluate(
            self.full_pose(x), x[lay["expression"][0]], x[lay["transl"][0]],
            self.pose_joints if jacobian else None, expression_jacobian=jacobian)
        if not jacobian:
            return points, None
        k = points.shape[0]
        jac = np.zeros((k, 3, x.size))
        jac[:, :, self.pose_columns] = d_pose.reshape(k, 3, -1)
        jac[:, :, lay["expression"][0]] = d_expr
        jac[:, :, lay["transl"][0]] = np.eye(3)
        jac[~self.kinematics.available] = 0.0
        return points, jac

    def _terms(self, x: np.ndarray, problem: _Problem, sqrt_w: np.ndarray, jacobian: bool
               ) -> tuple[list[_Term], np.ndarray]:
        """The objective's residual blocks at x (cost = the sum of their squares) and the
        projections [K, 2]. Without `jacobian` the blocks carry no derivatives."""
        seen = self._data(x, problem.camera, jacobian)
        proj = seen.pixels
        used = sqrt_w > 0
        data = sqrt_w[used, None] * (proj[used] - problem.target[used]) / problem.scale
        d_data = None
        if jacobian:
            d_data = ((sqrt_w[used, None, None] / problem.scale) * seen.d_pixels[used]).reshape(
                -1, x.size)
        terms = [_Term(data.reshape(-1), d_data)]
        if problem.depth_pairs is not None:
            terms.append(self._depth_term(seen, problem, jacobian))
        if problem.world_pairs is not None:
            terms.append(_Term(*world_cues.world_residuals(
                seen.depth, seen.d_depth, problem.world_pairs, problem.camera.focal,
                problem.scale, jacobian)))
        if problem.direction_pairs is not None:
            terms.append(_Term(*world_cues.direction_residuals(
                seen.points, seen.d_points, problem.direction_pairs, jacobian)))
        # Quadratic priors toward rest, and the temporal term: diagonal Jacobians.
        terms.append(_Term(self.prior_sqrt * (x - self.prior_rest), None, self.prior_sqrt))
        if problem.previous is not None:
            terms.append(_Term(self.temporal_sqrt * (x - problem.previous), None,
                               self.temporal_sqrt))
        if self.hinge_jacobian.size:
            terms.append(_Term(self.hinge_jacobian @ x + self.hinge_offset,
                               self.hinge_jacobian if jacobian else None))
        hinges = self._hinge_term(x, jacobian)
        if hinges is not None:
            terms.append(hinges)
        return terms, proj

    def _hinge_term(self, x: np.ndarray, jacobian: bool) -> _Term | None:
        """Hinges on expression coefficients past their bound and rotation angles past
        `JOINT_LIMITS_DEG`: only the active rows (None when none is)."""
        limit = math.sqrt(LIMIT_WEIGHT)
        cols = np.arange(x.size)[self.layout["expression"][0]]
        over = np.abs(x[cols]) - EXPRESSION_LIMIT
        on = np.flatnonzero(over > 0)
        residuals, jacobians = [limit * over[on]], []
        if jacobian:
            j = np.zeros((len(on), x.size))
            j[np.arange(len(on)), cols[on]] = limit * np.sign(x[cols[on]])
            jacobians.append(j)
        for joint_cols, bound in self.angle_limits:
            aa = x[joint_cols]                                       # [R, 3]
            angle = np.sqrt((aa ** 2).sum(-1) + 1e-12)
            on = np.flatnonzero(angle > bound)
            residuals.append(limit * (angle[on] - bound[on]))
            if jacobian:
                j = np.zeros((len(on), x.size))
                j[np.arange(len(on))[:, None], joint_cols[on]] = \
                    limit * aa[on] / angle[on, None]
                jacobians.append(j)
        if self.elbow_flexion is not None:
            rows, bound = self.elbow_flexion
            over = -(rows @ x) - bound  # how far each elbow bends backward past the bound
            on = np.flatnonzero(over > 0)
            residuals.append(limit * over[on])
            if jacobian:
                jacobians.append(-limit * rows[on])
        r = np.concatenate(residuals)
        if not r.size:
            return None
        return _Term(r, np.concatenate(jacobians) if jacobian else None)

    def _depth_term(self, seen: _Projected, problem: _Problem, jacobian: bool) -> _Term:
        """Relative depth in pixels, f (d_k - d_ref) / d_ref, against MediaPipe's z (each hand
        point against its wrist, each face point against the nose tip): it tells the palm
        from the back of a flat hand, and a head pitched up from one pitched down, where the
        2D landmarks alone leave them ambiguous."""
        k, ref, target, sqrt_w = problem.depth_pairs
        f = problem.camera.focal
        d_k, d_ref = seen.depth[k], np.maximum(seen.depth[ref], MIN_DEPTH_M)
        r = sqrt_w * (f * (d_k / d_ref - 1.0) - target) / problem.scale
        jac = None
        if jacobian:
            jac = (sqrt_w * f / problem.scale)[:, None] * (
                seen.d_depth[k] / d_ref[:, None]
                - (d_k / d_ref ** 2)[:, None] * seen.d_depth[ref])
        return _Term(np.nan_to_num(r), jac)

    def _data(self, x: np.ndarray, camera: WebcamCamera, jacobian: bool) -> _Projected:
        """The keypoints seen by the camera at x, with derivatives when asked."""
        points, jac = self._keypoints(x, jacobian)
        proj, d_proj = project_points(points, camera)
        if not jacobian:
            return _Projected(proj, -points[:, 2], points)
        d_proj[~self.kinematics.available] = 0.0  # NaN rows: no keypoint, weight 0
        return _Projected(proj, -points[:, 2], points, np.einsum("kab,kbn->kan", d_proj, jac),
                          -jac[:, 2], jac)

    def dense_system(self, x: np.ndarray, problem: _Problem, sqrt_w: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
        """All residuals [M] and their Jacobian [M, N] as one dense system (for tests)."""
        terms, _ = self._terms(x, problem, sqrt_w, True)
        jac = [t.jacobian if t.diagonal is None else np.diag(t.diagonal) for t in terms]
        return np.concatenate([t.residuals for t in terms]), np.concatenate(jac)

    # -- fitting -------------------------------------------------------------------------------

    def initial_placement(self, start: dict[str, np.ndarray], obs: Observations,
                          camera: WebcamCamera) -> np.ndarray:
        """A transl that puts the observed landmarks' model counterparts at the right scale and
        place, from their spread and centroid (the model at `start`, transl 0)."""
        used = obs.weights > 0
        model_pts, _ = self._keypoints(self.pack({**start, "transl": np.zeros(3)}), False)
        used &= np.isfinite(model_pts).all(axis=1)
        if used.sum() < 2:
            return np.array([0.0, -0.55, -NEUTRAL_DEPTH_M])  # the head about centred
        m, px = model_pts[used], obs.pixels[used]
        spread_m = np.sqrt(((m[:, :2] - m[:, :2].mean(0)) ** 2).sum(1).mean())
        spread_px = np.sqrt(((px - px.mean(0)) ** 2).sum(1).mean())
        depth = camera.focal * spread_m / max(spread_px, 1e-6)
        depth = float(np.clip(depth if np.isfinite(depth) else NEUTRAL_DEPTH_M, 0.2, 10.0))
        mz = float(m[:, 2].mean())
        centre = camera.unproject_depth(px.mean(0), depth)  # where the centroid must be
        return np.array([centre[0] - m[:, 0].mean(), centre[1] - m[:, 1].mean(), -depth - mz])

    def fit(self, obs: Observations, camera: WebcamCamera,
            start: dict[str, np.ndarray] | None = None,
            palm_targets: dict[str, np.ndarray] | None = None) -> FitResult:
        """Fit one frame. `start`: the previous frame's parameters (a warm start), or None.
        `palm_targets`: side -> the palm rotation a wrist is retried from (`palm_retry`);
        None: this frame's own (`palm_targets`), {}: no retry."""
        t0 = time.perf_counter()
        warm = start is not None
        start = dict(start) if warm else dict(self.neutral)
        if not warm:
            start["transl"] = self.initial_placement(start, obs, camera)
        weight = np.asarray(obs.weights, dtype=np.float64) * self.group_weights
        weight = np.where(self.kinematics.available, weight, 0.0)
        x = self.pack(start)
        problem = _Problem(camera, np.asarray(obs.pixels, dtype=np.float64),
                           max(camera.width, camera.height) / 100.0,
                           x.copy() if warm else None, self._depth_pairs(obs, weight),
                           self._world_pairs(obs, weight),
                           world_cues.joined_pairs(
                               world_cues.direction_pairs(obs, weight,
                                                          self.config.world_direction_weight,
                                                          self.config.world_direction_bones,
                                                          self.config.shoulder_line_yaw_gain),
                               world_cues.direction_pairs(obs, weight,
                                                          self.config.torso_axis_weight,
                                                          world_cues.TORSO_AXIS,
                                                          world_only_in_view=self.config
                                                          .torso_axis_hips_in_view)))
        stats = {"iterations": 0, "evaluations": 0}
        if not warm:  # coarse to fine: place the head and torso first, then the limbs
            n = self.config.placement_iterations
            for names, mask in ((PLACEMENT_VARIABLES, "core"), (CORE_VARIABLES, "core"),
                                (ARM_VARIABLES, "arms")):
                x = self._levenberg_marquardt(x, self._free_mask(names), n, problem,
                                              weight * self.stage_masks[mask], stats)
        x = self._levenberg_marquardt(
            x, np.ones(x.size, dtype=bool),
            self.config.warm_iterations if warm else self.config.cold_iterations,
            problem, weight, stats)
        if self.config.palm_retry_deg < 180.0:
            targets = self.palm_targets(obs, camera) if palm_targets is None else palm_targets
            x = palm_retry.retry(self, x, targets, problem, weight, stats)
        terms, proj = self._terms(x, problem, np.sqrt(weight), False)
        return FitResult(self.to_params(x), reprojection_errors(proj, obs),
                         sum(float(t.residuals @ t.residuals) for t in terms),
                         (time.perf_counter() - t0) * 1e3, stats)

    def world_rotation(self, x: np.ndarray, joint: int) -> np.ndarray:
        """[3, 3] world rotation of `joint` at the free variables x (its chain only)."""
        pose = self.full_pose(x)
        chain = []
        while joint >= 0:
            chain.append(joint)
            joint = int(self.kinematics.parents[joint])
        rot, _ = rodrigues_and_left_jacobian(pose[chain[::-1]])
        out = np.eye(3)
        for r in rot:
            out = out @ r
        return out

    def robust_cost(self, x: np.ndarray, problem: _Problem, weight: np.ndarray) -> float:
        """The objective at x with the pseudo-Huber weights taken at x itself."""
        proj = self._data(x, problem.camera, False).pixels
        err2 = ((np.nan_to_num(proj) - problem.target) ** 2).sum(-1)
        sqrt_w = np.sqrt(weight / np.sqrt(1 + err2 / HUBER_PX ** 2))
        terms, _ = self._terms(x, problem, sqrt_w, False)
        return sum(float(t.residuals @ t.residuals) for t in terms)

    def palm_targets(self, obs: Observations, camera: WebcamCamera) -> dict[str, np.ndarray]:
        """Each hand's palm rotation, side -> [3, 3] (`palm_retry.palm_targets`)."""
        return palm_retry.palm_targets(self.palm_hands, obs, camera, HAND_Z_SCALE)

    def _depth_pairs(self, obs: Observations, weight: np.ndarray):
        """(keypoint, reference, target, sqrt weight) rows of the relative-depth term: each
        used point of a group against the group's reference point (`DEPTH_GROUPS`), where
        MediaPipe gave z for both; None when there is none."""
        if obs.depth is None:
            return None
        cfg = self.config
        parts = []
        for rows, ref, z_scale, w in (
                *((h, h[0], HAND_Z_SCALE, cfg.hand_depth_weight) for h in DEPTH_HANDS),
                (DEPTH_FACE, FACE_DEPTH_REF, FACE_Z_SCALE, cfg.face_depth_weight)):
            if w <= 0 or weight[ref] <= 0 or not np.isfinite(obs.depth[ref]):
                continue
            k = rows[(rows != ref) & (weight[rows] > 0) & np.isfinite(obs.depth[rows])]
            parts.append((k, np.full(len(k), ref), z_scale * (obs.depth[k] - obs.depth[ref]),
                          np.sqrt(w * weight[k])))
        image_z = world_cues.pose_pairs(obs, weight, obs.depth[cor.POSE_SLICE], self._z_scale(
            "image_z_scale"), cfg.image_z_weight)
        if image_z is not None:
            parts.append(image_z)
        if not parts or not sum(len(p[0]) for p in parts):
            return None
        return tuple(np.concatenate(column) for column in zip(*parts, strict=True))

    def _z_scale(self, name: str) -> float:
        return 1.0 if self.embedding is None else float(getattr(self.embedding, name))

    def _world_pairs(self, obs: Observations, weight: np.ndarray):
        """The world term's pairs (`world_cues.pose_pairs`), or None."""
        return world_cues.pose_pairs(obs, weight, None if obs.world is None else obs.world[:, 2],
                                     self._z_scale("world_z_scale"), self.config.world_weight)

    def _levenberg_marquardt(self, x: np.ndarray, free: np.ndarray, iterations: int,
                             problem: _Problem, weight: np.ndarray, stats: dict) -> np.ndarray:
        """Levenberg-Marquardt on the free entries of x with the analytic Jacobian; the robust
        loss by iterative reweighting (weights fixed within a step)."""
        idx = np.flatnonzero(free)
        damping, grow = INITIAL_DAMPING, 2.0
        proj = self._data(x, problem.camera, False).pixels
        for _ in range(iterations):
            err2 = ((np.nan_to_num(proj) - problem.target) ** 2).sum(-1)
            sqrt_w = np.sqrt(weight / np.sqrt(1 + err2 / HUBER_PX ** 2))  # pseudo-Huber
            terms, _ = self._terms(x, problem, sqrt_w, True)
            stats["evaluations"] += 1
            jtj, jtr, cost = _normal_equations(terms, idx)
            scaling = np.diag(jtj.diagonal()) + 1e-6 * np.eye(len(idx))
            improved = False
            for _attempt in range(10):
                step = np.linalg.solve(jtj + damping * scaling, -jtr)
                step *= self._step_scale(step, idx)
                trial = x.copy()
                trial[idx] += step
                trial_terms, proj_t = self._terms(trial, problem, sqrt_w, False)
                stats["evaluations"] += 1
                gain = cost - sum(float(t.residuals @ t.residuals) for t in trial_terms)
                predicted = -2.0 * float(step @ jtr) - float(step @ jtj @ step)
                if gain > 0:  # Nielsen's damping update, by how well the model predicted it
                    rho = gain / max(predicted, 1e-300)
                    damping *= max(1 / 3, 1 - (2 * rho - 1) ** 3)
                    damping, grow = max(damping, 1e-9), 2.0
                    x, proj, improved = trial, proj_t, True
                    break
                damping, grow = damping * grow, grow * 2
            stats["iterations"] += 1
            if not improved or float(np.abs(step).max()) < 1e-6:
                break
        return x


    def _step_scale(self, step: np.ndarray, idx: np.ndarray) -> float:
        """Shrinks a step that turns any joint by more than `MAX_ROTATION_STEP`: the
        linearization of a rotation is poor beyond that, and weakly observed rotations (a
        finger's twist) otherwise take steps of a radian that fail the cost test."""
        full = np.zeros(self.layout["right_hand_pose"][0].stop)
        full[idx] = step
        turns = np.linalg.norm(full[self.pose_columns].reshape(-1, 3), axis=1)
        return min(1.0, MAX_ROTATION_STEP / max(float(turns.max()), 1e-12))


@dataclass(frozen=True)
class _Term:
    """A block of residuals and their Jacobian: dense [R, N], or diagonal (`diagonal` [N]:
    residual i depends on variable i only) for the quadratic priors."""
    residuals: np.ndarray
    jacobian: np.ndarray | None
    diagonal: np.ndarray | None = None


def _normal_equations(terms: list[_Term], idx: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, float]:
    """(J^T J, J^T r) over the free variables idx, and the cost sum r^2."""
    n = len(idx)
    jtj, jtr, cost = np.zeros((n, n)), np.zeros(n), 0.0
    for t in terms:
        cost += float(t.residuals @ t.residuals)
        if t.diagonal is not None:
            jtj[np.arange(n), np.arange(n)] += t.diagonal[idx] ** 2
            jtr += t.diagonal[idx] * t.residuals[idx]
        elif t.residuals.size:
            j = t.jacobian[:, idx]
            jtj += j.T @ j
            jtr += j.T @ t.residuals
    return jtj, jtr, cost


@dataclass(frozen=True)
class _Problem:
    """What one frame's fit holds fixed."""
    camera: WebcamCamera
    target: np.ndarray               # [K, 2] px
    scale: float                     # px per residual unit
    previous: np.ndarray | None      # [N] the previous frame's variables (warm starts)
    # Relative-depth pairs: (keypoint [D], its reference [D], target z - z_ref px [D],
    # sqrt weight [D]), or None.
    depth_pairs: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
    world_pairs: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
    # Bone directions: (from rows [B], to rows [B], target unit directions [B, 3], sqrt
    # weight [B]), or None.
    direction_pairs: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None


@dataclass(frozen=True)
class _Projected:
    pixels: np.ndarray                  # [K, 2]
    depth: np.ndarray                   # [K] m in front of the camera
    points: np.ndarray                  # [K, 3] camera frame
    d_pixels: np.ndarray | None = None  # [K, 2, N]
    d_depth: np.ndarray | None = None   # [K, N]
    d_points: np.ndarray | None = None  # [K, 3, N]


def reprojection_errors(proj: np.ndarray, obs: Observations) -> dict[str, float]:
    """Mean pixel distance per group over the landmarks used (NaN for an unseen group)."""
    out = {}
    for group, sl in cor.GROUP_SLICES.items():
        used = obs.weights[sl] > 0
        d = np.linalg.norm(proj[sl][used] - obs.pixels[sl][used], axis=-1)
        out[group] = float(d.mean()) if used.any() and np.isfinite(d).all() else float("nan")
    return out
