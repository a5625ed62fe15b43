"""One frame's fit: SMPL-X parameters whose keypoints reproject onto the observed landmarks.

Minimized by Levenberg-Marquardt (bounded iterations; the Jacobian by forward differences in
one batched model pass, which the cut-down keypoint model makes cheap):

    sum_k w_k * pseudo_huber(|project(keypoint_k) - landmark_k|) / s^2   (data, s = max(W,H)/100)
  + pose prior (spine, neck, head, collars toward rest; arms and hands weakly toward neutral)
  + joint limits (hinge on each rotation's angle beyond `JOINT_LIMITS_DEG`)
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
from torch import Tensor

from ...body.models import SMPLXModel
from ...body.skeleton import JOINT, LEFT_HAND_JOINTS, SMPLX_JOINT_NAMES
from ...synth.motion import EXPRESSION_LIMIT, JOINT_LIMITS_DEG, RELAXED_ARMS
from . import correspondence as cor
from .camera import WebcamCamera
from .keypoints import BodyKeypoints
from .observations import Observations

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
HAND_PRIOR = 0.05
EXPRESSION_PRIOR = 0.02
GLOBAL_PRIOR = 0.5     # the body mostly faces the camera
LIMIT_WEIGHT = 100.0
# Per keypoint group: a weight on its data term (the contour is loosely defined on any face).
GROUP_WEIGHT = {"face": 1.0, "left_hand": 1.0, "right_hand": 1.0, "pose": 2.0}
CONTOUR_WEIGHT = 0.3
HUBER_PX = 8.0         # pseudo-Huber knee: larger errors grow linearly (outlier landmarks)
NEUTRAL_DEPTH_M = 0.8  # a webcam subject's distance when nothing tells otherwise
FD_STEP = 1e-5        # forward-difference step of the Jacobian (radians, metres, coeffs)


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
    dtype: torch.dtype = torch.float64


@dataclass
class FitResult:
    params: dict[str, np.ndarray]           # smplx names, per frame (no batch axis)
    keypoints_px: np.ndarray                # [K, 2] the fitted model's reprojection
    reprojection_px: dict[str, float]       # group -> mean px error over used landmarks
    loss: float
    ms: float
    stats: dict = field(default_factory=dict)


def _free_joint_rows() -> list[int]:
    return [JOINT[n] - 1 for n in FREE_BODY_JOINTS]


def _limits_rad(names: list[str]) -> Tensor:
    return torch.tensor([math.radians(JOINT_LIMITS_DEG.get(n, 180.0)) for n in names])


class FrameFitter:
    """Fits single frames; holds the model keypoints and the camera-independent priors."""

    def __init__(self, model: SMPLXModel, betas: np.ndarray | None = None,
                 config: FitConfig | None = None) -> None:
        self.config = config or FitConfig()
        dt = self.config.dtype
        self.keypoints = BodyKeypoints(model, dtype=dt)
        self.num_expression = model.num_expression
        n_betas = self.keypoints.model.num_betas
        b = np.zeros(n_betas) if betas is None else np.asarray(betas, dtype=np.float64)
        self.betas = torch.as_tensor(np.pad(b[:n_betas], (0, max(0, n_betas - b.size))),
                                     dtype=dt)[None]
        self.neutral = neutral_params(model)
        self.rows = _free_joint_rows()
        self.body_prior = torch.tensor([BODY_PRIOR.get(n, ARM_PRIOR) for n in FREE_BODY_JOINTS],
                                       dtype=dt)
        self.body_limits = _limits_rad(list(FREE_BODY_JOINTS)).to(dt)
        hand_names = [SMPLX_JOINT_NAMES[j].removeprefix("left_") for j in LEFT_HAND_JOINTS]
        self.hand_limits = _limits_rad([f"left_{n}" for n in hand_names]).to(dt)
        self.jaw_limit = math.radians(JOINT_LIMITS_DEG["jaw"])
        weights = np.ones(cor.NUM_KEYPOINTS)
        weights[cor.FACE_SLICE][list(cor.IBUG_CONTOUR)] = CONTOUR_WEIGHT
        for group, sl in cor.GROUP_SLICES.items():
            weights[sl] *= GROUP_WEIGHT[group]
        self.group_weights = torch.as_tensor(weights, dtype=dt)
        self.body_rest = torch.as_tensor(self.neutral["body_pose"][self.rows], dtype=dt)
        self.layout = self._layout()
        core = np.zeros(cor.NUM_KEYPOINTS)
        core[cor.FACE_SLICE] = 1.0
        arms = core.copy()
        core[cor.POSE_SLICE.start + np.array(CORE_POSE_LANDMARKS)] = 1.0
        arms[cor.POSE_SLICE.start + np.array(ARM_POSE_LANDMARKS)] = 1.0
        for sl in (cor.LEFT_HAND_SLICE, cor.RIGHT_HAND_SLICE):
            arms[sl.start + np.array(HAND_PALM_LANDMARKS)] = 1.0
        self.stage_masks = {"core": torch.as_tensor(core, dtype=dt),
                            "arms": torch.as_tensor(arms, dtype=dt)}
        temporal = np.full(sum(sl.stop - sl.start for sl, _ in self.layout.values()),
                           self.config.temporal_weight)
        temporal[self.layout["transl"][0]] *= 100.0  # 1 cm weighs as 0.1 rad
        self.temporal_sqrt = torch.as_tensor(np.sqrt(temporal), dtype=dt)

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

    def unpack(self, x: Tensor) -> dict[str, Tensor]:
        """Free variables [B, N] -> batched SMPL-X parameters."""
        b = x.shape[0]
        get = {name: x[:, sl].reshape(b, *shape) for name, (sl, shape) in self.layout.items()}
        body = x.new_zeros(b, 21, 3)
        body[:, self.rows] = get.pop("body")
        zeros = x.new_zeros(b, 3)
        return {**get, "betas": self.betas.expand(b, -1), "body_pose": body,
                "leye_pose": zeros, "reye_pose": zeros}

    def to_params(self, x: np.ndarray) -> dict[str, np.ndarray]:
        p = self.unpack(torch.as_tensor(x, dtype=self.config.dtype)[None])
        return {k: t[0].double().numpy().copy() for k, t in p.items() if k != "betas"}

    # -- the objective: a residual vector, cost = sum of squares -------------------------------

    def project(self, params: dict[str, Tensor], camera: WebcamCamera) -> Tensor:
        """[B, K, 2] pixels."""
        return camera.project(self.keypoints(params))

    def _prior_residuals(self, x: Tensor, previous: Tensor | None) -> Tensor:
        """[B, P] residuals of the priors, bounds and temporal term."""
        lay = self.layout
        b = x.shape[0]
        body = x[:, lay["body"][0]].reshape(b, -1, 3)
        hands = x[:, lay["left_hand_pose"][0].start:lay["right_hand_pose"][0].stop]
        hands = hands.reshape(b, 30, 3)
        expr = x[:, lay["expression"][0]]
        jaw = x[:, lay["jaw_pose"][0]]
        angle = lambda aa: torch.sqrt((aa ** 2).sum(-1) + 1e-12)  # noqa: E731
        limit = math.sqrt(LIMIT_WEIGHT)
        parts = [
            (self.body_prior.sqrt()[:, None] * (body - self.body_rest)).reshape(b, -1),
            math.sqrt(GLOBAL_PRIOR) * x[:, lay["global_orient"][0]],
            math.sqrt(HAND_PRIOR) * hands.reshape(b, -1),
            math.sqrt(EXPRESSION_PRIOR) * expr,
            limit * torch.relu(expr.abs() - EXPRESSION_LIMIT),
            limit * torch.relu(angle(body) - self.body_limits),
            limit * torch.relu(angle(hands) - self.hand_limits.repeat(2)),
            limit * torch.relu(angle(jaw) - self.jaw_limit)[:, None],
        ]
        if previous is not None:
            parts.append(self.temporal_sqrt * (x - previous))
        return torch.cat(parts, dim=1)

    def _residuals(self, x: Tensor, camera: WebcamCamera, target: Tensor, sqrt_w: Tensor,
                   scale: float, previous: Tensor | None) -> tuple[Tensor, Tensor]:
        """([B, M] residuals, [B, K, 2] projections) for free variables [B, N]."""
        proj = self.project(self.unpack(x), camera)
        data = (sqrt_w[None, :, None] * (torch.nan_to_num(proj) - target) / scale)
        return torch.cat([data.reshape(x.shape[0], -1),
                          self._prior_residuals(x, previous)], dim=1), proj

    # -- fitting -------------------------------------------------------------------------------

    def initial_placement(self, start: dict[str, np.ndarray], obs: Observations,
                          camera: WebcamCamera) -> np.ndarray:
        """A transl that puts the observed landmarks' model counterparts at the right scale and
        place, from their spread and centroid (the model at `start`, transl 0)."""
        used = obs.weights > 0
        x = torch.as_tensor(self.pack({**start, "transl": np.zeros(3)}), dtype=self.config.dtype)
        with torch.no_grad():
            model_pts = self.keypoints(self.unpack(x[None]))[0].double().numpy()
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
            start: dict[str, np.ndarray] | None = None) -> FitResult:
        """Fit one frame. `start`: the previous frame's parameters (a warm start), or None."""
        t0 = time.perf_counter()
        warm = start is not None
        start = dict(start) if warm else dict(self.neutral)
        if not warm:
            start["transl"] = self.initial_placement(start, obs, camera)
        dt = self.config.dtype
        target = torch.as_tensor(obs.pixels, dtype=dt)
        weight = torch.as_tensor(obs.weights, dtype=dt) * self.group_weights
        weight = torch.where(self.keypoints.available, weight, 0.0)
        scale = max(camera.width, camera.height) / 100.0
        x = torch.as_tensor(self.pack(start), dtype=dt)
        previous = x.clone() if warm else None
        stats = {"iterations": 0, "evaluations": 0}
        if not warm:  # coarse to fine: place the head and torso first, then the limbs
            n = self.config.placement_iterations
            for names, mask in ((PLACEMENT_VARIABLES, "core"), (CORE_VARIABLES, "core"),
                                (ARM_VARIABLES, "arms")):
                x = self._levenberg_marquardt(x, self._free_mask(names), n, camera, target,
                                              weight * self.stage_masks[mask], scale,
                                              previous, stats)
        x = self._levenberg_marquardt(
            x, np.ones(x.numel(), dtype=bool),
            self.config.warm_iterations if warm else self.config.cold_iterations,
            camera, target, weight, scale, previous, stats)
        with torch.no_grad():
            r, proj = self._residuals(x[None], camera, target, weight.sqrt(), scale, previous)
        proj_np = proj[0].double().numpy()
        return FitResult(self.to_params(x.numpy()), proj_np, reprojection_errors(proj_np, obs),
                         float((r ** 2).sum()), (time.perf_counter() - t0) * 1e3, stats)

    @torch.no_grad()
    def _levenberg_marquardt(self, x: Tensor, free: np.ndarray, iterations: int,
                             camera: WebcamCamera, target: Tensor, weight: Tensor,
                             scale: float, previous: Tensor | None, stats: dict) -> Tensor:
        """Levenberg-Marquardt on the free entries of x; the Jacobian by batched forward
        differences (one model pass of batch N + 1), the robust loss by reweighting."""
        idx = torch.as_tensor(np.flatnonzero(free))
        n = len(idx)
        damping = 1e-3
        for _ in range(iterations):
            r0, proj = self._residuals(x[None], camera, target, weight.sqrt(), scale, previous)
            # Pseudo-Huber as iteratively reweighted least squares: weights fixed per step.
            err2 = ((torch.nan_to_num(proj[0]) - target) ** 2).sum(-1)
            sqrt_w = (weight / torch.sqrt(1 + err2 / HUBER_PX ** 2)).sqrt()
            r0, _ = self._residuals(x[None], camera, target, sqrt_w, scale, previous)
            batch = x.repeat(n, 1)
            batch[torch.arange(n), idx] += FD_STEP
            r, _ = self._residuals(batch, camera, target, sqrt_w, scale, previous)
            stats["evaluations"] += n + 1
            jac = ((r - r0) / FD_STEP).T  # [M, n]
            res = r0[0]
            jtj, jtr = jac.T @ jac, jac.T @ res
            cost = float(res @ res)
            improved = False
            eye = torch.eye(n, dtype=x.dtype)
            for _attempt in range(10):
                a = jtj + damping * (torch.diag(jtj.diagonal()) + 1e-6 * eye)
                step = torch.linalg.solve(a, -jtr)
                trial = x.clone()
                trial[idx] += step
                rt, _ = self._residuals(trial[None], camera, target, sqrt_w, scale, previous)
                stats["evaluations"] += 1
                if float((rt ** 2).sum()) < cost:
                    x, damping, improved = trial, max(damping / 3, 1e-7), True
                    break
                damping *= 4
            stats["iterations"] += 1
            if not improved or float(step.abs().max()) < 1e-6:
                break
        return x


def reprojection_errors(proj: np.ndarray, obs: Observations) -> dict[str, float]:
    """Mean pixel distance per group over the landmarks used (NaN for an unseen group)."""
    out = {}
    for group, sl in cor.GROUP_SLICES.items():
        used = obs.weights[sl] > 0
        d = np.linalg.norm(proj[sl][used] - obs.pixels[sl][used], axis=-1)
        out[group] = float(d.mean()) if used.any() and np.isfinite(d).all() else float("nan")
    return out
